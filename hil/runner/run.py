"""Running one scenario: wire the emulator side and the onboard program together (in one process over
memory links, or as two processes over pseudo-terminals), fly it in lockstep or real time, check the
expectations and write the results (summary.json, run.tlog, timeseries.npz, report.html)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from emulator.fc.tuning import fc_gains
from emulator.physics import backend_names
from emulator.profile import load_profile
from hil.link.clock import SimClock
from hil.link.memory import MemoryTransport
from hil.link.pty import PtyTransport
from hil.link.tlog import TlogWriter
from hil.link.transport import Transport
from hil.report import write_report_html, write_summary, write_timeseries
from hil.report.html import REPORT_NAME
from hil.report.mcap_log import MCAP_NAME
from hil.report.summary import SUMMARY_NAME
from hil.report.timeseries import TIMESERIES_NAME
from hil.runner.checks import Check, Observations, evaluate
from hil.runner.emulator_side import EmulatorSide, flown_profile
from hil.runner.flight_quality import measure
from hil.runner.lockstep import (
    DEFAULT_GUARD_S,
    DEFAULT_TICK_S,
    LoopReport,
    kept_to,
    lockstep_cpu,
    lockstep_spin_s,
    run_lockstep,
)
from hil.runner.mission import phase_intervals, window_hits
from hil.runner.onboard_report import OnboardReport
from hil.runner.onboard_side import (
    InProcessOnboard,
    ProcessOnboard,
    onboard_argv,
    onboard_options,
    prestart,
    program_config,
)
from hil.runner.over_time import time_mean
from hil.runner.preflight import preflight_check, refusal, refused_summary, write_refused
from hil.runner.realtime import CONTACT_WAIT_S, run_realtime
from hil.runner.recorder import FC_STATE_CODES
from hil.scenario.schema import COMMAND_PROTOCOLS, DEFAULT_VEHICLE, Fault, Scenario
from policies.onboard import pilot_names

TLOG_NAME = "run.tlog"
ONBOARD_LOG_NAME = "onboard_events.jsonl"
ONBOARD_STDERR_NAME = "onboard_stderr.txt"
MEMORY_CAPACITY_BYTES = 1 << 20
SEGMENT_PHASES = {"approach": 1, "traverse": 2, "recovery": 3, "hover": 0}


class RunSetupError(ValueError):
    """The scenario or the options cannot be run as given (bad input, exit 2)."""


@dataclass(frozen=True)
class RunOptions:
    """Overrides of the scenario for one run; None keeps the scenario's value."""

    pilot: str | None = None
    in_process: bool | None = None  # None: in-process when both links say "memory"
    realtime: bool | None = None
    seed: int | None = None
    backend: str | None = None
    vehicle: str | None = None  # a profile name or file; the opening grows with its body box (`for_vehicle`)
    protocol: str | None = None  # the command link's protocol ("mavlink", "dji_open")
    tick_s: float = DEFAULT_TICK_S
    guard_s: float = DEFAULT_GUARD_S
    #: report.html for every run, or only for a failed one (a sweep's passed runs need none: 15 % of a run)
    html_report: bool | str = True  # True, or "failed"
    #: start the onboard program as a new interpreter instead of forking it warm (over ptys only)
    cold_start: bool = False
    #: runs flying at once on this machine (a suite's workers): with fewer than two cores per run the
    #: two sides of a lockstep run wait for each other asleep instead of polling (`lockstep_spin_s`)
    parallel_runs: int = 1
    #: which of those workers flies this run (0-based; None: not known): with as many runs as cores, a
    #: lockstep run over ptys keeps to that worker's core (`lockstep_cpu`)
    worker: int | None = None


@dataclass(frozen=True)
class RunResult:
    """One run's verdict and where its files are."""

    passed: bool
    checks: tuple[Check, ...]
    out_dir: Path
    summary: dict[str, Any] = field(repr=False)

    @property
    def failed_checks(self) -> tuple[Check, ...]:
        return tuple(c for c in self.checks if not c.passed)

    @property
    def report_path(self) -> Path:
        return self.out_dir / "report.html"

    @property
    def tlog_path(self) -> Path:
        return self.out_dir / TLOG_NAME


