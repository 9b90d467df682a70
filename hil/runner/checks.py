"""The scenario's expectations checked against what a run observed: small pure functions, one `Check`
each (name, passed, expected, observed, sim time)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.runner.flight_quality import SETTLE_BAND_M, Figure, FlightQuality
from hil.runner.mission import window_hits
from hil.scenario.expect_fields import EXPECT_FIELDS, ExpectField, add_expect_field
from hil.scenario.schema import (
    QUALITY_CHECKS,
    Expectations,
    Fault,
    LinkExpectations,
    QualityExpectations,
    Scenario,
)

RECOVERY_MAX_SPEED_M_S = 0.5  # "hovering": slower than this


@dataclass(frozen=True)
class Check:
    """One expectation's verdict; ``time_s`` is the sim time it refers to (None: the whole run)."""

    name: str
    passed: bool
    expected: Any
    observed: Any
    time_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "passed": self.passed,
            "expected": self.expected,
            "observed": self.observed,
            "time_s": self.time_s,
        }


@dataclass(frozen=True)
class Observations:
    """What the checks read, gathered by the runner at the end of a run."""

    sim_time_s: float
    crossed_gap: bool
    crossing_time_s: float | None
    collision: str | None
    collision_time_s: float | None
    min_clearance_m: float | None
    min_clearance_time_s: float | None
    attitude_error_deg: float | None
    max_outside_lab_m: float
    failsafe_states: tuple[tuple[str, float], ...]  # (state, sim s) entered
    onboard_abort_s: float | None
    hover_point_m: tuple[float, float, float] | None  # the scenario's recovery point (run.recovery_point_m)
    columns: dict[str, np.ndarray]
    link: dict[str, float | None]  # delivered fractions and rates
    quality: FlightQuality  # the flight-quality figures (`hil.runner.flight_quality`)
    nonfinite_state_s: float | None = None  # first sim time the simulated state was NaN or Inf
    lockstep: bool = True  # the run was flown in lockstep (not on the wall clock)
    lockstep_lost_s: float | None = None  # first tick whose announced mocap bytes did not arrive
    lockstep_short_reads: int = 0  # how many tick reads came up short
    realtime: dict[str, Any] | None = None  # a real-time run's loop health (`hil.runner.realtime`)
    faults: tuple[Fault, ...] = ()  # as flown: those timed after a mission event carry their times
    phases: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # phase -> sim intervals
    onboard_abort_reason: str | None = None  # why the onboard program aborted (its reason and detail)
    command_link_bursty: bool = False  # the command link loses frames in bursts by design (its burst)


#: one registered check's verdicts from the scenario's expectations and the run's observations (none
#: when the expectations do not ask for it)
CheckFn = Callable[[Expectations, Observations], list[Check]]


#: what a check reads from ``expect:``: a field of `Expectations` by name, or a field the check brings
#: (`ExpectField`: its type, default, range and meaning, added to the schema while the check is registered)
ExpectRef = str | ExpectField


@dataclass(frozen=True)
class CheckKind:
    """A registered check: ``name`` (the `Check` names it gives: ``gives``, default its name alone),
    ``expect`` (the ``expect:`` fields it owns and reads; none: the run itself asks for it), ``doc`` (what
    it checks, the format document's check table) and ``run``. ``added`` are the fields of ``expect`` it
    brought to the schema (`hil.scenario.expect_fields`), the rest are `Expectations`' own."""

    name: str
    expect: tuple[str, ...]
    doc: str
    run: CheckFn
    gives: tuple[str, ...] = ()
    added: tuple[ExpectField, ...] = ()

    @property
    def check_names(self) -> tuple[str, ...]:
        return self.gives or (self.name,)

    def table_row(self) -> str:
        """The check's row in docs/scenario-format.md's check table."""
        names = ", ".join(f"`{n}`" for n in self.check_names)
        set_by = ", ".join(f"`{n}`" for n in self.expect) or "none"
        return f"| {names} | {set_by} | {self.doc} |"


