"""Scenario files' typed contents: frozen dataclasses with defaults, units and allowed ranges.

Each field's range, choices and one-line meaning live in its metadata (see `spec`): the loader
validates against them and the format document is checked against them, so a limit is written once.
Angles are in degrees here because the file format says ``_deg``; use the ``*_rad`` properties inside.
World frame ENU (z up), SI units.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from typing import Any

from hil.link.protocols import PROTOCOLS
from hil.scenario.expect_fields import EXPECT_FIELDS
from hil.scenario.fault_kinds import NoParams, fault_kind
from hil.scenario.spec import Vec3, spec

# `spec` wraps dataclasses.field (adding validation metadata), so calling it in defaults is intended.
# ruff: noqa: RUF009

TRANSPORTS = ("pty", "memory", "udp")
FAILSAFE_KINDS = ("hover", "land")  # the FC's failsafe action; `true` in a file means any of them
#: how late the emulator loop of a real-time run may wake at worst (ms): half the onboard program's
#: stale-mocap limit (100 ms), five of its control periods without physics or links behind them
REALTIME_MAX_LATE_MS = 50.0
#: the mission events the onboard program reports (its takeoff, plan and each segment's start) that a
#: fault's time may be given after: the phase a fault names holds wherever the flight's timing moves it
MISSION_EVENTS = (
    "mocap_ok",
    "authority",
    "armed",
    "takeoff",
    "plan",
    "approach",
    "traverse",
    "recovery",
    "hover",
    "mission_done",
)
#: the phases of a flight a fault can be meant for: the takeoff, then the mission's segments
FLIGHT_PHASES = ("takeoff", "approach", "traverse", "recovery", "hover")
DEFAULT_VEHICLE = "n3_tx2"
DEFAULT_PHYSICS = "native"


@dataclass(frozen=True)
class GapSpec:
    """The wall's rectangular opening; rotation R = Rz(yaw) Ry(pitch) Rx(roll) (see emulator.world)."""

    centre_m: Vec3 = spec((0.0, 0.5, 2.1), lo=-100.0, hi=100.0, doc="centre of the opening, world ENU")
    roll_deg: float = spec(0.0, lo=-90.0, hi=90.0, doc="tilt about the crossing axis (the paper's gap angle)")

    pitch_deg: float = spec(0.0, lo=-90.0, hi=90.0, doc="rotation about world y, applied after roll")
    yaw_deg: float = spec(0.0, lo=-180.0, hi=180.0, doc="heading of the crossing direction from world +x")
    width_m: float = spec(0.8, lo=0.0, hi=5.0, lo_open=True, doc="long side of the opening (along e0)")
    height_m: float = spec(0.45, lo=0.0, hi=5.0, lo_open=True, doc="short side of the opening (along e2)")
    wall_thickness_m: float = spec(
        0.05, lo=0.0, hi=1.0, lo_open=True, doc="wall depth along the crossing axis"
    )

    @property
    def roll_rad(self) -> float:
        return math.radians(self.roll_deg)

    @property
    def pitch_rad(self) -> float:
        return math.radians(self.pitch_deg)

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)

    @property
    def tilt_deg(self) -> float:
        """The opening's tilt from upright (deg): the angle of its short side from vertical, which the
        vehicle's body z takes in the traverse."""
        return math.degrees(math.acos(min(1.0, abs(math.cos(self.roll_rad) * math.cos(self.pitch_rad)))))


@dataclass(frozen=True)
class LabSpec:
    """The lab's flyable volume, an axis-aligned box in world ENU (m)."""

    min_m: Vec3 = spec((-5.0, -5.0, 0.0), lo=-1000.0, hi=1000.0, doc="lower corner")
    max_m: Vec3 = spec((5.0, 5.0, 4.0), lo=-1000.0, hi=1000.0, doc="upper corner (each axis above min_m)")


@dataclass(frozen=True)
class InitialState:
    """Where the vehicle starts (the release's test case start by default)."""

    pos_m: Vec3 = spec((-2.0, -1.0, 0.5), lo=-1000.0, hi=1000.0, doc="start position; inside the lab")
    vel_m_s: Vec3 = spec((0.0, 0.0, 0.0), lo=-20.0, hi=20.0, doc="start velocity; zero when on_ground")
    yaw_deg: float = spec(0.0, lo=-180.0, hi=180.0, doc="start heading from world +x")
    on_ground: bool = spec(False, doc="start landed and disarmed (z of pos_m is then the ground)")

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)


