"""The lockstep loop: simulated time advances tick by tick, each tick only once the onboard program has
answered it (or has been declared dead), so a run is faster than real time and deterministic.

Per tick at time t: the emulator side runs up to t (physics, FC, mocap, links), the runner writes the
tick's mocap frames, then the FC's frames and the TIMESYNC tick (tc1 = 0, ts1 = t in ns) on the command
link; the onboard program reads everything, acts, writes its outputs and answers TIMESYNC(tc1 = ts1 = t).
Its outputs count as handed to the command link at t + the onboard computer's compute time (one tick by
default, the scenario's ``onboard_compute_ms``) and reach the FC after their modelled wire time. The
emulator side runs on to that time while the onboard program works, so with the default the two
processes work on the same tick at once. A wall-clock guard declares a silent onboard program dead so
the run goes on and the FC's failsafe can act. Faults on the process: killed at a tick, stalled (not
ticked) over an interval.

The loop's wall time (and so the real-time factor) starts at the first answered tick: a new onboard
process first imports its libraries and opens its ports (`LoopReport.startup_wall_s`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from hil.link.mavlink import encode_frame, mav
from hil.runner.emulator_side import FC_SYSTEM_ID, EmulatorSide
from hil.runner.faults import FaultSchedule
from hil.runner.onboard_side import OnboardSide

DEFAULT_TICK_S = 0.01  # one tick per onboard control period (100 Hz)
DEFAULT_GUARD_S = 3.0  # wall time without an answer before the onboard program counts as dead
STARTUP_GUARD_S = 60.0  # the first answer may wait for a process to start
_TIMESYNC = mav.MAVLink_timesync_message.unpacker
RESEND_S = 1.0  # a tick not answered within this wall time is sent again (lost on a fresh port)
#: until the first answer: a new process opening its port drops what was written before (pyserial
#: flushes on open), so the first tick is repeated often; the program acts on a repeat only once
STARTUP_RESEND_S = 0.02


@dataclass
class LoopReport:
    """What the loop saw: ticks, onboard status changes (sim s, text) and wall times (s).

    ``wall_loop_s`` is the wall time of the loop proper, which covers ``loop_sim_s`` of simulated time:
    in lockstep it starts once the first tick is answered, so the onboard program's start-up (a new
    process importing its libraries) is in ``startup_wall_s`` and not in the real-time factor."""

    ticks: int = 0
    answered: int = 0
    events: list[dict[str, object]] = field(default_factory=list)
    wall_loop_s: float = 0.0
    onboard_exit_s: float | None = None
    startup_wall_s: float = 0.0
    loop_sim_s: float | None = None  # None: the whole run


def apply_process_faults(
    rep: LoopReport, onboard: OnboardSide, faults: FaultSchedule, kill_s: float | None, t: float
) -> None:
    """Kill, stall or resume the onboard program as the fault schedule says at ``t`` (s), noting it."""
    if onboard.alive and kill_s is not None and t >= kill_s:
        onboard.kill()
        rep.events.append({"time_s": t, "source": "runner", "text": "onboard program killed"})
    stalled = faults.any_active("onboard_stalled", t)
    if stalled and onboard.alive and not onboard.paused:
        onboard.pause()
        rep.events.append({"time_s": t, "source": "runner", "text": "onboard program stalled"})
    elif not stalled and onboard.paused:
        onboard.resume()
        rep.events.append({"time_s": t, "source": "runner", "text": "onboard program resumed"})


def run_lockstep(
    emu: EmulatorSide,
    onboard: OnboardSide,
    duration_s: float,
    *,
    tick_s: float = DEFAULT_TICK_S,
    compute_s: float | None = None,
    guard_s: float = DEFAULT_GUARD_S,
    progress: Callable[[float], None] | None = None,
) -> LoopReport:
    """Fly ``duration_s`` of sim time in lockstep; returns what the loop saw.

    ``compute_s`` (s, 0..``tick_s``; None: ``tick_s``) is the onboard computer's modelled compute time:
    its outputs for the tick at t are handed to the command link at t + ``compute_s``. Until then the
    emulator side runs on, so with one tick (the default) the two sides work on the same tick at once.
    """
    compute = tick_s if compute_s is None else compute_s
    if not 0.0 <= compute <= tick_s + 1e-12:
        raise ValueError(
            f"onboard compute time must be 0..{tick_s * 1e3:g} ms (one tick), got {compute * 1e3:g} ms"
        )
    rep = LoopReport()
    faults = emu.faults
    kill_s = faults.killed_at_s()
    n_ticks = round(duration_s / tick_s)
    wall0 = loop0 = time.perf_counter()
    t_loop0 = 0.0
    next_progress = wall0 + 0.5
    first = True
    wire = emu.wire
    wire.hold_output = True  # the FC's frames go out with the tick, in one write
    emu.hold_mocap = True  # and the mocap frames just before it: never while the onboard reads a tick
    pending: float | None = None  # the tick whose outputs are still being computed
    for k in range(1, n_ticks + 1):  # no tick at 0: its answer TIMESYNC(0, 0) would read as a request
        t = k * tick_s
        if pending is not None:
            t_out = min(pending + compute, t)
            emu.advance_to(t_out)
            _collect(rep, emu, onboard, pending, t_out, guard_s)
            pending = None
        if emu.time_s < t - 1e-12:
            emu.advance_to(t)
        rep.ticks += 1
        apply_process_faults(rep, onboard, faults, kill_s, t)
        emu.mocap_link.flush()
        if onboard.alive and not onboard.paused:
            if onboard.exited():
                _note_exit(rep, onboard, t)
            else:
                _send_tick(emu, t)
                onboard.service()
                emu.recorder.flush()  # the tick's checks and time-series rows, while the onboard works
                pending = t
                if first:  # wait for the new process, then the loop proper starts
                    _collect(rep, emu, onboard, t, t + compute, STARTUP_GUARD_S, STARTUP_RESEND_S)
                    pending = None
                    loop0, t_loop0 = time.perf_counter(), t
                    first = False
        wire.flush()  # frames of a tick not sent (onboard dead or stalled) go out as they are
        if progress is not None and time.perf_counter() >= next_progress:
            progress(t)
            next_progress = time.perf_counter() + 0.5
    if pending is not None:  # the last tick's answer: the program has acted on it before the run ends
        _collect(rep, emu, onboard, pending, pending + compute, guard_s)
    rep.startup_wall_s = loop0 - wall0
    rep.wall_loop_s = time.perf_counter() - loop0
    rep.loop_sim_s = n_ticks * tick_s - t_loop0
    return rep


def _note_exit(rep: LoopReport, onboard: OnboardSide, t: float) -> None:
    onboard.alive = False
    rep.onboard_exit_s = t
    rep.events.append({"time_s": t, "source": "runner", "text": "onboard program exited"})


def _tick_frame(t: float) -> bytes:
    """TIMESYNC(tc1 = 0, ts1 = t in ns): the harness's own frame, sequence number always 0."""
    return encode_frame(
        mav.MAVLINK_MSG_ID_TIMESYNC,
        _TIMESYNC.pack(0, round(t * 1e9)),
        0,
        FC_SYSTEM_ID,
        mav.MAV_COMP_ID_AUTOPILOT1,
    )