#: check name -> kind, in the order a run's checks are listed
CHECK_KINDS: dict[str, CheckKind] = {}


def _expect_refs(expect: ExpectRef | tuple[ExpectRef, ...] | None) -> tuple[ExpectRef, ...]:
    if expect is None:
        return ()
    return expect if isinstance(expect, tuple) else (expect,)


def register_check(
    name: str, *, expect: ExpectRef | tuple[ExpectRef, ...] | None, doc: str, gives: tuple[str, ...] = ()
) -> Callable[[CheckFn], CheckFn]:
    """Register the decorated function as the check ``name`` (see `CheckKind`); ``expect`` names the
    `Expectations` fields it reads, or brings its own (`ExpectField`), which scenario files may then give
    in ``expect:``. ValueError for a name taken, an `Expectations` field that does not exist or is owned
    by another check, or an added field whose name is taken."""
    refs = _expect_refs(expect)

    def add(run: CheckFn) -> CheckFn:
        if name in CHECK_KINDS:
            raise ValueError(f"check {name!r} is registered already")
        own = Expectations.own_fields()
        owned = {n for k in CHECK_KINDS.values() for n in k.expect}
        for ref in refs:
            if isinstance(ref, str) and (ref not in own or ref in owned):
                why = "is set by another check" if ref in own else "is no field of expect"
                raise ValueError(f"check {name!r}: {ref!r} {why}")
        added = tuple(r for r in refs if isinstance(r, ExpectField))
        for i, f in enumerate(added):
            try:
                add_expect_field(f, own)
            except ValueError:
                for done in added[:i]:
                    EXPECT_FIELDS.pop(done.name, None)
                raise
        names = tuple(r if isinstance(r, str) else r.name for r in refs)
        CHECK_KINDS[name] = CheckKind(name, names, doc, run, gives, added)
        return run

    return add


def unregister_check(name: str) -> None:
    """Remove the check ``name`` and the ``expect:`` fields it added (nothing when it is not registered)."""
    kind = CHECK_KINDS.pop(name, None)
    for f in kind.added if kind is not None else ():
        EXPECT_FIELDS.pop(f.name, None)


@contextmanager
def check_registered(
    name: str, run: CheckFn, *, expect: ExpectRef | tuple[ExpectRef, ...] | None = None, doc: str = ""
) -> Iterator[CheckKind]:
    """The check ``name`` registered for the block, unregistered after (one added by a test or a plugin)."""
    register_check(name, expect=expect, doc=doc)(run)
    try:
        yield CHECK_KINDS[name]
    finally:
        unregister_check(name)


def evaluate(scenario: Scenario, obs: Observations) -> list[Check]:
    """Every check the scenario asks for, in the registry's order."""
    checks: list[Check] = []
    for kind in CHECK_KINDS.values():
        checks += kind.run(scenario.expect, obs)
    return checks


def check_fault_phases(obs: Observations) -> Check:
    """Each fault that names a flight phase acted during it: a fault that missed its phase tested
    something else than its scenario says (the flight's timing moved, or its event never came)."""
    misses = []
    first_t = None
    for i, f in enumerate(obs.faults):
        phase = f.target_phase
        if phase is None:
            continue
        intervals = obs.phases.get(phase, [])
        instant = f.instant
        if window_hits(f.start_s, f.end_s, intervals, instant):
            continue
        flown = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in intervals) or "never flown"
        if not math.isfinite(f.start_s):
            assert f.after is not None
            when = f"never started (no {f.after.after!r} event)"
        else:
            end = " s" if instant else (" s to the end" if f.end_s is None else f"-{f.end_s:.2f} s")
            when = f"at {f.start_s:.2f}{end}"
            first_t = f.start_s if first_t is None else first_t
        misses.append(f"faults[{i}] {f.kind} {when}; {phase}: {flown}")
    observed = "each fault acted in its phase" if not misses else "; ".join(misses)
    return Check("fault_phases", not misses, "each fault acts during the phase it names", observed, first_t)


