"""The lockstep loop: simulated time advances tick by tick, each tick only once the onboard program has
answered it (or has been declared dead), so a run is faster than real time and deterministic.

Per tick at time t: the emulator side runs up to t (physics, FC, mocap, links), the runner writes the
tick's mocap frames, then the FC's frames and the tick on the command link (the convention is
`hil.link.lockstep`'s); the onboard program reads everything, acts, writes its outputs and answers.
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

import math
import os
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from hil.link.lockstep import MOCAP_COUNT_MASK, RESEND_S, STARTUP_RESEND_S
from hil.runner.emulator_side import CHECK_OVERRUN_S, EmulatorSide
from hil.runner.faults import FaultSchedule
from hil.runner.onboard_side import OnboardSide

DEFAULT_TICK_S = 0.01  # one tick per onboard control period (100 Hz)
DEFAULT_GUARD_S = 3.0  # wall time without an answer before the onboard program counts as dead
STARTUP_GUARD_S = 60.0  # the first answer may wait for a process to start
#: wall time the loop polls for an answer before it sleeps: the answer usually comes within it, and a
#: sleeping CPU of a virtual machine takes tens to hundreds of microseconds to wake
SPIN_S = 1e-3
#: samples the recorder gathers before it checks and records them together (about half a second)
RECORD_BATCH = 64
#: wall time the loop waits on a silent onboard program before asking whether it has exited (the spin,
#: SPIN_S, is part of it)
EXIT_POLL_S = 2e-3


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
    ended_early: str | None = None  # why the loop stopped before the run's duration, None if it did not
    realtime: dict[str, object] | None = None  # a real-time loop's health (see `hil.runner.realtime`)


def _cores() -> list[int]:
    """The CPUs this process may run on."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def lockstep_spin_s(parallel_runs: int = 1) -> float:
    """How long each side polls for the other before it sleeps (s): `SPIN_S` while every process of the
    ``parallel_runs`` runs flying at once (two each) has a core of its own, else 0: polling would take
    the cores the other runs need (a suite of two workers on two cores runs faster asleep)."""
    return SPIN_S if 2 * max(1, parallel_runs) <= len(_cores()) else 0.0


def lockstep_cpu(worker: int | None, parallel_runs: int) -> int | None:
    """The CPU a lockstep run over ptys keeps to (itself and its onboard program, for the run) when it
    flies in worker number ``worker`` of ``parallel_runs`` that fill the cores: the two sides then hand
    each tick over without waking another CPU, which costs more than the tick's work where CPUs are
    virtual. None (left to the scheduler) with fewer runs than cores, or no worker number."""
    cores = _cores()
    if worker is None or parallel_runs < len(cores) or not hasattr(os, "sched_setaffinity"):
        return None
    return cores[worker % len(cores)]


@contextmanager
def kept_to(cpu: int | None) -> Iterator[None]:
    """This process (and what it starts meanwhile) on ``cpu`` for the block (None: as it is)."""
    if cpu is None:
        yield
        return
    before = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {cpu})
    except OSError:
        yield
        return
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def apply_process_faults(rep: LoopReport, onboard: OnboardSide, faults: FaultSchedule, t: float) -> None:
    """Kill, stall or resume the onboard program as the fault schedule says at ``t`` (s), noting it."""
    kill_s = faults.kill_s
    if onboard.alive and kill_s is not None and t >= kill_s:
        onboard.kill()
        rep.events.append({"time_s": t, "source": "runner", "text": "onboard program killed"})
    stalled = faults.stalled(t)
    if stalled and onboard.alive and not onboard.paused:
        onboard.pause()
        rep.events.append({"time_s": t, "source": "runner", "text": "onboard program stalled"})
    elif not stalled and onboard.paused:
        onboard.resume()
        rep.events.append({"time_s": t, "source": "runner", "text": "onboard program resumed"})


def process_fault_due(onboard: OnboardSide, faults: FaultSchedule, t: float) -> bool:
    """Whether `apply_process_faults` would kill, stall or resume the onboard program at ``t``."""
    kill_s = faults.kill_s
    if onboard.alive and kill_s is not None and t >= kill_s:
        return True
    return faults.stalled(t) != onboard.paused