def resolve(scenario: Scenario, options: RunOptions) -> tuple[Scenario, bool, bool]:
    """The scenario with the overrides applied, in_process, realtime; RunSetupError for bad values."""
    s = scenario
    if options.pilot is not None:
        s = replace(s, pilot=options.pilot)
    if options.seed is not None:
        if options.seed < 0:
            raise RunSetupError(f"seed must be >= 0, got {options.seed}")
        s = replace(s, seed=options.seed)
    if options.backend is not None:
        s = replace(s, physics=options.backend)
    if options.protocol is not None:
        if options.protocol not in COMMAND_PROTOCOLS:
            raise RunSetupError(f"command-link protocol must be one of {', '.join(COMMAND_PROTOCOLS)}, "
                                f"got {options.protocol!r}")
        command = replace(s.links.command, protocol=options.protocol)
        s = replace(s, links=replace(s.links, command=command))
    if options.vehicle is not None and options.vehicle != s.vehicle:
        why = not_applicable(s, options.vehicle)
        if why is not None:
            raise RunSetupError(f"{s.id} is not flown with vehicle {options.vehicle}: {why}")
        s = for_vehicle(s, options.vehicle)
    if s.pilot not in pilot_names():
        raise RunSetupError(f"unknown pilot {s.pilot!r}; known: {', '.join(pilot_names())}")
    if s.physics not in backend_names():
        raise RunSetupError(f"unknown physics backend {s.physics!r}; known: {', '.join(backend_names())}")
    transports = {s.links.command.transport, s.links.mocap.transport}
    if "udp" in transports:
        raise RunSetupError(
            "the runner joins the two sides over ptys or memory; transport 'udp' is not supported"
        )
    in_process = options.in_process if options.in_process is not None else transports == {"memory"}
    realtime = options.realtime if options.realtime is not None else s.realtime
    if not (0.001 <= options.tick_s <= 0.1):
        raise RunSetupError(f"tick must be 1..100 ms, got {options.tick_s * 1e3:g} ms")
    if s.onboard_compute_ms is not None and s.onboard_compute_ms > options.tick_s * 1e3 + 1e-9:
        raise RunSetupError(
            f"{s.source}: onboard_compute_ms is {s.onboard_compute_ms:g} ms, longer than the lockstep tick "
            f"({options.tick_s * 1e3:g} ms): expected 0..{options.tick_s * 1e3:g} or null (one tick)"
        )
    return s, in_process, realtime


def not_applicable(scenario: Scenario, vehicle: str) -> str | None:
    """Why ``scenario`` cannot be flown by ``vehicle`` in place of its own (the pytest plugin and
    `hil suite --vehicle` skip it, `hil run --vehicle` refuses it), or None when it can: a scenario that
    names a vehicle of its own is about that vehicle, and a gap tilted beyond the new vehicle's tilt
    limit is one it cannot cross (a scenario file naming such a vehicle is refused when it loads).
    None too for a vehicle that does not load: the run names what is wrong with it."""
    if vehicle == scenario.vehicle:
        return None
    if scenario.vehicle != DEFAULT_VEHICLE:
        return f"the scenario is about its own vehicle {scenario.vehicle}"
    try:
        profile = load_profile(vehicle)
    except ValueError:
        return None
    if scenario.gap.tilt_deg > profile.max_tilt_deg:
        return (f"gap tilted {scenario.gap.tilt_deg:.0f} deg, beyond {profile.name}'s "
                f"{profile.max_tilt_deg:g} deg tilt limit")
    return None


def for_vehicle(scenario: Scenario, vehicle: str) -> Scenario:
    """``scenario`` flown by ``vehicle`` (a built-in profile name or a profile file) instead of its own:
    where the new body box is larger, the opening grows by the difference (long side by the larger of
    length and width, short side by the height), keeping the clearance the scenario was written with.
    RunSetupError for an unknown vehicle."""
    try:
        old, new = load_profile(scenario.vehicle), load_profile(vehicle)
    except ValueError as exc:
        raise RunSetupError(str(exc)) from exc
    grow_w = max(new.body_box_m[:2]) - max(old.body_box_m[:2])
    grow_h = new.body_box_m[2] - old.body_box_m[2]
    gap = replace(
        scenario.gap,
        width_m=scenario.gap.width_m + max(grow_w, 0.0),
        height_m=scenario.gap.height_m + max(grow_h, 0.0),
    )
    return replace(scenario, vehicle=vehicle, gap=gap)