@dataclass(frozen=True)
class ApproachSpec:
    """The approach manoeuvre to the traverse's start."""

    speed_m_s: float | None = spec(
        None, lo=1.0, hi=5.0, doc="desired speed through the gap; null: the pilot's own choice"
    )
    duration_s: float = spec(2.6, lo=0.0, hi=30.0, lo_open=True, doc="approach primitive duration")


@dataclass(frozen=True)
class BurstLoss:
    """Gilbert-Elliott two-state loss: every message is lost while the channel is in the bad state."""

    p_gb: float = spec(0.0, lo=0.0, hi=1.0, doc="probability per message of going good -> bad")
    p_bg: float = spec(1.0, lo=0.0, hi=1.0, lo_open=True, doc="probability per message of going bad -> good")


@dataclass(frozen=True)
class LinkSpec:
    """One serial-style link between the emulator and the onboard computer."""

    transport: str = spec("pty", choices=TRANSPORTS, doc="what carries the bytes")
    baud: int = spec(921600, lo=1200, hi=20_000_000, doc="line rate (bit/s; 10 bits a byte)")
    latency_ms: float = spec(0.0, lo=0.0, hi=10_000.0, doc="added one-way delay per message")
    jitter_ms: float = spec(0.0, lo=0.0, hi=10_000.0, doc="standard deviation of the added delay")
    loss: float = spec(0.0, lo=0.0, hi=1.0, doc="independent loss probability per message")
    burst: BurstLoss | None = spec(None, doc="burst loss on top of `loss`; null: none")


#: the command link's protocols, a live view of `hil.link.protocols.PROTOCOLS` (MAVLink 2, PX4-flavoured;
#: DJI's OPEN protocol, Onboard SDK 3.x; any registered later)
COMMAND_PROTOCOLS = PROTOCOLS.keys()


@dataclass(frozen=True)
class CommandLinkSpec(LinkSpec):
    """The link between the onboard computer and the flight controller, with the protocol it speaks."""

    protocol: str = spec("mavlink", choices=COMMAND_PROTOCOLS,
                         doc="what the FC and the onboard program speak (docs/dji-open-link.md)")


@dataclass(frozen=True)
class MocapLinkSpec(LinkSpec):
    """The motion-capture radio link, with the tracker's frame rate."""

    rate_hz: float = spec(120.0, lo=1.0, hi=1000.0, doc="mocap frame rate")


@dataclass(frozen=True)
class EscBusSpec:
    """The motors behind DroneCAN ESCs on a CAN bus (`emulator.esc.bus`); the FC's watch over them is
    set by its parameters N3_ESC_TOUT and N3_ESC_FS_ACT."""

    bitrate_bps: int = spec(1_000_000, lo=10_000, hi=1_000_000, doc="CAN bit rate")
    command_rate_hz: float = spec(400.0, lo=50.0, hi=2000.0, doc="RawCommand rate (the FC's loop rate)")
    status_rate_hz: float = spec(50.0, lo=1.0, hi=1000.0, doc="esc.Status rate of each ESC")
    loss: float = spec(0.0, lo=0.0, hi=1.0, hi_open=True, doc="fraction of frames lost")
    corruption: float = spec(0.0, lo=0.0, hi=1.0, hi_open=True,
                             doc="fraction of frames hit by a bit error (error frame, then resent)")


@dataclass(frozen=True)
class LinksSpec:
    """Both links of a run, and the ESC bus when the motors are behind one."""

    command: CommandLinkSpec = spec(factory=CommandLinkSpec,
                                    doc="onboard computer <-> flight controller (MAVLink or DJI OPEN)")
    mocap: MocapLinkSpec = spec(factory=MocapLinkSpec, doc="mocap -> onboard computer (UWB radio)")
    esc_bus: EscBusSpec | None = spec(None, doc="FC -> ESCs over DroneCAN; null: the FC drives the motors")


