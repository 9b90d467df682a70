"""Bench rows for the JSBSim physics backend: steps per second the way the FC emulator steps it."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from emulator.physics import make_backend
from emulator.physics.native import hover_state
from emulator.profile import load_profile
from hil.benches import BenchRow, time_per_call


def collect(quick: bool) -> Iterator[BenchRow]:
    """``jsbsim_steps_per_s``: one ``step(cmd)`` per 1 ms step with a fresh motor command each call."""
    profile = load_profile("n3_tx2")
    backend = make_backend("jsbsim", profile, dt_s=0.001)  # a clear error if jsbsim is missing
    try:
        backend.reset(hover_state(profile, (0.0, 0.0, 50.0)))
        rng = np.random.default_rng(0)
        hover = profile.hover_throttle
        cmds = hover + rng.uniform(-0.02, 0.02, size=(1024, 4))
        i = 0

        def one_step() -> None:
            nonlocal i
            backend.step(cmds[i & 1023])
            i += 1

        per_call_s = time_per_call(one_step, min_time_s=0.3 if quick else 1.0)
    finally:
        backend.close()
    yield BenchRow(
        "jsbsim_steps_per_s",
        1.0 / per_call_s,
        "steps/s",
        "n3_tx2 at 1 kHz, one step(cmd) per call with a new throttle vector (rotor model in Python)",
    )