def run_scenario(
    scenario: Scenario,
    out_dir: str | Path,
    options: RunOptions | None = None,
    progress: Callable[[float, float], None] | None = None,
    watch: Callable[[EmulatorSide, Path], Callable[[], None] | None] | None = None,
) -> RunResult:
    """Fly ``scenario`` and write its results to ``out_dir``; RunSetupError (or ValueError) for bad input.

    ``progress(sim_time_s, duration_s)`` is called about twice a second of wall time; ``watch(emulator
    side, onboard event log)`` once before the flight starts (a live view reads them from its own
    thread), and what it returns (if anything) once the flight is over, before the emulator closes.
    """
    options = options or RunOptions()
    s, in_process, realtime = resolve(scenario, options)
    cpu = None if in_process or realtime else lockstep_cpu(options.worker, options.parallel_runs)
    with kept_to(cpu):
        return _run(s, out_dir, options, progress, in_process, realtime, watch)


def _run(
    s: Scenario,
    out_dir: str | Path,
    options: RunOptions,
    progress: Callable[[float, float], None] | None,
    in_process: bool,
    realtime: bool,
    watch: Callable[[EmulatorSide, Path], Callable[[], None] | None] | None,
) -> RunResult:
    warm = not (in_process or options.cold_start)
    if options.parallel_runs < 1:
        raise RunSetupError(f"parallel runs must be >= 1, got {options.parallel_runs}")
    spin_s = lockstep_spin_s(options.parallel_runs)
    if warm:
        prestart()  # (the first run of a process: the fork server imports while the emulator is built)
    try:
        profile = flown_profile(load_profile(s.vehicle), s.airframe)
        fc_gains(profile)  # a vehicle the FC cannot stabilise is refused here, with the reason
        ob_options = onboard_options(s)
        config = program_config(ob_options)
    except ValueError as exc:
        raise RunSetupError(str(exc)) from exc
    out = Path(out_dir)
    clear_run_folder(out)
    why = refusal(s, profile, config)
    if why is not None:  # an opening too small for the body is never flown
        check = preflight_check(s.expect.refused, why)
        summary = refused_summary(s, check, why)
        write_refused(out, summary)
        return RunResult(check.passed, (check,), out, summary)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(s.seed)
    clock = SimClock()
    links: list[Transport] = []
    tlog = TlogWriter(out / TLOG_NAME, epoch_unix_s=time.time() if realtime else 0.0)
    log_path = out / ONBOARD_LOG_NAME
    emu = None
    onboard: InProcessOnboard | ProcessOnboard | None = None
    spawn_s = 0.0  # wall time the onboard process took to spawn (s)
    started_monotonic_s = None  # when it was spawned (time.monotonic, s): real time's zero
    wall0 = time.perf_counter()
    cpu0 = time.process_time()
    try:
        if in_process:
            cmd_fc, cmd_ob = MemoryTransport.pair(MEMORY_CAPACITY_BYTES, name="command")
            moc_fc, moc_ob = MemoryTransport.pair(MEMORY_CAPACITY_BYTES, name="mocap")
            links += [cmd_fc, cmd_ob, moc_fc, moc_ob]
        else:
            cmd_fc = PtyTransport.create(s.links.command.baud)
            moc_fc = PtyTransport.create(s.links.mocap.baud)
            links += [cmd_fc, moc_fc]
        try:
            emu = EmulatorSide(
                s,
                profile,
                rng,
                cmd_fc,
                moc_fc,
                clock=clock,
                backend=s.physics,
                tlog=tlog,
                # (in real time the run lasts duration_s from the program's first frame)
                duration_s=s.duration_s + (CONTACT_WAIT_S if realtime else 0.0),
            )
        except ValueError as exc:
            raise RunSetupError(str(exc)) from exc
        if in_process:
            onboard = InProcessOnboard(cmd_ob, moc_ob, config, log_path, lockstep=not realtime)
        else:
            argv = onboard_argv(
                cmd_fc.endpoint,
                moc_fc.endpoint,
                s.links.command.baud,
                s.links.mocap.baud,
                [*ob_options, f"--lockstep-spin-us={spin_s * 1e6:g}"],
                log_path,
                lockstep=not realtime,
            )
            # started only now, right before the first tick: the frames written with that tick reach
            # a program that has not opened its ports yet and are dropped, always (a program started
            # earlier would get them or not depending on how fast it starts)
            spawn0 = time.perf_counter()
            started_monotonic_s = time.monotonic()
            onboard = ProcessOnboard(argv, log_path, out / ONBOARD_STDERR_NAME, warm=warm)
            spawn_s = time.perf_counter() - spawn0

        # (no progress asked: none given to the loop, which then reads no wall clock a tick for it)
        tell = None if progress is None else (lambda t: progress(t, s.duration_s))
        unwatch = None if watch is None else watch(emu, log_path)
        compute_s = None if s.onboard_compute_ms is None else s.onboard_compute_ms * 1e-3
        if realtime:  # the modelled compute time as lockstep's (default: one tick)
            compute = options.tick_s if compute_s is None else compute_s
            loop = run_realtime(emu, onboard, s.duration_s, progress=tell, compute_s=compute,
                                started_monotonic_s=started_monotonic_s)
        else:
            loop = run_lockstep(
                emu,
                onboard,
                s.duration_s,
                tick_s=options.tick_s,
                compute_s=compute_s,
                guard_s=options.guard_s,
                progress=tell,
                spin_s=spin_s,
            )
        if unwatch is not None:
            unwatch()
        loop.startup_wall_s += spawn_s  # (the program's start-up counts from its spawn)
        exit_code = onboard.close()  # first: the program's closing summary is among its events then
        report = OnboardReport.from_events(onboard.events(), exit_code)
        facts = RunFacts(
            wall_s=time.perf_counter() - wall0,
            in_process=in_process,
            realtime=realtime,
            # each side's CPU time (s): this process's up to here (both sides when they share it), the
            # onboard program's whole life where its fork server reaped it (None in this process or cold)
            cpu_s={"harness": time.process_time() - cpu0,
                   "onboard": onboard.cpu_s if isinstance(onboard, ProcessOnboard) else None},
            onboard_start=_start_mode(onboard),
        )
        tlog.close()  # (complete before summary.json, the run's last file, says the run is done)
        return _finish(s, out, emu, loop, report, facts, options.html_report)
    finally:
        if onboard is not None:
            onboard.close()
        tlog.close()
        if emu is not None:
            emu.close()
        for link in links:
            link.close()