@dataclass(frozen=True)
class MocapBiasSpec:
    """What the mocap system reports for the gap minus the truth (a mis-measured gap: markers placed
    off, a calibration error). The onboard side sees the biased pose; the world and the checks keep the
    true gap."""

    gap_pos_m: Vec3 = spec(
        (0.0, 0.0, 0.0), lo=-1.0, hi=1.0, doc="error of the gap's reported centre, world ENU"
    )
    gap_roll_deg: float = spec(0.0, lo=-30.0, hi=30.0, doc="error of the gap's reported roll")
    gap_yaw_deg: float = spec(0.0, lo=-30.0, hi=30.0, doc="error of the gap's reported yaw")


@dataclass(frozen=True)
class AirframeSpec:
    """The airframe flown against its profile (a heavier battery, worn propellers); the onboard side is
    still told the profile's mass and thrust, as a real onboard computer would be."""

    mass_scale: float = spec(1.0, lo=0.5, hi=2.0, doc="flown mass / the profile's mass")
    thrust_scale: float = spec(
        1.0, lo=0.5, hi=1.5, doc="flown rotor thrust / the profile's, at every rotor speed (and at 100 %)"
    )


#: the ways a dispersed field is drawn
DISTRIBUTIONS = ("uniform", "normal", "choice")
#: fields a dispersion may not vary: each run draws its own seed; the rest name the scenario
FIXED_FIELDS = ("seed", "name", "description", "dispersions", "skip", "markers", "realtime")


@dataclass(frozen=True)
class Distribution:
    """How one field is drawn for each run: exactly one of ``uniform``, ``normal``, ``choice``. A
    vector field (``[x, y, z]``) draws each component on its own from the same distribution."""

    uniform: tuple[float, float] | None = spec(None, lo=-1e6, hi=1e6, doc="[low, high]")
    normal: tuple[float, float] | None = spec(None, lo=-1e6, hi=1e6, doc="[mean, standard deviation >= 0]")
    choice: tuple[Any, ...] | None = spec(None, doc="values picked with equal chance")
    offset: bool = spec(False, doc="add the draw to the scenario's own value instead of replacing it")
    clip: tuple[float, float] | None = spec(None, lo=-1e6, hi=1e6, doc="[low, high]: draws kept inside")

    @property
    def kind(self) -> str:
        return next(k for k in DISTRIBUTIONS if getattr(self, k) is not None)

    def extremes(self) -> tuple[Any, ...]:
        """Values a draw can reach or is likely to (a normal's mean +- 3 standard deviations, clipped)."""
        if self.choice is not None:
            return self.choice
        if self.uniform is not None:
            lo, hi = self.uniform
        else:
            assert self.normal is not None
            mean, std = self.normal
            lo, hi = mean - 3.0 * std, mean + 3.0 * std
        if self.clip is not None:
            lo, hi = max(lo, self.clip[0]), min(hi, self.clip[1])
        return (lo, hi)


@dataclass(frozen=True)
class GoCriterion:
    """When a dry run says go: the success probability's lower confidence bound at least ``min_success``."""

    min_success: float = spec(0.95, lo=0.0, hi=1.0, doc="success probability a go needs")
    confidence: float = spec(0.95, lo=0.5, hi=1.0, hi_open=True, doc="two-sided level of the interval")


@dataclass(frozen=True)
class Dispersions:
    """Dispersed runs of a scenario (`hil dryrun`): each run draws every field of ``vary`` and a seed of
    its own from one generator seeded with ``seed``. ``vary`` maps a field's path (``gap.roll_deg``,
    ``initial.pos_m[2]``, ``faults[0].params.force_n``, ``wind.speed_m_s``) to its distribution."""

    vary: tuple[tuple[str, Distribution], ...] = ()
    runs: int = spec(100, lo=1, hi=1_000_000, doc="runs when `hil dryrun` is not given --runs")
    seed: int = spec(0, lo=0, hi=2**63 - 1, doc="seed of the generator every run's draws come from")
    go: GoCriterion = spec(factory=GoCriterion, doc="the go/no-go threshold")
    envelope: tuple[str, str] | None = spec(
        None, doc="two paths of `vary` the report maps the pass rate over (default: the first two)"
    )
    bins: int = spec(6, lo=2, hi=50, doc="bins per axis of the envelope map")

    def to_dict(self) -> dict[str, Any]:
        """The block as written in a scenario file."""
        out = _plain(self)
        out["vary"] = {path: {k: v for k, v in _plain(d).items() if v is not None and v is not False}
                       for path, d in self.vary}
        return out


