"""Bench group `rl`: control steps a second of the batched RL environment `CrossGap-v0`."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from hil.benches import BenchRow, time_per_call

BATCH_N = 4096


def collect(quick: bool) -> Iterator[BenchRow]:
    """`rl_env_steps_per_s`: `CrossGapVecEnv.step` at N = 4096 under the hover-ish action of the
    imitation policy's order (physics 10 x 1 ms with the FC's inner loop, world check, reward, the
    29 inputs, restarts), control steps (one vehicle, 10 ms) a second; `rl_env_link_steps_per_s` the
    same with the observation through the link model (`EnvConfig.link`)."""
    # (torch and gymnasium, the optional 'learn' extra: imported only when this bench runs)
    from hil.rl.env import CrossGapVecEnv, EnvConfig
    from hil.rl.link_observe import LinkModel

    rng = np.random.default_rng(0)
    actions = np.zeros((64, BATCH_N, 3))
    actions[..., 0:2] = rng.normal(0.0, 0.05, (64, BATCH_N, 2))
    actions[..., 2] = 8.8 + rng.normal(0.0, 0.3, (64, BATCH_N))
    for name, link, what in (("rl_env_steps_per_s", None, "observing the true state"),
                             ("rl_env_link_steps_per_s", LinkModel(), "observing through the link model")):
        env = CrossGapVecEnv(BATCH_N, EnvConfig(pool_size=32 if quick else 128, seed=0, link=link))
        env.reset()
        k = [0]

        def one_step(env: CrossGapVecEnv = env, k: list[int] = k) -> None:
            env.step(actions[k[0] & 63])
            k[0] += 1

        per_step = time_per_call(one_step, min_time_s=0.5 if quick else 3.0)
        yield BenchRow(name, BATCH_N / per_step, "steps/s",
                       f"CrossGapVecEnv.step, N={BATCH_N}, control steps of 10 ms (10 physics steps each), "
                       f"{what}")