def check_finite_state(obs: Observations) -> Check:
    """The simulated state stayed finite: a NaN state compares false against every bound, so without
    this check a diverged simulation would pass as a flight that stayed in the lab."""
    t = obs.nonfinite_state_s
    observed = "finite throughout" if t is None else f"diverged (NaN, Inf or > 1e30) at t={t:.3f} s"
    return Check("finite_state", t is None, "a finite simulated state", observed, t)


def check_lockstep(obs: Observations) -> Check:
    """Every tick's mocap bytes reached the onboard program before it acted: a run that lost lockstep
    is not the scenario's deterministic run, whatever else it did."""
    t, n = obs.lockstep_lost_s, obs.lockstep_short_reads
    observed = "held on every tick" if t is None else f"lost: {n} tick read(s) short of the mocap announced"
    return Check("lockstep", t is None, "every tick's mocap read in full", observed, t)


#: the longest silence between setpoints at the FC a real-time run may have, against the loop's lateness
#: limit: twice it (100 ms by default, the onboard program's stale-mocap limit; the loop's own lateness
#: shows in the setpoint stream as that lateness plus up to a control period)
SETPOINT_GAP_PER_LATE = 2.0
#: a fault explains a setpoint gap that ends within this long after it (s)
FAULT_AFTERMATH_S = 1.0
#: the faults that may silence the setpoints (the link, the program, what it flies by)
SILENCING_FAULTS = ("command_link_down", "corrupt_bytes", "onboard_killed", "onboard_stalled", "mocap_frozen",
                    "mocap_dropped")


def check_realtime(limit_ms: float, health: dict[str, Any], faults: tuple[Fault, ...] = (),
                   abort_s: float | None = None, bursty: bool = False) -> Check:
    """The run kept real time on both sides: the emulator's loop never woke more than ``limit_ms``
    late (a late loop runs the physics in a burst and holds the links meanwhile: the onboard program
    flew against wrong physics), the onboard program made contact at all, and its setpoints never
    stopped reaching the FC for more than `SETPOINT_GAP_PER_LATE` times that (an onboard side starved
    of CPU flies blind as much), unless a fault or its abort explains the silence, or the command link
    loses setpoints in bursts by design (``bursty``: the scenario's ``links.command.burst``)."""
    loop = health.get("loop") or {}
    worst = float(loop.get("late_worst_ms") or 0.0)
    gap_limit = SETPOINT_GAP_PER_LATE * limit_ms
    expected = (f"the emulator loop at most {limit_ms:g} ms late, setpoints at the FC at most "
                f"{gap_limit:g} ms apart")
    if health.get("contact_s") is None:
        return Check("realtime", False, expected, "no frame from the onboard program")
    sp = health.get("setpoints_at_fc") or {}
    gap = float(sp.get("max_gap_ms") or 0.0)
    end = sp.get("max_gap_end_s")
    explained = end is not None and (
        # (an abort explains a silence that starts after it: a program that aborts on what its own
        # silence did, stale mocap once it runs again, does not excuse the silence)
        bursty or (abort_s is not None and end - gap * 1e-3 >= abort_s)
        or any(f.kind in SILENCING_FAULTS and f.start_s <= end
               and (f.end_s is None or end - gap * 1e-3 <= f.end_s + FAULT_AFTERMATH_S) for f in faults))
    starved = gap > gap_limit and not explained
    observed = (f"worst {worst:g} ms late (median {loop.get('late_median_ms')} ms, p99 "
                f"{loop.get('late_p99_ms')} ms), {loop.get('caught_up_steps')} physics steps caught up; "
                f"longest setpoint gap at the FC {gap:g} ms")
    if explained:
        observed += " (in a fault, after the abort or on a bursty link)"
    when = end if starved and worst <= limit_ms else loop.get("late_worst_at_s")
    return Check("realtime", worst <= limit_ms and not starved, expected, observed, when)