def _send_tick(emu: EmulatorSide, t: float) -> None:
    emu.wire.send_sync(_tick_frame(t))


def _collect(
    rep: LoopReport,
    emu: EmulatorSide,
    onboard: OnboardSide,
    t: float,
    stamp_s: float,
    guard_s: float,
    resend_s: float = RESEND_S,
) -> None:
    """Wait for the answer to the tick at ``t``, its outputs handed to the link at ``stamp_s`` (s); an
    onboard program silent for ``guard_s`` (wall) is declared dead."""
    if not (onboard.alive and not onboard.paused):
        return  # killed or stalled since the tick was sent: no answer will come
    if _await_answer(emu, onboard, t, stamp_s, guard_s, resend_s):
        rep.answered += 1
    elif onboard.exited():
        _note_exit(rep, onboard, t)
    else:
        onboard.kill()
        rep.events.append(
            {
                "time_s": t,
                "source": "runner",
                "text": f"onboard program silent for {guard_s:g} s (wall): declared dead",
            }
        )


def _await_answer(
    emu: EmulatorSide, onboard: OnboardSide, t: float, stamp_s: float, guard_s: float, resend_s: float
) -> bool:
    """Read the onboard program's outputs until it answers the tick at ``t``; False when no answer came
    within ``guard_s`` (wall)."""
    wire = emu.wire
    ns = round(t * 1e9)
    deadline = time.monotonic() + guard_s
    resend_at = time.monotonic() + resend_s
    answers = wire.answers
    while True:
        if answers:
            done = ns in answers
            answers.clear()
            if done:
                return True
        now = time.monotonic()
        if now >= deadline:
            return False
        if now >= resend_at:
            wire.send_sync(_tick_frame(t))
            resend_at = now + resend_s
        # the process is asked whether it has exited only when it has been silent for a while
        wait = min(0.05, resend_s, max(0.0, deadline - now))
        if not wire.read_onboard(wait, stamp_s=stamp_s) and onboard.exited():
            wire.read_onboard(0.0, stamp_s=stamp_s)
            return ns in answers
        onboard.service()