def run_lockstep(
    emu: EmulatorSide,
    onboard: OnboardSide,
    duration_s: float,
    *,
    tick_s: float = DEFAULT_TICK_S,
    compute_s: float | None = None,
    guard_s: float = DEFAULT_GUARD_S,
    progress: Callable[[float], None] | None = None,
    spin_s: float = SPIN_S,
) -> LoopReport:
    """Fly ``duration_s`` of sim time in lockstep; returns what the loop saw.

    ``compute_s`` (s, 0..``tick_s``; None: ``tick_s``) is the onboard computer's modelled compute time:
    its outputs for the tick at t are handed to the command link at t + ``compute_s``. The emulator
    side runs on until then, so with one tick (the default) the next tick is sent before the answer to
    this one is read, and the two processes work at once. ``spin_s``: how long it polls for an answer
    before it sleeps (wall s, see `lockstep_spin_s`).
    """
    compute = tick_s if compute_s is None else compute_s
    if not 0.0 <= compute <= tick_s + 1e-12:
        raise ValueError(
            f"onboard compute time must be 0..{tick_s * 1e3:g} ms (one tick), got {compute * 1e3:g} ms"
        )
    rep = LoopReport()
    faults = emu.faults
    n_ticks = round(duration_s / tick_s)
    wall0 = loop0 = time.perf_counter()
    t_loop0 = 0.0
    next_progress = wall0 + 0.5
    first = True
    wire = emu.wire
    tick_frames = wire.framing.tick_frames  # (the command link's protocol)
    now_s, advance_to, recorder, mocap_link = emu.clock.now_s, emu.advance_to, emu.recorder, emu.mocap_link
    wire.hold_output = True  # the FC's frames go out with the tick, in one write
    wire.spin_s = 0.0  # (until the first answer: a new process takes milliseconds to start, asleep)
    emu.hold_mocap = True  # the mocap frames go out just before the tick that announces their size
    mocap_total = 0  # mocap bytes written in all (mod 2^31): each tick says, the onboard reads up to it
    pending: deque[float] = deque()  # ticks sent whose answers are not read yet, oldest first
    k = 0  # no tick at 0: its answer TIMESYNC(0, 0) would read as a request
    while True:
        k += 1
        if k > n_ticks:  # the run's duration is flown: on while a check's window is still open
            n_ticks = extend_ticks(emu, n_ticks, duration_s, tick_s)
            if k > n_ticks:
                break
        t = k * tick_s
        # the outputs of a pending tick act from its time + compute on: read them before running past it
        while pending and pending[0] + compute < t - 1e-12:
            if pending[0] + compute > now_s() + 1e-12:  # (with one tick of compute: there already)
                advance_to(pending[0] + compute)
            tick = pending.popleft()
            _collect(rep, emu, onboard, tick, tick + compute, mocap_total, guard_s)
        if advance_to(t) is not None:  # (`EmulatorSide.diverged_s`, as the call leaves it)
            note_divergence(rep, emu)
            break
        rep.ticks += 1
        if faults.acts_on_process:
            if pending and process_fault_due(onboard, faults, t):
                while pending:  # killed or stalled at t: what it wrote for the ticks before still counts
                    tick = pending.popleft()
                    _collect(rep, emu, onboard, tick, tick + compute, mocap_total, guard_s)
            apply_process_faults(rep, onboard, faults, t)
        if not first:  # the first tick's mocap waits for a program that has opened its ports
            mocap_total = (mocap_total + mocap_link.flush()) & MOCAP_COUNT_MASK
        if onboard.alive and not onboard.paused:
            # (no look at whether the program has exited here: one that answered its last tick and is
            # closing may or may not be gone yet, depending on the host's load; the tick goes out and its
            # missing answer says so, at this tick's time, on every run alike)
            if first:  # dropped by the program's port as it opens, always: whether it is open yet
                wire.discard_held()  # depends on how fast it started (warm or cold)
            wire.send_sync(tick_frames(t, mocap_total))
            onboard.service()
            if recorder.n_pending >= RECORD_BATCH:  # checks and rows in batches, while the onboard works
                recorder.flush()
            if first:  # wait for the new process, then the loop proper starts
                startup = (STARTUP_GUARD_S, STARTUP_RESEND_S)
                _collect(rep, emu, onboard, t, t + compute, mocap_total, *startup)
                wire.spin_s = spin_s
                loop0, t_loop0 = time.perf_counter(), t
                first = False
            else:
                pending.append(t)
        else:  # (a tick sent took the FC's frames with it)
            wire.flush()  # frames of a tick not sent (onboard dead or stalled) go out as they are
        if progress is not None and time.perf_counter() >= next_progress:
            progress(t)
            next_progress = time.perf_counter() + 0.5
    while pending:  # the last ticks' answers: the program has acted on them before the run ends
        tick = pending.popleft()
        _collect(rep, emu, onboard, tick, tick + compute, mocap_total, guard_s)
    rep.startup_wall_s = loop0 - wall0
    rep.wall_loop_s = time.perf_counter() - loop0
    rep.loop_sim_s = rep.ticks * tick_s - t_loop0
    return rep