def check_stays_in_lab(obs: Observations) -> Check:
    outside = obs.max_outside_lab_m
    if obs.nonfinite_state_s is not None:
        return Check("stays_in_lab", False, "inside the lab volume", "position not finite",
                     obs.nonfinite_state_s)
    return Check("stays_in_lab", outside <= 0.0, "inside the lab volume", f"{outside:.3f} m outside at most")


#: link check -> (the `LinkExpectations` limit it reads, its unit)
LINK_LIMITS = {
    "mocap_delivered_fraction": ("mocap_delivered_fraction_min", ""),
    "command_delivered_fraction": ("command_delivered_fraction_min", ""),
    "mocap_rate_hz": ("mocap_rate_hz_min", " Hz"),
    "command_rate_hz": ("command_rate_hz_min", " Hz"),
}


def check_link(limits: LinkExpectations, obs: Observations) -> list[Check]:
    """The link statistics over the run against the bounds given (a bound of None is not checked)."""
    checks = []
    for name, (field_name, unit) in LINK_LIMITS.items():
        limit = getattr(limits, field_name)
        if limit is not None:
            value = obs.link.get(name)
            ok = value is not None and value >= limit
            checks.append(Check(name, ok, f">= {limit:g}{unit}", None if value is None else round(value, 4)))
    return checks


def check_quality(limits: QualityExpectations, q: FlightQuality) -> list[Check]:
    """The flight-quality checks (`hil.runner.flight_quality`), one per figure, in every run; a check
    named in ``limits.expected_failures`` passes when its figure exceeds the limit."""
    pos = limits.position_error_m
    seg_limits = {"approach": pos.approach, "traverse": pos.traverse, "recovery": pos.recovery}
    settle = {k: Figure(None if f.value is None else (f.value if q.settled[k] else math.inf), f.time_s)
              for k, f in q.settling_time_s.items()}
    rows = (
        ("heading_error_deg", q.heading_error_deg,
         {"held": limits.heading_error_deg.held, "commanded": limits.heading_error_deg.commanded}, " deg",
         "off the held or the commanded heading"),
        ("attitude_tracking_deg", {"": q.attitude_tracking_deg}, {"": limits.attitude_tracking_deg}, " deg",
         "roll/pitch off the command (after the FC's nominal lag)"),
        ("position_error_m", q.position_error_m, seg_limits, " m", "from the plan"),
        ("thrust_saturation_s", {"": q.thrust_saturation_s}, {"": limits.thrust_saturation_s}, " s",
         "with a motor at full throttle"),
        ("settling_time_s", settle, dict.fromkeys(settle, limits.settling_time_s), " s",
         f"to settle within {SETTLE_BAND_M:g} m after each manoeuvre"),
    )
    return [_limit_check(name, figures, lims, unit, what, name in limits.expected_failures)
            for name, figures, lims, unit, what in rows]


def _limit_check(name: str, figures: dict[str, Figure], limits: dict[str, float], unit: str, what: str,
                 must_fail: bool) -> Check:
    """Whether every figure is within its limit (by part: a segment, a manoeuvre; "" for one figure);
    the time is the worst part's worst moment (the one furthest over, or nearest to, its limit)."""
    parts = [(k, f, limits[k]) for k, f in figures.items() if f.value is not None and k in limits]
    within = all(f.value <= lim for _, f, lim in parts)  # type: ignore[operator]
    worst = max(parts, key=lambda p: p[1].value / p[2] if p[2] > 0 else math.inf, default=None)  # type: ignore[operator]
    observed = "nothing to measure" if not parts else ", ".join(
        f"{k + ' ' if k else ''}{'never settled' if f.value == math.inf else f'{f.value:.3g}{unit}'}"
        for k, f, _ in parts
    )
    limit_text = ", ".join(f"{k + ' ' if k else ''}<= {lim:g}{unit}" for k, lim in limits.items())
    expected = f"{what}: {limit_text}"
    if must_fail:
        expected = f"fails (the check must catch this run): {expected}"
    return Check(name, (not within) if must_fail else within, expected, observed,
                 None if worst is None else worst[1].time_s)