@dataclass(frozen=True)
class RunFacts:
    """How a run was flown, for its summary."""

    wall_s: float  # the whole run's wall time (s)
    in_process: bool
    realtime: bool
    onboard_start: str | None  # "warm" (forked), "cold" (a new interpreter), None (in-process)
    #: CPU time (s, user + system) of the harness's process over the run, its reports excluded (both
    #: sides when they share it), and of the onboard program's process (None when unknown)
    cpu_s: dict[str, float | None]


def _finish(s: Scenario, out: Path, emu: EmulatorSide, loop: LoopReport, onboard: OnboardReport,
            facts: RunFacts, html_report: bool | str) -> RunResult:
    """Check the run and write its files: timeseries.npz, report.html, then summary.json last (written
    atomically: a summary.json means the run's files are complete)."""
    obs = observe(s, emu, loop, onboard, lockstep=not facts.realtime)
    checks = tuple(evaluate(s, obs))
    passed = all(c.passed for c in checks)
    summary = _summary(s, emu, loop, onboard, obs, checks, facts)
    write_timeseries(out, obs.columns)
    if html_report is True or (html_report == "failed" and not passed):
        write_report_html(out, summary, obs.columns, s)
    write_summary(out, summary)
    return RunResult(passed, checks, out, summary)


def observe(s: Scenario, emu: EmulatorSide, loop: LoopReport, onboard: OnboardReport, *,
            lockstep: bool) -> Observations:
    """What the checks read, from what each side reports of the run."""
    rec = emu.recorder
    cols = rec.columns()
    cols["phase"] = _phase_column(cols, list(onboard.events))
    tracker = rec.tracker
    first = tracker.crossings[0] if tracker.crossings else None
    sim_time = emu.time_s
    return Observations(
        sim_time_s=sim_time,
        crossed_gap=tracker.crossed_through_opening,
        crossing_time_s=None if first is None else first.time_s,
        collision=None if rec.collision is None else rec.collision.obstacle,
        collision_time_s=None if rec.collision is None else rec.collision.time_s,
        min_clearance_m=tracker.min_clearance_m,
        min_clearance_time_s=tracker.min_clearance_time_s,
        attitude_error_deg=rec.attitude_error_at_crossing_deg,
        max_outside_lab_m=rec.max_outside_lab_m,
        failsafe_states=emu.failsafes(),
        onboard_abort_s=onboard.abort_s,
        onboard_abort_reason=onboard.abort_reason,
        command_link_bursty=s.links.command.burst is not None,
        hover_point_m=recovery_point_m(emu.gap.axes(), np.asarray(emu.gap.centre_m),
                                       np.asarray(s.initial.pos_m)),
        columns=cols,
        link=dict(emu.link_stats()["summary"]),
        quality=measure(cols, list(onboard.events), emu.attitude_lag_s),
        nonfinite_state_s=emu.diverged_s,  # (the recorder has been flushed by `columns`)
        lockstep=lockstep,
        realtime=loop.realtime,
        lockstep_lost_s=onboard.lockstep_lost_s,
        lockstep_short_reads=onboard.short_reads,
        faults=emu.faults.faults,
        phases=phase_intervals(list(onboard.events), sim_time),
    )


