"""Bench group `rl`: control steps a second of the batched RL environment `CrossGap-v0`, beside the
fused flight kernel it calls, measured alone on the same rows."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from hil.benches import BenchRow, time_per_call

if TYPE_CHECKING:
    from hil.rl.env import CrossGapVecEnv

BATCH_N = 4096


def collect(quick: bool) -> Iterator[BenchRow]:
    """`rl_env_steps_per_s`: `CrossGapVecEnv.step` at N = 4096 under the hover-ish action of the
    imitation policy's order (physics 10 x 1 ms with the FC's inner loop, world check, reward, the
    29 inputs, restarts), control steps (one vehicle, 10 ms) a second; `rl_flight_kernel_steps_per_s`
    the fused flight kernel alone (`emulator.loops.batched_steps.fly_targets`: the FC's inner loop, the
    physics and the world check, 10 x 1 ms) on the same rows in the same units, so that the two rates
    say what the environment's own work costs; `rl_env_link_steps_per_s` the environment with the
    observation through the link model (`EnvConfig.link`)."""
    # (torch and gymnasium, the optional 'learn' extra: imported only when this bench runs)
    from hil.rl.env import CrossGapVecEnv, EnvConfig
    from hil.rl.link_observe import LinkModel

    rng = np.random.default_rng(0)
    actions = np.zeros((64, BATCH_N, 3))
    actions[..., 0:2] = rng.normal(0.0, 0.05, (64, BATCH_N, 2))
    actions[..., 2] = 8.8 + rng.normal(0.0, 0.3, (64, BATCH_N))
    min_time_s = 0.5 if quick else 3.0
    for name, link, what in (("rl_env_steps_per_s", None, "observing the true state"),
                             ("rl_env_link_steps_per_s", LinkModel(), "observing through the link model")):
        env = CrossGapVecEnv(BATCH_N, EnvConfig(pool_size=32 if quick else 128, seed=0, link=link))
        env.reset()
        k = [0]

        def one_step(env: CrossGapVecEnv = env, k: list[int] = k) -> None:
            env.step(actions[k[0] & 63])
            k[0] += 1

        per_step = time_per_call(one_step, min_time_s=min_time_s)
        yield BenchRow(name, BATCH_N / per_step, "steps/s",
                       f"CrossGapVecEnv.step, N={BATCH_N}, control steps of 10 ms (10 physics steps each), "
                       f"{what}")
        if link is None:
            yield _kernel_row(env, min_time_s)


def _kernel_row(env: CrossGapVecEnv, min_time_s: float) -> BenchRow:
    """`rl_flight_kernel_steps_per_s`: `CrossGapCore.fly_control_period` alone on the environment's rows
    as its last step left them, each row holding its last target (a hover-ish attitude)."""
    core = env.core
    x, aux, _ = core.physics.kernel_arrays
    start_x, start_aux = x.copy(), aux.copy()
    calls = [0]

    def one_call() -> None:
        if calls[0] % 64 == 0:  # back to the start every 64 calls (0.64 s flown): no row drifts off
            x[:] = start_x
            aux[:] = start_aux
        core.fly_control_period()
        calls[0] += 1

    per_call = time_per_call(one_call, min_time_s=min_time_s)
    return BenchRow("rl_flight_kernel_steps_per_s", core.n / per_call, "steps/s",
                    f"the fused flight kernel (fly_targets) alone on CrossGapVecEnv's rows, N={core.n}, "
                    f"control steps of 10 ms ({core.config.physics_steps} physics steps with the FC's inner "
                    f"loop, world checked once)")