def check_crossing(expected: bool, obs: Observations) -> Check:
    observed = "crossed through the opening" if obs.crossed_gap else "did not cross through the opening"
    return Check(
        "crosses_gap",
        obs.crossed_gap == expected,
        "crosses through the opening" if expected else "does not cross",
        observed,
        obs.crossing_time_s,
    )


def check_collision(expected: bool, obs: Observations) -> Check:
    observed = "none" if obs.collision is None else f"hit the {obs.collision}"
    return Check(
        "collision",
        (obs.collision is not None) == expected,
        "a collision" if expected else "no collision",
        observed,
        obs.collision_time_s,
    )


def check_clearance(limit_m: float, obs: Observations) -> Check:
    v = obs.min_clearance_m
    return Check(
        "min_clearance_m",
        v is not None and v >= limit_m,
        f">= {limit_m:g} m",
        "never at the wall" if v is None else round(v, 4),
        obs.min_clearance_time_s,
    )


def check_attitude(limit_deg: float, obs: Observations) -> Check:
    v = obs.attitude_error_deg
    return Check(
        "attitude_error_deg",
        v is not None and v <= limit_deg,
        f"<= {limit_deg:g} deg at the crossing",
        "no crossing" if v is None else round(v, 2),
        obs.crossing_time_s,
    )


def check_recovery(radius_m: float, time_s: float, obs: Observations) -> Check:
    """At ``time_s`` after the crossing: slower than 0.5 m/s and within ``radius_m`` of the recovery
    point the harness derives from the scenario (1 m up, 2.5 m past the gap centre along the crossing;
    of where the vehicle is then, for a vertical crossing, which has none)."""
    expected = f"hovering within {radius_m:g} m of the recovery point {time_s:g} s after crossing"
    if obs.crossing_time_s is None:
        return Check("recovery", False, expected, "no crossing")
    t_check = obs.crossing_time_s + time_s
    cols = obs.columns
    t = cols["t_s"]
    if len(t) == 0 or t[-1] < t_check - 0.02:
        return Check(
            "recovery",
            False,
            expected,
            f"run ended {t_check - (t[-1] if len(t) else 0):.2f} s early",
            t_check,
        )
    i = int(np.searchsorted(t, t_check))
    i = min(i, len(t) - 1)
    pos = np.array([cols["pos_m_x"][i], cols["pos_m_y"][i], cols["pos_m_z"][i]])
    vel = np.array([cols["vel_m_s_x"][i], cols["vel_m_s_y"][i], cols["vel_m_s_z"][i]])
    speed = float(np.linalg.norm(vel))
    target = np.array(obs.hover_point_m) if obs.hover_point_m is not None else pos
    dist = float(np.linalg.norm(pos - target))
    ok = dist <= radius_m and speed <= RECOVERY_MAX_SPEED_M_S and math.isfinite(dist)
    return Check("recovery", ok, expected, f"{dist:.2f} m from it at {speed:.2f} m/s", float(t[i]))


def check_failsafe(expected: bool | str, obs: Observations) -> Check:
    entered = [s for s, _ in obs.failsafe_states]
    first_t = obs.failsafe_states[0][1] if obs.failsafe_states else None
    observed = ", ".join(entered) if entered else "none"
    if expected is False:
        return Check("failsafe", not entered, "no failsafe", observed, first_t)
    if expected is True:
        return Check("failsafe", bool(entered), "a failsafe", observed, first_t)
    want = f"failsafe_{expected}"
    times = [t for s, t in obs.failsafe_states if s == want]
    return Check("failsafe", bool(times), f"failsafe {expected}", observed, times[0] if times else first_t)


def check_abort(expected: bool, obs: Observations) -> Check:
    aborted = obs.onboard_abort_s is not None
    return Check(
        "onboard_abort",
        aborted == expected,
        "onboard program aborts" if expected else "no abort",
        (f"aborted: {obs.onboard_abort_reason}" if obs.onboard_abort_reason else "aborted") if aborted
        else "none",
        obs.onboard_abort_s,
    )


