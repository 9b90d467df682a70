"""The real-time loop: the emulator side follows the wall clock, the onboard program runs on its own
(a real TX2 on a USB-serial adapter, or a pilot watching); faults act at their wall-clock times."""

from __future__ import annotations

import time
from collections.abc import Callable

from hil.runner.emulator_side import EmulatorSide
from hil.runner.lockstep import LoopReport, apply_process_faults, note_divergence
from hil.runner.onboard_side import InProcessOnboard, OnboardSide

POLL_S = 0.001  # the loop wakes at least this often (s)


def run_realtime(
    emu: EmulatorSide,
    onboard: OnboardSide,
    duration_s: float,
    progress: Callable[[float], None] | None = None,
) -> LoopReport:
    """Fly ``duration_s`` seconds of wall time; returns what the loop saw."""
    rep = LoopReport()
    faults = emu.faults
    wall0 = time.perf_counter()
    next_progress = 0.5
    while True:
        t = time.perf_counter() - wall0
        if t > duration_s:
            break
        emu.advance_to(t)
        if emu.diverged_s is not None:
            note_divergence(rep, emu)
            break
        rep.ticks += 1
        if faults.waiting:  # faults timed after a mission event
            emu.mission_events(onboard.new_events(t))
        apply_process_faults(rep, onboard, faults, t)
        if isinstance(onboard, InProcessOnboard):
            onboard.step_realtime(t)
        emu.wire.read_onboard(POLL_S)
        if progress is not None and t >= next_progress:
            progress(t)
            next_progress = t + 0.5
    if rep.ended_early is None:
        emu.advance_to(duration_s)
    rep.wall_loop_s = time.perf_counter() - wall0
    return rep