@dataclass(frozen=True)
class EventTime:
    """A time given after a mission event the onboard program reports: that event's sim time + ``s``."""

    after: str = spec(MISSING, choices=MISSION_EVENTS, doc="the mission event")
    s: float = spec(0.0, lo=0.0, hi=600.0, doc="seconds after it")


@dataclass(frozen=True)
class Fault:
    """One scheduled fault, active on sim time [start_s, end_s); end_s None: until the run ends.

    ``onboard_killed`` is written with ``at_s`` in files (an instant: start_s = at_s, end_s None).
    A fault given ``after`` a mission event (``start: {after: approach, s: 0.5}``, ``at:`` for
    onboard_killed) has ``start_s`` inf until the run sees the event (`at_event`); it then lasts
    ``duration_s`` (None: to the end). ``phase`` names the flight phase the fault is meant to hit (by
    default the event's, when the event starts a phase): the runner reports a window that missed it.
    """

    kind: str  # a registered kind (`hil.scenario.fault_kinds.FAULT_KINDS`)
    start_s: float
    end_s: float | None = None
    params: Any = field(default_factory=NoParams)  # the kind's parameters (its ``params`` class)
    after: EventTime | None = None
    duration_s: float | None = None
    phase: str | None = None

    @property
    def instant(self) -> bool:
        """Whether the fault's kind is an instant (``at_s``), not a window."""
        return fault_kind(self.kind).instant

    def active(self, time_s: float) -> bool:
        """Whether the fault acts at sim time ``time_s`` (s)."""
        return time_s >= self.start_s and (self.end_s is None or time_s < self.end_s)

    @property
    def target_phase(self) -> str | None:
        """The flight phase this fault is meant to hit, None when it names none."""
        if self.phase is not None:
            return self.phase
        if self.after is not None and self.after.after in FLIGHT_PHASES:
            return self.after.after
        return None

    def at_event(self, event_s: float, not_before_s: float = 0.0) -> Fault:
        """This fault timed from its mission event, seen at ``event_s`` (sim s); it starts no earlier
        than ``not_before_s`` (when the runner learnt of the event)."""
        if self.after is None:
            return self
        start = max(round(event_s + self.after.s, 9), not_before_s)  # (to the ns: no 3.1399999 s)
        instant = self.duration_s is None or self.instant
        end = None if instant else round(start + self.duration_s, 9)
        return replace(self, start_s=start, end_s=end)

    def to_dict(self) -> dict[str, Any]:
        """The fault as written in a scenario file."""
        out: dict[str, Any] = {"kind": self.kind}
        if self.after is not None:
            out["at" if self.instant else "start"] = _plain(self.after)
            if self.duration_s is not None:
                out["duration_s"] = self.duration_s
        elif self.instant:
            out["at_s"] = self.start_s
        else:
            out["start_s"] = self.start_s
            out["end_s"] = self.end_s
        if self.phase is not None:
            out["phase"] = self.phase
        params = _plain(self.params)
        if params:
            out["params"] = {k: v for k, v in params.items() if v is not None}
        return out


@dataclass(frozen=True)
class RecoveryExpectation:
    """After crossing, the vehicle hovers within radius_m of the recovery point within time_s."""

    radius_m: float = spec(0.5, lo=0.0, hi=10.0, lo_open=True, doc="allowed distance from the hover point")
    time_s: float = spec(4.0, lo=0.0, hi=600.0, lo_open=True, doc="deadline after the crossing")


@dataclass(frozen=True)
class LinkExpectations:
    """Bounds on link statistics over the whole run; null: not checked."""

    mocap_delivered_fraction_min: float | None = spec(None, lo=0.0, hi=1.0, doc="mocap frames delivered")
    command_delivered_fraction_min: float | None = spec(None, lo=0.0, hi=1.0, doc="setpoints delivered")
    mocap_rate_hz_min: float | None = spec(None, lo=0.0, hi=1000.0, lo_open=True, doc="mocap rate at onboard")
    command_rate_hz_min: float | None = spec(None, lo=0.0, hi=1000.0, lo_open=True, doc="setpoint rate at FC")