# The registered checks, in the order a run lists them.


@register_check("crosses_gap", expect="crosses_gap", doc="the centre passes through the opening (or not)")
def _crosses_gap(e: Expectations, obs: Observations) -> list[Check]:
    return [check_crossing(e.crosses_gap, obs)]


@register_check("collision", expect="collision_expected", doc="a collision happens (or none does)")
def _collision(e: Expectations, obs: Observations) -> list[Check]:
    return [check_collision(e.collision_expected, obs)]


@register_check("min_clearance_m", expect="min_clearance_m", doc="the smallest clearance while in the wall")
def _clearance(e: Expectations, obs: Observations) -> list[Check]:
    return [] if e.min_clearance_m is None else [check_clearance(e.min_clearance_m, obs)]


@register_check("attitude_error_deg", expect="max_attitude_error_deg",
                doc="the attitude error to the gap's orientation at the crossing")
def _attitude(e: Expectations, obs: Observations) -> list[Check]:
    return [] if e.max_attitude_error_deg is None else [check_attitude(e.max_attitude_error_deg, obs)]


@register_check("recovery", expect="recovery", doc="a hover near the recovery point after the crossing")
def _recovery(e: Expectations, obs: Observations) -> list[Check]:
    if e.recovery is None or not e.crosses_gap:
        return []
    return [check_recovery(e.recovery.radius_m, e.recovery.time_s, obs)]


@register_check("fault_phases", expect=None,
                doc="each fault that names a `phase` acted during it (runs with such a fault)")
def _fault_phases(e: Expectations, obs: Observations) -> list[Check]:
    return [check_fault_phases(obs)] if any(f.target_phase is not None for f in obs.faults) else []


@register_check("finite_state", expect=None, doc="the simulated state stayed finite (every run)")
def _finite_state(e: Expectations, obs: Observations) -> list[Check]:
    return [check_finite_state(obs)]


@register_check("lockstep", expect=None, doc="every tick's mocap bytes were read in full (lockstep runs)")
def _lockstep(e: Expectations, obs: Observations) -> list[Check]:
    return [check_lockstep(obs)] if obs.lockstep else []


@register_check("realtime", expect="realtime_max_late_ms",
                doc="both sides kept to the wall clock: the emulator loop's lateness and the setpoints' "
                    "gaps at the FC (real-time runs)")
def _realtime(e: Expectations, obs: Observations) -> list[Check]:
    if obs.lockstep or obs.realtime is None:
        return []
    return [check_realtime(e.realtime_max_late_ms, obs.realtime, obs.faults, obs.onboard_abort_s,
                           bursty=obs.command_link_bursty)]


@register_check("stays_in_lab", expect="stays_in_lab", doc="the vehicle never leaves the lab volume")
def _stays_in_lab(e: Expectations, obs: Observations) -> list[Check]:
    return [check_stays_in_lab(obs)] if e.stays_in_lab else []


@register_check("failsafe", expect="failsafe_expected", doc="the FC entered a failsafe (of a kind), or none")
def _failsafe(e: Expectations, obs: Observations) -> list[Check]:
    return [check_failsafe(e.failsafe_expected, obs)]


@register_check("onboard_abort", expect="onboard_abort_expected", doc="the onboard program aborted (or not)")
def _abort(e: Expectations, obs: Observations) -> list[Check]:
    return [] if e.onboard_abort_expected is None else [check_abort(e.onboard_abort_expected, obs)]


@register_check("link", expect="link", gives=tuple(LINK_LIMITS), doc="the link statistics' bounds given")
def _link(e: Expectations, obs: Observations) -> list[Check]:
    return check_link(e.link, obs)


@register_check("quality", expect="quality", gives=QUALITY_CHECKS, doc="the flight-quality limits (all runs)")
def _quality(e: Expectations, obs: Observations) -> list[Check]:
    return check_quality(e.quality, obs.quality)
