"""The real-time loop: the emulator side follows the wall clock, the onboard program runs on its own
(a real TX2 on a USB-serial adapter, or a pilot watching).

One verdict whatever the clock: a program started cold takes wall time to start (about 0.7 s to its
first frame) that lockstep does not see, so in real time the run lasts ``duration_s`` from the onboard
program's first frame on the command link, and the faults given in sim seconds count from there too
(in lockstep the first frame comes with the first tick, 10 ms in). The loop also measures how well it
kept real time (`PacingStats`: its lateness, the steps it ran late to catch up) and the setpoint and
mocap streams as the wire saw them (rates, longest gaps): `LoopReport.realtime`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from emulator.loops.realtime_runner import WireWatch
from hil.link.clock import PacingStats
from hil.runner.emulator_side import CHECK_OVERRUN_S, EmulatorSide
from hil.runner.lockstep import RECORD_BATCH, LoopReport, apply_process_faults, note_divergence
from hil.runner.mission import CONTACT_EVENT
from hil.runner.onboard_side import InProcessOnboard, OnboardSide, ProcessOnboard

POLL_S = 0.001  # the loop wakes at least this often (s)


#: the longest the loop waits for the onboard program's first frame before flying ``duration_s`` anyway
CONTACT_WAIT_S = 10.0


def run_realtime(
    emu: EmulatorSide,
    onboard: OnboardSide,
    duration_s: float,
    progress: Callable[[float], None] | None = None,
    compute_s: float = 0.0,
    started_monotonic_s: float | None = None,
) -> LoopReport:
    """Fly ``duration_s`` seconds of wall time from the onboard program's first frame; returns what the
    loop saw, its real-time health in ``realtime``. ``compute_s`` (s) is the onboard computer's modelled
    compute time, as in lockstep: its outputs reach the link that long after the program wrote them (the
    program runs on the harness's machine, faster than the TX2 it stands for). ``started_monotonic_s``
    (`time.monotonic`, s) is when the program was started, the loop's time zero, so its start-up counts
    however long the harness took between spawning it and entering this loop (default: now)."""
    rep = LoopReport()
    emu.wire.compute_s = compute_s
    faults = emu.faults
    faults.count_from(CONTACT_EVENT)
    pacing = PacingStats(POLL_S, emu.vehicle.dt_s)
    streams = WireWatch(emu.server, emu.mocap)
    wire = emu.wire
    contact_s: float | None = None
    end_s = CONTACT_WAIT_S + duration_s  # until the first frame
    # (the clock the onboard program stamps its events with, too)
    wall0 = time.monotonic() if started_monotonic_s is None else started_monotonic_s
    if isinstance(onboard, ProcessOnboard):
        onboard.harness_zero_monotonic_s = wall0
    next_progress = 0.5
    while True:
        t = time.monotonic() - wall0
        if contact_s is not None:  # (a process starting beside the loop slows it: that is no flight)
            pacing.wake(t)
        if contact_s is None and t > CONTACT_WAIT_S:
            break
        if t > end_s:  # the run's duration is flown: on while a check's window is still open
            until = emu.checks_open_until_s()
            if until is None or t > min(until, end_s + CHECK_OVERRUN_S):
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
        if wire.read_onboard(POLL_S) and contact_s is None:
            contact_s, end_s = t, t + duration_s
            rep.events.append({"time_s": t, "source": "runner", "text": "onboard program's first frame"})
            emu.mission_events([{"event": CONTACT_EVENT, "t_s": t}])
        emu.recorder.flush(RECORD_BATCH)  # (checks and rows in batches, as in lockstep)
        streams.poll(t)
        if progress is not None and t >= next_progress:
            progress(t)
            next_progress = t + 0.5
    if contact_s is None:
        rep.events.append({"time_s": t, "source": "runner",
                           "text": f"no frame from the onboard program in {CONTACT_WAIT_S:g} s (wall)"})
        rep.ended_early = rep.ended_early or "the onboard program never sent a frame"
    elif rep.ended_early is None:
        emu.advance_to(max(end_s, emu.time_s))
    rep.wall_loop_s = time.monotonic() - wall0
    rep.realtime = {
        "contact_s": None if contact_s is None else round(contact_s, 4),
        "loop": pacing.as_dict(),
        **streams.as_dict(),
    }
    return rep