QUALITY_CHECKS = (
    "heading_error_deg",
    "attitude_tracking_deg",
    "position_error_m",
    "thrust_saturation_s",
    "settling_time_s",
)


@dataclass(frozen=True)
class SegmentErrorLimits:
    """Largest distance from the plan's reference in each segment of the mission (m)."""

    approach: float = spec(0.25, lo=0.0, hi=10.0, lo_open=True, doc="during the approach")
    traverse: float = spec(0.2, lo=0.0, hi=10.0, lo_open=True, doc="during the traverse (through the gap)")
    recovery: float = spec(0.25, lo=0.0, hi=10.0, lo_open=True, doc="during the recovery")


@dataclass(frozen=True)
class HeadingErrorLimits:
    """Largest heading error (deg) to the heading the FC holds itself, and to the commanded one."""

    held: float = spec(3.0, lo=0.0, hi=180.0, lo_open=True, doc="in hold, failsafe hover and landing")
    commanded: float = spec(
        20.0, lo=0.0, hi=180.0, lo_open=True, doc="in offboard (the crossing's recovery takes up to ~17)"
    )


@dataclass(frozen=True)
class QualityExpectations:
    """Flight-quality limits, checked in every run (defaults the shipped suite meets; tighten them here).
    ``expected_failures`` names the checks that must fail: a scenario showing what a check catches."""

    heading_error_deg: HeadingErrorLimits = spec(
        factory=HeadingErrorLimits, doc="heading off the held or the commanded heading"
    )
    # 15: the shipped suite peaks at 9.6 (n3_tx2) and 12.8 (f450, its slower loop), a detuned loop at 20
    attitude_tracking_deg: float = spec(
        15.0, lo=0.0, hi=180.0, lo_open=True, doc="roll or pitch off the command through the FC's nominal lag"
    )
    position_error_m: SegmentErrorLimits = spec(
        factory=SegmentErrorLimits, doc="distance from the plan's reference, per segment"
    )
    thrust_saturation_s: float = spec(
        0.2, lo=0.0, hi=3600.0, doc="time with a motor commanded at full throttle"
    )
    settling_time_s: float = spec(
        0.5, lo=0.0, hi=3600.0, doc="after the takeoff and the crossing, until within 0.1 m of the end point"
    )
    expected_failures: tuple[str, ...] = spec(
        (), choices=QUALITY_CHECKS, doc="quality checks that must fail (names of the checks above)"
    )


@dataclass(frozen=True)
class Expectations:
    """What must hold for the scenario to pass; defaults: crosses, no collision, recovers, stays in lab."""

    crosses_gap: bool = spec(True, doc="the centre passes through the opening")
    min_clearance_m: float | None = spec(None, lo=-1.0, hi=1.0, doc="smallest clearance while in the wall")
    collision_expected: bool = spec(False, doc="a collision must happen (write no_collision: false alike)")
    max_attitude_error_deg: float | None = spec(
        None, lo=0.0, hi=180.0, lo_open=True, doc="attitude error to the gap's orientation at the crossing"
    )
    recovery: RecoveryExpectation | None = spec(
        factory=RecoveryExpectation, doc="hover after crossing; null or false: not checked"
    )
    stays_in_lab: bool = spec(True, doc="never leaves the lab volume")
    failsafe_expected: bool | str = spec(
        False, choices=FAILSAFE_KINDS, doc="the FC must enter a failsafe (true: any; or the kind)"
    )
    onboard_abort_expected: bool | None = spec(
        False, doc="the onboard program must abort the crossing (null: not checked)"
    )
    link: LinkExpectations = spec(factory=LinkExpectations, doc="link-statistics bounds")
    realtime_max_late_ms: float = spec(
        REALTIME_MAX_LATE_MS, lo=0.0, hi=10_000.0, lo_open=True,
        doc="real-time runs: the emulator loop's worst lateness against the wall clock (ms)",
    )
    quality: QualityExpectations = spec(factory=QualityExpectations, doc="flight-quality limits")
    refused: bool = spec(
        False, doc="the pre-flight check refuses the gap, too small for the body (never flown)"
    )
    #: the fields registered checks added (`hil.scenario.expect_fields.EXPECT_FIELDS`), (name, value), each
    #: registered one present (its default unless given); read them as attributes (``e.my_field``)
    extra: tuple[tuple[str, Any], ...] = ()

    INTERNAL_FIELDS = ("extra",)

    def __post_init__(self) -> None:
        given = dict(self.extra)
        values = {name: given.pop(name, f.default) for name, f in EXPECT_FIELDS.items()}
        object.__setattr__(self, "extra", tuple({**values, **given}.items()))

    def __getattr__(self, name: str) -> Any:
        """A registered check's field (`extra`)."""
        for key, value in self.__dict__.get("extra", ()):
            if key == name:
                return value
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @classmethod
    def own_fields(cls) -> tuple[str, ...]:
        """The project's own fields (those registered checks add are in `extra`)."""
        return tuple(f.name for f in fields(cls) if f.name not in cls.INTERNAL_FIELDS)

    def to_dict(self) -> dict[str, Any]:
        """The block as written in a scenario file (added fields beside the project's own)."""
        return {**{name: _plain(getattr(self, name)) for name in self.own_fields()},
                **{name: _plain(value) for name, value in self.extra}}