def extend_ticks(emu: EmulatorSide, n_ticks: int, duration_s: float, tick_s: float) -> int:
    """The ticks to fly in all: ``n_ticks``, or more while a check's window is still open
    (`EmulatorSide.checks_open_until_s`), by up to `CHECK_OVERRUN_S` past ``duration_s``."""
    emu.recorder.flush()
    until = emu.checks_open_until_s()
    if until is None:
        return n_ticks
    return max(n_ticks, math.ceil(min(until, duration_s + CHECK_OVERRUN_S) / tick_s - 1e-9))


def note_divergence(rep: LoopReport, emu: EmulatorSide) -> None:
    """End the run where the simulated state diverged, saying so."""
    t = emu.diverged_s
    rep.ended_early = f"the simulated state diverged at t={t:.3f} s"
    rep.events.append({"time_s": t, "source": "runner", "text": rep.ended_early})


def _note_exit(rep: LoopReport, onboard: OnboardSide, t: float) -> None:
    onboard.alive = False
    rep.onboard_exit_s = t
    rep.events.append({"time_s": t, "source": "runner", "text": "onboard program exited"})


def _collect(
    rep: LoopReport,
    emu: EmulatorSide,
    onboard: OnboardSide,
    t: float,
    stamp_s: float,
    mocap_total: int,
    guard_s: float,
    resend_s: float = RESEND_S,
) -> None:
    """Wait for the answer to the tick at ``t``, its outputs handed to the link at ``stamp_s`` (s); an
    onboard program silent for ``guard_s`` (wall) is declared dead."""
    if not (onboard.alive and not onboard.paused):
        return  # killed or stalled since the tick was sent: no answer will come
    ns = round(t * 1e9)
    # the answer read before, or in what the program has written by now (no wait), else waited for
    read = emu.wire.take_until_answer(ns, stamp_s, True)
    if read or _await_answer(emu, onboard, (t, ns, stamp_s, mocap_total), guard_s, resend_s, read):
        rep.answered += 1
        if emu.faults.waiting:  # faults timed after a mission event: the events up to this tick
            emu.mission_events(onboard.new_events(t))
    elif onboard.exited():
        _note_exit(rep, onboard, t)
    else:
        onboard.kill()
        text = f"onboard program silent for {guard_s:g} s (wall): declared dead"
        rep.events.append({"time_s": t, "source": "runner", "text": text})


def _await_answer(
    emu: EmulatorSide, onboard: OnboardSide, tick: tuple[float, int, float, int], guard_s: float,
    resend_s: float, read: bool | None = None,
) -> bool:
    """Queue the onboard program's outputs until its answer to ``tick`` (time (s), time (ns), outputs'
    stamp (s), mocap byte total), which has not come yet; False when no answer came within ``guard_s``
    (wall). ``read``: what the link's last read gave (`CommandWire.take_until_answer`'s False: bytes
    without the answer, which the program is let act on first, as after each read here; None:
    nothing)."""
    t, ns, stamp_s, mocap_total = tick
    wire = emu.wire
    if read is False:
        onboard.service()
    deadline = time.monotonic() + guard_s
    resend_at = time.monotonic() + resend_s
    lost = False
    while True:
        now = time.monotonic()
        if now >= deadline:
            return False
        if now >= resend_at or (not lost and wire.answered_later_than(ns)):
            lost = True
            # lost on a port opened after it was written, or to corrupt bytes in front of it (a later
            # tick has been answered): the same tick again, after enough filler bytes to complete any
            # frame the program's parser is still collecting on a corrupt length
            wire.send_sync(wire.framing.resend_filler + wire.framing.tick_frames(t, mocap_total))
            resend_at = now + resend_s
        # the process is asked whether it has exited each time it has been silent for EXIT_POLL_S: a
        # program that finished its mission while ticks were in flight leaves them unanswered
        wait = min(EXIT_POLL_S, resend_s, max(0.0, deadline - now))
        if not wire.read_raw(wait, read_first=False) and onboard.exited():
            wire.read_raw(0.0)
            return wire.take_until_answer(ns, stamp_s)
        if wire.take_until_answer(ns, stamp_s):
            return True
        onboard.service()