def _summary(s: Scenario, emu: EmulatorSide, loop: LoopReport, onboard: OnboardReport, obs: Observations,
             checks: tuple[Check, ...], facts: RunFacts) -> dict[str, Any]:
    """summary.json's contents."""
    cols = obs.columns
    first = emu.recorder.tracker.crossings[0] if emu.recorder.tracker.crossings else None
    events = emu.fc_report_events() + onboard.report_events() + emu.faults.events() + loop.events
    events += emu.world_report_events()
    events.sort(key=lambda ev: ev["time_s"] if isinstance(ev["time_s"], int | float) else math.inf)
    loop_sim = obs.sim_time_s if loop.loop_sim_s is None else loop.loop_sim_s
    airborne = cols["fc_state"] > FC_STATE_CODES["disarmed"]
    emu_figures = emu.summary_figures()
    return {
        "passed": all(c.passed for c in checks),
        "scenario_id": s.id,
        "end_reason": loop.ended_early or "duration reached",
        "checks": [c.to_dict() for c in checks],
        "crossed_gap": obs.crossed_gap,
        "collision": obs.collision,
        "collision_time_s": obs.collision_time_s,
        "min_clearance_m": obs.min_clearance_m,
        "attitude_error_deg": obs.attitude_error_deg,
        "crossing": None
        if first is None
        else {
            "time_s": first.time_s,
            "point_m": list(first.point_m),
            "through_opening": first.through_opening,
        },
        "sim_time_s": obs.sim_time_s,
        "wall_time_s": facts.wall_s,
        "loop_wall_time_s": loop.wall_loop_s,
        "loop_sim_time_s": loop_sim,
        "onboard_startup_s": loop.startup_wall_s,
        "cpu_s": facts.cpu_s,
        "real_time_factor": loop_sim / loop.wall_loop_s if loop.wall_loop_s > 0 else None,
        "mode": {
            "in_process": facts.in_process,
            "realtime": facts.realtime,
            "onboard_start": facts.onboard_start,
            "pilot": s.pilot,
            "pilot_flies": onboard.flies,  # what computed each segment's commands, as the program said
            "seed": s.seed,
            "physics": s.physics,
        },
        "ticks": loop.ticks,
        "ticks_answered": loop.answered,
        "lockstep": None
        if facts.realtime
        else {"held": obs.lockstep_lost_s is None, "short_mocap_reads": obs.lockstep_short_reads,
              "lost_at_s": obs.lockstep_lost_s},
        "nonfinite_state_s": obs.nonfinite_state_s,
        "realtime": loop.realtime,
        "links": emu_figures["links"],
        "esc_bus": emu_figures["esc_bus"],
        "failsafe_events": [{"state": st, "time_s": t} for st, t in obs.failsafe_states],
        "faults": [_fault_as_flown(f, obs.phases) for f in obs.faults],
        "fc_final_state": emu_figures["fc_final_state"],
        "onboard_exit_code": onboard.exit_code,
        # the program's own counters (mocap poses refused by kind, messages not from the FC, commands
        # refused, ...), from its closing "summary" event; None when it wrote none (killed)
        "onboard": onboard.counters,
        "onboard_abort_s": obs.onboard_abort_s,
        "recovery_point_m": obs.hover_point_m,
        "onboard_hover_point_m": onboard.hover_point_m,
        # over time (`hil.runner.over_time`), not over samples: the recorder samples 10x as often near the gap
        "mean_thrust_n": time_mean(cols["t_s"], cols["thrust_n"], mask=airborne) or 0.0,
        "mean_angular_rate_rad_s": time_mean(cols["t_s"], cols["body_rate_rad_s"]) or 0.0,
        "flight_quality": obs.quality.to_dict(),
        "events": events,
        "scenario": s.to_dict(),
    }