@dataclass(frozen=True)
class Scenario:
    """One scenario document, validated. ``id`` is the ``name`` field or the file stem (+ ``-index``)."""

    id: str
    description: str
    source: str = "<string>"  # the file it came from
    line: int = 1  # line of the document's first field (1-based)
    index: int = 0  # position of the document in its file
    name: str | None = None
    vehicle: str = DEFAULT_VEHICLE
    physics: str = DEFAULT_PHYSICS
    gap: GapSpec = field(default_factory=GapSpec)
    lab: LabSpec = field(default_factory=LabSpec)
    initial: InitialState = field(default_factory=InitialState)
    pilot: str = "traditional"
    approach: ApproachSpec = field(default_factory=ApproachSpec)
    links: LinksSpec = field(default_factory=LinksSpec)
    #: FC parameters set before the flight (name, value), by their MAVLink names (`emulator.params`)
    params: tuple[tuple[str, float], ...] = ()
    faults: tuple[Fault, ...] = ()
    seed: int = 0
    duration_s: float = 8.0
    onboard_compute_ms: float | None = None
    realtime: bool = False
    skip: str | None = None
    markers: tuple[str, ...] = ()
    expect: Expectations = field(default_factory=Expectations)
    mocap_bias: MocapBiasSpec = field(default_factory=MocapBiasSpec)
    airframe: AirframeSpec = field(default_factory=AirframeSpec)
    dispersions: Dispersions | None = None

    META_FIELDS = ("id", "source", "line", "index")

    def to_dict(self, include_meta: bool = True) -> dict[str, Any]:
        """Plain JSON/YAML-ready dict; without meta it is a valid scenario document again."""
        out: dict[str, Any] = {}
        for f in fields(self):
            if f.name in self.META_FIELDS and not include_meta:
                continue
            value = getattr(self, f.name)
            if f.name == "faults":
                out["faults"] = [fault.to_dict() for fault in value]
            elif f.name == "params":
                out["params"] = dict(value)
            elif f.name == "dispersions":
                out[f.name] = None if value is None else value.to_dict()
            elif f.name == "expect":
                out[f.name] = value.to_dict()
            else:
                out[f.name] = _plain(value)
        return out


# Top-level fields of a document with their ranges (the rest are nested dataclasses).
SCENARIO_LIMITS: dict[str, dict[str, Any]] = {
    "seed": {"lo": 0, "hi": 2**63 - 1, "doc": "seed of every random draw in the run"},
    "duration_s": {"lo": 0.0, "hi": 3600.0, "lo_open": True, "doc": "simulated time the run lasts"},
    "onboard_compute_ms": {
        "lo": 0.0,
        "hi": 100.0,
        "doc": "lockstep: sim time from a tick to the onboard computer's outputs; null: one tick",
    },
}


def _plain(value: Any) -> Any:
    """Dataclasses -> dicts, tuples -> lists, recursively."""
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value
