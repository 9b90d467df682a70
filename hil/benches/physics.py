"""Bench group `physics`: native single-vehicle and batched physics step rates."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from emulator.physics.native import BatchPhysics, NativeBackend, hover_state
from emulator.profile import load_profile
from hil.benches import BenchRow, time_per_call

BATCH_N = 4096


def collect(quick: bool) -> Iterator[BenchRow]:
    """`physics_steps_per_s` (one vehicle, one Python call per 1 ms step) and `batch_env_steps_per_s`."""
    profile = load_profile("n3_tx2")
    min_time_s = 0.3 if quick else 1.5

    single = NativeBackend(profile, dt_s=0.001)
    single.reset(hover_state(profile, (0.0, 0.0, 1e6)))  # high up: no ground contact for the whole run
    cmd = np.full(4, profile.hover_throttle)
    rng = np.random.default_rng(0)
    cmds = profile.hover_throttle + rng.uniform(-0.01, 0.01, (1024, 4))  # a fresh command each step
    k = [0]

    def one_step() -> None:
        cmd[:] = cmds[k[0] & 1023]
        k[0] += 1
        single.step(cmd)

    per_step = time_per_call(one_step, min_time_s=min_time_s)
    yield BenchRow(
        "physics_steps_per_s", 1.0 / per_step, "steps/s",
        "NativeBackend.step, one call per 1 ms step with a new motor command",
    )

    batch = BatchPhysics(profile, BATCH_N, dt_s=0.001)
    batch.reset(hover_state(profile, (0.0, 0.0, 1e6)))
    batch_cmd = np.full((BATCH_N, 4), profile.hover_throttle)
    inner = 10

    per_call = time_per_call(lambda: batch.step(batch_cmd, inner), min_time_s=min_time_s)
    yield BenchRow(
        "batch_env_steps_per_s", BATCH_N * inner / per_call, "steps/s",
        f"BatchPhysics N={BATCH_N}, {inner} steps a call, vehicle-steps",
    )