#: what a run writes into its folder, besides the .tlog it opens fresh itself
RUN_FILES = (ONBOARD_LOG_NAME, SUMMARY_NAME, TIMESERIES_NAME, REPORT_NAME, MCAP_NAME, ONBOARD_STDERR_NAME)


def clear_run_folder(out: Path) -> None:
    """``out`` rid of an earlier run's files before this run starts: a live view or a replay never
    shows another run's plan, events or flight from a reused folder."""
    out.mkdir(parents=True, exist_ok=True)
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)


def _fault_as_flown(f: Fault, phases: dict[str, list[tuple[float, float]]]) -> dict[str, Any]:
    """A fault's times as flown (None: it never started) and whether it hit the phase it names."""
    started = math.isfinite(f.start_s)
    phase = f.target_phase
    hit = None if phase is None else window_hits(f.start_s, f.end_s, phases.get(phase, []),
                                                   f.instant)
    return {"kind": f.kind, "start_s": f.start_s if started else None, "end_s": f.end_s if started else None,
            "phase": phase, "hit_phase": hit}


def _start_mode(onboard: InProcessOnboard | ProcessOnboard) -> str | None:
    """How the onboard program was started: "warm" (forked), "cold" (a new interpreter), None (in-process)."""
    if isinstance(onboard, ProcessOnboard):
        return "warm" if onboard.warm else "cold"
    return None


def _phase_column(cols: dict[str, np.ndarray], events: list[dict[str, Any]]) -> np.ndarray:
    t = cols["t_s"]
    phase = np.zeros(len(t))
    for ev in events:
        name, t0 = ev.get("event"), ev.get("t_s")
        if not isinstance(t0, int | float):
            continue
        if name == "segment":
            seg = str(ev.get("segment", "")).lower()
            code = next((c for key, c in SEGMENT_PHASES.items() if key in seg), 0)
            phase[t >= t0] = code
        elif name == "abort":
            phase[t >= t0] = 4
    failsafe = np.isin(cols["fc_state"], (FC_STATE_CODES["failsafe_hover"], FC_STATE_CODES["failsafe_land"]))
    phase[failsafe] = 4
    return phase


#: the paper's recovery point: 1 m above the ground, 2.5 m past the gap centre along the crossing
RECOVERY_DISTANCE_M = 2.5
RECOVERY_HEIGHT_M = 1.0


def recovery_point_m(
    gap_axes: np.ndarray, centre_m: np.ndarray, start_m: np.ndarray
) -> tuple[float, float, float] | None:
    """Where the scenario expects the vehicle to hover after crossing (m), from the gap and the start
    alone, so that the check does not take the pilot's word for it; None for a vertical crossing."""
    e1 = gap_axes[1]
    direction = -e1 if float(np.dot(start_m - centre_m, e1)) > 0 else e1  # away from the start side
    horiz = np.array([direction[0], direction[1], 0.0])
    norm = float(np.linalg.norm(horiz))
    if norm < 1e-6:
        return None
    p = centre_m + RECOVERY_DISTANCE_M * horiz / norm
    return (float(p[0]), float(p[1]), RECOVERY_HEIGHT_M)
