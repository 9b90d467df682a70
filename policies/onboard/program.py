"""The onboard program: the mission state machine that flies a pilot through the gap over the links.

Phases: wait for mocap and the FC -> take control authority (stream setpoints, DO_SET_MODE OFFBOARD,
wait for the ACK and the heartbeat's mode) -> arm -> take off and settle (expert controller) -> the
mission (approach -> traverse -> recovery -> hover, flown by the pilot) -> hand back to the FC's HOLD.

Driven by time, not by sleeping: `step(now_s)` does everything due at ``now_s`` and returns at once.
`run_realtime()` calls it on the wall clock, waiting on the command link's fd and its own schedule;
`run_lockstep()` takes its clock from the FC's TIMESYNC ticks and answers each tick once its outputs
are sent. On either clock the mocap link is read at the control steps (in lockstep: at the ticks they
fall on), each pose stamped with that moment: a program that read each pose as it came would predict
from estimates a few ms fresher in real time than lockstep can model, and cross closer to the wall
(docs/notes/realtime-vs-lockstep.md).

Safe hover on stale mocap (no vehicle pose taken by the state estimator for ``stale_mocap_s``: poses the
mocap reader or the estimator refuse, non-finite, from the future, out of order, do not count as fresh;
see `policies.mocap_reader`; when the latest were poses the vehicle cannot have flown to, a glitch of the
tracker, the reason is "implausible_mocap"), on a gap pose that cannot be used or that has moved for
``stale_mocap_s`` ("implausible_gap_pose": the gap stands still), or on a command that is not finite
(refused, never sent): one level-attitude setpoint
at hover thrust (m g) is sent at once and repeated every control period, and DO_SET_MODE AUTO.LOITER
(PX4 Hold) is sent until the FC's heartbeat shows it; from then the FC holds the vehicle on its own and
the program stops ("abort" then "hold" events, exit code 3).

Actuation lead: the FC reaches a commanded attitude with a lag (the emulated N3 answers a 20 deg roll
step with an equivalent lag of about 0.09 s), which takes most of the phase margin of the expert's
lightly damped position loop (zeta ~0.3 by design) and left a +-0.2 m, 1.6 s ringing after every
manoeuvre. Each control step therefore computes its command for ``control_lead_s`` ahead: the state
estimate predicted that far and the reference taken that far along, so that the attitude is right
when the FC gets there.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import select
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from enum import StrEnum
from typing import IO, Any

import numpy as np

from hil.link.clock import WallClock
from hil.link.linktrack import BODY_IDS
from hil.link.mavlink import mav
from hil.link.transport import LinkError, Transport, wait_readable
from policies.controller import (
    EXPERT_LAW,
    EXPERT_LAW_ROWS,
    AttitudeThrustCommand,
    ExpertController,
    ExpertGains,
    gains_array,
    limit_tilt_step,
)
from policies.frames import GRAVITY_M_S2
from policies.gap_planning import (
    _PLAN_APPROACH,
    _PLAN_RECOVERY,
    PLAN_FLOATS,
    PLAN_POLY_FLOATS,
    PLAN_REFERENCE,
    BodyClearance,
    GapPose,
    LabVolume,
    MissionPlan,
    MissionRequest,
    PlanningError,
    Segment,
    VehicleLimits,
    poly_packed,
    start_plan,
)
from policies.mocap_reader import MocapReader
from policies.onboard.command_link import SETPOINT_WIRE
from policies.onboard.command_links import COMMAND_LINKS, OnboardLink
from policies.onboard.dji_command_link import SETPOINT_ANGLES
from policies.onboard.estimator import (
    STATE_FLOATS,
    EstimatorConfig,
    PoseEstimator,
    StaticPoseCheck,
    plausible_jump_m,
)
from policies.onboard.mocap_intake import mocap_intake
from policies.onboard.pilots import FloatObservation, Pilot, PilotContext, make_pilot
from policies.onboard.pilots.traditional import (
    TAKEOFF_STEP,
    TRADITIONAL_COMMAND,
    TRADITIONAL_STEP,
    plan_with_gains,
    takeoff_heading,
)
from policies.primitives import solve
from policies.vehicle import TRAVERSE_LEAD_M

MIN_RATE_HZ = 50.0  # the N3 expects setpoints at 50 Hz at least
HEARTBEAT_REQUEST_S = 0.1  # how often the FC's heartbeat is asked for until one comes (s)
VEHICLE_BODY_ID = BODY_IDS["vehicle"]  # the mocap body whose poses feed the estimator
GAP_BODY_ID = BODY_IDS["gap"]
#: a gap pose turned more than this from the gap's first is refused (a mocap's attitude noise is ~0.1 deg)
GAP_TURN_LIMIT_RAD = math.radians(2.0)
EXIT_DONE, EXIT_ERROR, EXIT_ABORTED = 0, 1, 3


class Phase(StrEnum):
    """Where the program is."""

    WAIT = "wait"  # for fresh mocap of vehicle and gap, and the FC's heartbeat
    AUTHORITY = "authority"  # streaming setpoints, asking for OFFBOARD
    ARMING = "arming"
    TAKEOFF = "takeoff"  # climb to the start height, turn to the mission heading, settle
    MISSION = "mission"  # approach -> traverse -> recovery -> hover, flown by the pilot
    HANDBACK = "handback"  # mission over: asking the FC to HOLD
    ABORTING = "aborting"  # safe hover: level, hover thrust, asking the FC to HOLD
    DONE = "done"
    ABORTED = "aborted"
    FAILED = "failed"


#: what `step` does in each active phase (a method name of OnboardProgram)
_PHASE_HANDLERS = {
    Phase.WAIT: "_wait",
    Phase.AUTHORITY: "_authority",
    Phase.ARMING: "_arming",
    Phase.TAKEOFF: "_takeoff_progress",
    Phase.MISSION: "_mission_progress",
    Phase.HANDBACK: "_handback",
    Phase.ABORTING: "_aborting",
}


#: (a set: the per-tick paths ask whether the phase is one of them five times a tick, and a tuple compares
#: the phase with each member as strings)
FINAL_PHASES = frozenset({Phase.DONE, Phase.ABORTED, Phase.FAILED})
# the members the per-tick paths compare with, as module constants (Python 3.11 reads a member through its
# class with a descriptor call, about 0.4 us: a dozen a tick)
_WAIT, _ABORTING, _TAKEOFF = Phase.WAIT, Phase.ABORTING, Phase.TAKEOFF
#: the phases with a vehicle state to keep fresh (a stale one aborts), and those streaming a level setpoint
_FRESH_STATE = frozenset({Phase.AUTHORITY, Phase.ARMING, Phase.TAKEOFF, Phase.MISSION, Phase.HANDBACK})
_LEVEL = frozenset({Phase.AUTHORITY, Phase.ARMING})
_PILOTED = frozenset({Phase.MISSION, Phase.HANDBACK})  # the pilot's commands
_APPROACH = Segment.APPROACH


@dataclass(frozen=True)
class ProgramConfig:
    """Settings of the onboard program (SI units)."""

    pilot: str = "traditional"
    fc_protocol: str = "mavlink"  # what the FC speaks on the command link (`COMMAND_LINKS`)
    rate_hz: float = 100.0  # control rate; >= 50 Hz (the N3's minimum)
    approach_speed_m_s: float = 2.0  # speed through the gap centre
    approach_duration_s: float = 2.6
    # the traverse starts at least this far before the gap plane (d_min; the paper: 0.1 m): the vehicle's
    # (policies.vehicle: 0.25 m lets the n3_tx2's FC finish most of the roll into the gap's tilt before
    # its 0.52 m body reaches the wall)
    traverse_lead_m: float = TRAVERSE_LEAD_M
    stale_mocap_s: float = 0.1  # vehicle pose older than this: abort to a safe hover
    # the vehicle as the onboard side knows it (its own configuration, policies.vehicle; n3_tx2's here)
    mass_kg: float = 0.9
    full_thrust_n: float = 24.0  # thrust at N3 100 % (the vehicle's n3_full_thrust_n)
    max_tilt_deg: float = 75.0  # the expert's tilt limit (takeoff, mission, hover)
    gap_width_m: float = 0.8  # the opening's size (mocap gives its pose only)
    gap_height_m: float = 0.45
    lab_min_m: tuple[float, float, float] = (-5.0, -5.0, 0.0)
    lab_max_m: tuple[float, float, float] = (5.0, 5.0, 4.0)
    #: the vehicle's collision box, length x width x height in body FLU (m; the paper's vehicle), and the
    #: margin (m) the plan keeps beyond its reach from the floor, the lab's faces and the wall
    body_box_m: tuple[float, float, float] = (0.52, 0.52, 0.18)
    clearance_margin_m: float = 0.05
    takeoff_height_m: float = 0.5  # climb at least to this height (m, world z) before the mission
    takeoff_duration_s: float = 2.5
    settle_s: float = 1.0  # hold the start point this long before planning
    hover_s: float = 2.0  # hover at the end point this long before handing back
    wait_timeout_s: float = 10.0  # for mocap and the FC at the start
    command_timeout_s: float = 3.0  # for an ACK and the mode to show in the heartbeat
    command_retry_s: float = 0.5
    stream_before_offboard_s: float = 0.3  # setpoints streamed before asking for OFFBOARD
    fc_lost_s: float = 3.0  # FC heartbeat silence that ends the program
    heartbeat_period_s: float = 1.0
    max_catch_up_steps: int = 3  # control steps run at once after a stall; later ones are skipped
    control_lead_s: float = 0.06  # state and reference taken this far ahead (the FC's attitude lag)
    #: the body rate the vehicle's FC turns it at, at most (rad/s): plans within it are preferred; below the
    #: planner's limits, the start height is chosen for the approach and, from the traverse on, the command
    #: turns no faster
    max_body_rate_rad_s: float = VehicleLimits.max_body_rate_rad_s
    #: lockstep: wall time (s) to poll for the next tick before sleeping (it usually comes within it)
    lockstep_spin_s: float = 1e-3
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)

    def __post_init__(self) -> None:
        if self.fc_protocol not in COMMAND_LINKS:
            raise ValueError(f"FC protocol must be one of {', '.join(COMMAND_LINKS)}, "
                             f"got {self.fc_protocol!r}")
        if not (math.isfinite(self.lockstep_spin_s) and 0.0 <= self.lockstep_spin_s <= 0.1):
            raise ValueError(f"lockstep spin must be 0..100000 us, got {self.lockstep_spin_s * 1e6:g}")
        if not (math.isfinite(self.rate_hz) and self.rate_hz >= MIN_RATE_HZ):
            raise ValueError(f"rate_hz must be >= {MIN_RATE_HZ:g} Hz (the N3's minimum), got {self.rate_hz}")
        if not (math.isfinite(self.approach_speed_m_s) and 0 < self.approach_speed_m_s <= 6):
            raise ValueError(f"approach speed must be in (0, 6] m/s, got {self.approach_speed_m_s}")
        for name in ("approach_duration_s", "traverse_lead_m", "stale_mocap_s", "mass_kg", "full_thrust_n",
                     "max_body_rate_rad_s", "gap_width_m", "gap_height_m", "takeoff_duration_s",
                     "wait_timeout_s", "command_timeout_s", "command_retry_s", "fc_lost_s",
                     "heartbeat_period_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.control_lead_s) and 0 <= self.control_lead_s <= 0.2):
            raise ValueError(f"control_lead_s must be in [0, 0.2] s, got {self.control_lead_s!r}")
        for name in ("settle_s", "hover_s", "stream_before_offboard_s", "takeoff_height_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be >= 0, got {v!r}")
        if not (math.isfinite(self.max_tilt_deg) and 0 < self.max_tilt_deg < 90):
            raise ValueError(f"max_tilt_deg must be in (0, 90), got {self.max_tilt_deg!r}")
        if self.mass_kg * GRAVITY_M_S2 >= self.full_thrust_n:
            raise ValueError(f"full thrust {self.full_thrust_n} N cannot hold {self.mass_kg} kg")
        LabVolume(self.lab_min_m, self.lab_max_m)  # validates
        BodyClearance(self.body_box_m, self.clearance_margin_m)  # validates

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def hover_thrust_n(self) -> float:
        return self.mass_kg * GRAVITY_M_S2


def mission_request(cfg: ProgramConfig, pos_m: np.ndarray, vel_m_s: np.ndarray,
                    gap: GapPose) -> MissionRequest:
    """The mission a program of ``cfg`` plans from ``pos_m`` (m) at ``vel_m_s`` (m/s) through ``gap`` (its
    `plan` is the plan; its `to_dict` goes into the plan event)."""
    return MissionRequest(tuple(map(float, pos_m)), tuple(map(float, vel_m_s)), gap,
                          LabVolume(cfg.lab_min_m, cfg.lab_max_m), cfg.approach_duration_s,
                          cfg.approach_speed_m_s, cfg.traverse_lead_m,
                          BodyClearance(cfg.body_box_m, cfg.clearance_margin_m), cfg.max_body_rate_rad_s)


def pre_takeoff_check(cfg: ProgramConfig, pos_m: object, gap: GapPose) -> float:
    """The height (m, world z) a program of ``cfg`` on the ground at ``pos_m`` (m) starts its mission
    through ``gap`` from (`start_height`, from where its climb ends), once it has planned the mission from
    there (it plans again when it gets there); PlanningError when there is no plan, PassageError when the
    plan crosses at a speed the body cannot pass the opening at (`MissionRequest.checked_plan`)."""
    start = np.array(pos_m, dtype=float)
    start[2] = max(start[2], cfg.takeoff_height_m)
    request = mission_request(cfg, start, np.zeros(3), gap)
    z, plan = start_plan(request)  # (from the start itself: the plan `start_height` made, not planned again)
    replace(request, start_pos_m=(float(start[0]), float(start[1]), z)).checked(plan)
    return z


class ProgramClock:
    """The program's notion of now (s): set by `step` (wall time or the latest lockstep tick)."""

    def __init__(self) -> None:
        self.t_s = 0.0  # (what `now_s` gives)

    def now_s(self) -> float:
        return self.t_s

    def set(self, t_s: float) -> None:
        self.t_s = t_s


class EventLog:
    """Mission events as JSON lines ({"event": ..., "t_s": ..., ...}) to a stream and/or a file."""

    def __init__(self, stream: IO[str] | None = None, path: str | None = None) -> None:
        self.stream = stream
        self._file = open(path, "w", encoding="utf-8") if path else None  # noqa: SIM115
        self.events: list[dict[str, Any]] = []

    def emit(self, name: str, t_s: float, **fields: Any) -> dict[str, Any]:
        event = {"event": name, "t_s": round(t_s, 4), **fields}
        self.events.append(event)
        line = json.dumps(event, default=_jsonable)
        for out in (self.stream, self._file):
            if out is not None:
                out.write(line + "\n")
                out.flush()
        return event

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def _jsonable(x: object) -> object:
    if isinstance(x, np.ndarray):
        return [round(float(v), 4) for v in x]
    if isinstance(x, np.floating | np.integer):
        return x.item()
    return str(x)


class _Request:
    """A command sent until the FC acknowledges it and ``done()`` holds, or until a deadline."""

    def __init__(self, command: int, send: Callable[[], None], done: Callable[[], bool], now_s: float,
                 timeout_s: float, retry_s: float) -> None:
        self.command, self._send, self.done = command, send, done
        self.deadline_s = now_s + timeout_s
        self.retry_s = retry_s
        self.next_send_s = now_s
        self.tries = 0

    def update(self, link: OnboardLink, now_s: float) -> bool | None:
        """True when done, False when timed out, None while pending (sends or resends as due)."""
        ack = link.acks.get(self.command)
        if ack is not None and ack.accepted and self.done():
            return True
        if now_s >= self.deadline_s:
            return False
        if now_s >= self.next_send_s and (self.tries == 0 or ack is None or not ack.accepted):
            self._send()
            self.tries += 1
            self.next_send_s = now_s + self.retry_s
        return None


@functools.cache
def warm_kernels() -> None:
    """Compile (or load from the cache) every kernel the program calls (`policies.compiling`), for the
    argument types it passes; once a process (a process forked after it has them)."""
    g = gains_array(ExpertGains())
    EXPERT_LAW.get()(*(0.0,) * 16, 0.9, g)
    one = np.zeros((1, 3))
    EXPERT_LAW_ROWS.get()(one, one, one, one, one, np.zeros(1), 0.9, g, np.empty((1, 3)))
    plan = np.zeros(PLAN_FLOATS)
    plan[[_PLAN_APPROACH, _PLAN_RECOVERY]] = 6.0
    plan.flags.writeable = False  # (as `MissionPlan.packed`: numba compiles a read-only array apart)
    for t in (-1.0, 0.0, 1.0):
        PLAN_REFERENCE.get()(plan, t)
        TRADITIONAL_COMMAND.get()(plan_with_gains(plan, g), t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.9)
        TRADITIONAL_STEP.get()(plan_with_gains(plan, g), 0.9, np.zeros(STATE_FLOATS), t, t, 0.0, 0.0, 0.1)
        TAKEOFF_STEP.get()(plan_with_gains(plan[_PLAN_APPROACH:_PLAN_RECOVERY], g), 0.9,
                           np.zeros(STATE_FLOATS), t, t, 0.0, 2.5, 0.0, 1.0)
    est = PoseEstimator(max_accel_m_s2=30.0)  # (its arrays: the program's argument types)
    for k in range(3):
        est.take(k * 0.01, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), k * 0.01 + 0.03)
    est.state_tuples(0.05)
    mocap_intake(est, StaticPoseCheck(0.1, 0.1))  # (the mocap intake, for the estimator's and the check's)
    SETPOINT_WIRE.entry(0.0, 0.0, 0.0, 0.0)  # (the command links' setpoint numbers)
    SETPOINT_ANGLES.entry(0.0, 0.0, 0.0, 0.0)


class OnboardProgram:
    """The onboard program on a command link (MAVLink to the FC) and a mocap link (LinkTrack frames)."""

    def __init__(self, command_transport: Transport, mocap_transport: Transport,
                 config: ProgramConfig | None = None, *, pilot: Pilot | None = None,
                 events: EventLog | None = None) -> None:
        self.config = cfg = config or ProgramConfig()
        warm_kernels()  # (once a process: no control step waits for a kernel's compilation or cache load)
        self.clock = ProgramClock()
        self.link: OnboardLink = COMMAND_LINKS[cfg.fc_protocol](command_transport, self.clock)
        self.estimator = PoseEstimator(cfg.estimator, cfg.full_thrust_n / cfg.mass_kg + GRAVITY_M_S2)
        noise_jump_m = plausible_jump_m(0.0, 0.0, 0.0, cfg.estimator.jump_sigmas, cfg.estimator.pos_noise_m)
        self.gap_check = StaticPoseCheck(noise_jump_m, GAP_TURN_LIMIT_RAD)
        # (the usual mocap bytes into the estimator and the gap check in one compiled call, the rest
        # through `_on_pose`)
        self.mocap = MocapReader(mocap_transport, self.clock, cfg.stale_mocap_s, on_pose=self._on_pose,
                                 intake=mocap_intake(self.estimator, self.gap_check))
        self.pilot = pilot or make_pilot(
            cfg.pilot, PilotContext(cfg.mass_kg, cfg.full_thrust_n, max_tilt_deg=cfg.max_tilt_deg)
        )
        self.expert = ExpertController(cfg.mass_kg, ExpertGains(tilt_max_rad=math.radians(cfg.max_tilt_deg)))
        self.events = events or EventLog()
        self.lab = LabVolume(cfg.lab_min_m, cfg.lab_max_m)
        self.body = BodyClearance(cfg.body_box_m, cfg.clearance_margin_m)
        self.phase = Phase.WAIT
        self.exit_code: int | None = None
        self.plan: MissionPlan | None = None
        self.gap: GapPose | None = None
        self.segment: Segment | None = None
        self._segment_end_s = -math.inf  # (mission time, s) until which `segment` holds
        self.control_steps = 0
        self.skipped_steps = 0
        self.commands_refused = 0  # setpoints not sent for not being finite
        self._started_s: float | None = None
        self._phase_since_s = 0.0
        self._next_control_s: float | None = None
        self._mocap_read_s = -math.inf  # when `step` last read the mocap link (s)
        self._next_heartbeat_s = -math.inf
        self._next_heartbeat_request_s = -math.inf  # (while waiting for the FC's first heartbeat)
        self._clock_zero_monotonic_s: float | None = None  # on the wall clock only (`run_realtime`)
        self._request: _Request | None = None
        self._mission_start_s = 0.0
        #: trajectory, its `poly_packed` form followed by the expert's gains (`plan_with_gains`), yaw0, yaw1,
        #: start
        self._takeoff: tuple[Any, np.ndarray, float, float, float] | None = None
        # (the take-off's step compiled for a packed trajectory with the expert's gains, the estimator's
        # state array and floats: no dispatch a step)
        self._gains, self._mass_kg = self.expert.gains_array, self.expert.mass_kg
        self._takeoff_step = TAKEOFF_STEP.entry(plan_with_gains(np.zeros(PLAN_POLY_FLOATS), self._gains), 0.0,
                                                self.estimator.state, *(0.0,) * 6)
        self._takeoff_duration_s = cfg.takeoff_duration_s
        self._start_height_m = 0.0  # the mission's start height (m, world z) chosen before the take-off
        # the most the commanded roll and pitch move in a control step from the traverse on (rad; the
        # vehicle's body rate times the period), so that the pull-out asks no faster turn than the FC makes:
        # a command swinging across from its tilt limit in 0.1 s is one the f450's FC trails by 20 deg, and
        # at 70 deg the n3's command swung 10-20 deg a tick while the body was still turning through level
        self._tilt_step_rad = cfg.max_body_rate_rad_s * cfg.period_s
        self._lead_s = cfg.control_lead_s
        self._period_s = cfg.period_s  # (the control period, s: a property of the frozen config, read once)
        # (the frozen config's and the link's per-tick numbers and method, bound once)
        self._stale_mocap_s, self._full_thrust_n = cfg.stale_mocap_s, cfg.full_thrust_n
        self._fc_lost_s = cfg.fc_lost_s
        self._heartbeat_period_s, self._max_catch_up_steps = cfg.heartbeat_period_s, cfg.max_catch_up_steps
        self._send_attitude_target = self.link.send_attitude_target
        self._gap_update, self._estimator_take = self.gap_check.update, self.estimator.take  # (per pose)
        self._abort_yaw = 0.0  # heading (rad, ENU) of the level setpoints: as first seen, or at an abort
        #: the latest setpoint sent: roll, pitch, yaw (rad), thrust (N) (the tilt-step limit's start); None
        #: before one
        self._last_setpoint: tuple[float, float, float, float] | None = None
        #: the pilot's control step on the plan as one compiled call (`Pilot.compiled_step`), when it offers
        #: one; with the estimator's state array it reads
        self._pilot_step: Callable[..., tuple[float, float, float, float]] | None = None
        self._estimator_state = self.estimator.state
        self._last_tick_s = -math.inf  # the latest lockstep tick acted on (s)
        self._summary_logged = False
        self._handlers = {ph: getattr(self, name) for ph, name in _PHASE_HANDLERS.items()}  # (bound once)

    # --- the step ---------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        return self.phase in FINAL_PHASES

    def step(self, now_s: float) -> None:
        """Do everything due at ``now_s`` (s, the program's clock) without blocking."""
        self.clock.set(now_s)
        try:
            self.link.read()
            self.link.take_ticks()  # only meaningful in lockstep (see `lockstep_tick`)
            if now_s >= self._mocap_due_s():
                self.mocap.poll()
                self._mocap_read_s = now_s
        except LinkError as exc:
            self._finish(Phase.FAILED, EXIT_ERROR, "link_lost", reason=str(exc))
            return
        self._act(now_s)

    def lockstep_tick(self, tick_s: float, *, repeat: bool = False) -> None:
        """One lockstep tick: read the mocap link up to what the harness has announced (all that has
        arrived when it does not say), act at ``tick_s``, then answer the tick. A ``repeat`` (a tick acted
        on before) is read and answered, not acted on, and leaves the clock where it is."""
        if not repeat:
            self.clock.t_s = tick_s  # (`ProgramClock.set`, without the call: per tick)
        link, mocap = self.link, self.mocap
        try:
            announced = link.mocap_announced
            if announced is None:
                mocap.poll()
            else:
                short = mocap.lockstep_short_reads
                mocap.poll_to(announced)
                if mocap.lockstep_short_reads != short:
                    # the bytes the harness announced did not arrive: from here the run is not the
                    # scenario's deterministic run any more, which the harness must be told (it fails its
                    # lockstep check)
                    self.events.emit("lockstep_lost", self.clock.now_s(),
                                     short_reads=mocap.lockstep_short_reads)
        except LinkError as exc:
            self._finish(Phase.FAILED, EXIT_ERROR, "link_lost", reason=str(exc))
            return
        if not repeat:
            self._act(tick_s)
        link.answer_tick(tick_s)

    def _mocap_due_s(self) -> float:
        """When `step` next reads the mocap link (s): at the next control step, as lockstep reads it at
        the tick the step falls on; every control period while no step is scheduled."""
        if self._next_control_s is not None:
            return self._next_control_s
        return self._mocap_read_s + self.config.period_s

    def next_wake_s(self) -> float:
        """When `step` next has something to do if no command-link input arrives (s)."""
        return min(self._next_heartbeat_s, self._mocap_due_s())

    def _act(self, now_s: float) -> None:
        if self.phase in FINAL_PHASES:  # (`finished` without the property's calls, here and below: per tick)
            return
        if self._started_s is None:
            self._started_s = self._phase_since_s = now_s
            self.events.emit("start", now_s, pilot=self.config.pilot, rate_hz=self.config.rate_hz,
                             approach_speed_m_s=self.config.approach_speed_m_s,
                             flies=getattr(self.pilot, "flies", None),  # (a pilot that says)
                             clock_zero_monotonic_s=self._clock_zero_monotonic_s)
        if now_s >= self._next_heartbeat_s:
            self.link.send_heartbeat()
            self._next_heartbeat_s = now_s + self._heartbeat_period_s
        # the phase logic, in the order its checks win: the FC lost, stale mocap, an implausible gap pose,
        # then the phase's own progress (one place a tick: no call of its own)
        ph = self.phase
        est = self.estimator
        gap = self.gap_check
        if ph is not _WAIT and self.link.heartbeat_age_s(now_s) > self._fc_lost_s:
            self._finish(Phase.FAILED, EXIT_ERROR, "fc_lost", phase=str(ph),
                         silence_s=round(self.link.heartbeat_age_s(now_s), 3))
        elif ph in _FRESH_STATE and not est.age_s(now_s) <= self._stale_mocap_s:  # (`_mocap_fresh`)
            if est.implausible_run:  # the poses came, but none the vehicle could have flown to
                self._abort(now_s, "implausible_mocap", age_s=round(est.age_s(now_s), 4),
                            refused=est.implausible_run, jump_m=round(est.latest_jump_m, 3))
            else:
                self._abort(now_s, "stale_mocap", age_s=round(est.age_s(now_s), 4))
        elif ph is not _ABORTING and gap.implausible_run and now_s - gap.received_s > self._stale_mocap_s:
            self._abort(now_s, "implausible_gap_pose", refused=gap.implausible_run,
                        jump_m=round(gap.latest_jump_m, 3))
        else:
            handler = self._handlers.get(ph)
            if handler is not None:  # the final phases have none
                handler(now_s)
        if self.phase in FINAL_PHASES or self._next_control_s is None:
            return
        period = self._period_s
        steps = 0
        while self._next_control_s <= now_s and self.phase not in FINAL_PHASES:
            if steps >= self._max_catch_up_steps:
                missed = math.floor((now_s - self._next_control_s) / period) + 1
                self.skipped_steps += missed
                self._next_control_s += missed * period
                break
            self._control(self._next_control_s, now_s)
            self._next_control_s += period
            steps += 1

    # --- phase logic ------------------------------------------------------------------------
    def _go(self, phase: Phase, now_s: float) -> None:
        self.phase = phase
        self._phase_since_s = now_s

    def _finish(self, phase: Phase, code: int, event: str, /, **fields: Any) -> None:
        self.events.emit(event, self.clock.now_s(), **fields)
        self.phase = phase
        self.exit_code = code

    def _mocap_fresh(self, now_s: float) -> bool:
        """Whether the estimator has taken a vehicle pose within ``stale_mocap_s`` of ``now_s``."""
        return self.estimator.age_s(now_s) <= self._stale_mocap_s

    def _wait(self, now_s: float) -> None:
        cfg = self.config
        gap_ok = not self.mocap.is_stale("gap") and self.gap_check.pose is not None
        fc_ok = self.link.status is not None
        if self._mocap_fresh(now_s) and gap_ok and fc_ok:
            est = self.estimator.estimate(now_s)
            gap = self.gap_check.pose
            assert gap is not None
            self.events.emit("mocap_ok", now_s, vehicle_pos_m=est.pos_m, gap_centre_m=gap[0],
                             fc_armed=self.link.status.armed)  # type: ignore[union-attr]
            self._abort_yaw = float(est.euler_rad[2])
            # before taking off: a plan from where the climb ends must exist (it is planned again there);
            # a slow vehicle climbs higher where its approach needs the room (`start_height`)
            gap_pose = self._gap_pose(now_s)
            if gap_pose is None:
                return  # (aborted, naming why)
            try:
                self._start_height_m = pre_takeoff_check(cfg, est.pos_m, gap_pose)
            except (PlanningError, ValueError) as exc:
                self._abort(now_s, "planning_failed", detail=str(exc))  # landed: ends; flying: holds
                return
            self._go(Phase.AUTHORITY, now_s)
            self._next_control_s = now_s
            return
        if not fc_ok and now_s >= self._next_heartbeat_request_s:
            self.link.request_heartbeat()
            self._next_heartbeat_request_s = now_s + HEARTBEAT_REQUEST_S
        if now_s - self._phase_since_s > cfg.wait_timeout_s:
            self._finish(Phase.FAILED, EXIT_ERROR, "error", reason="timed out waiting for mocap and the FC",
                         vehicle_mocap=self.estimator.ready, gap_mocap=gap_ok, fc_heartbeat=fc_ok,
                         status_texts=self.link.status_texts[-3:])  # (a refused activation says so)

    def _authority(self, now_s: float) -> None:
        if self._request is None:
            if now_s - self._phase_since_s < self.config.stream_before_offboard_s:
                return
            self._request = self._new_request(mav.MAV_CMD_DO_SET_MODE, self.link.request_offboard, now_s,
                                              lambda: self._fc("offboard"))
        done = self._request.update(self.link, now_s)
        if done:
            self.events.emit("authority", now_s, tries=self._request.tries)
            self._request = None
            if self._fc("armed"):
                self.events.emit("armed", now_s, already=True)
                self._start_takeoff(now_s)
            else:
                self._go(Phase.ARMING, now_s)
        elif done is False:
            self._request = None
            self._finish(Phase.FAILED, EXIT_ERROR, "error", reason="FC did not grant OFFBOARD",
                         status_texts=self.link.status_texts[-3:])

    def _arming(self, now_s: float) -> None:
        if self._request is None:
            self._request = self._new_request(mav.MAV_CMD_COMPONENT_ARM_DISARM, self.link.request_arm, now_s,
                                              lambda: self._fc("armed"))
        done = self._request.update(self.link, now_s)
        if done:
            self.events.emit("armed", now_s, tries=self._request.tries)
            self._request = None
            self._start_takeoff(now_s)
        elif done is False:
            self._request = None
            self._finish(Phase.FAILED, EXIT_ERROR, "error", reason="FC did not arm",
                         status_texts=self.link.status_texts[-3:])

    def _new_request(self, command: int, send: Callable[[], None], now_s: float,
                     done: Callable[[], bool]) -> _Request:
        cfg = self.config
        return _Request(command, send, done, now_s, cfg.command_timeout_s, cfg.command_retry_s)

    def _fc(self, what: str) -> bool:
        """Whether the FC's last heartbeat says ``what`` ("armed", "offboard", "holding")."""
        return self.link.status is not None and bool(getattr(self.link.status, what))

    def _mission_yaw(self, pos_m: np.ndarray, gap: GapPose) -> float:
        """Heading along the crossing direction (the gap normal pointing away from ``pos_m``)."""
        side = float((pos_m - gap.centre) @ gap.e1)
        u = gap.e1 * (-1.0 if side > 0 else 1.0)
        return math.atan2(float(u[1]), float(u[0]))

    def _gap_pose(self, now_s: float) -> GapPose | None:
        """The gap from its latest mocap pose; None, after an abort naming why, when there is none or it
        cannot be used."""
        g = self.gap_check.pose  # the latest pose of the gap that lies where it was first seen
        try:
            if g is None:
                raise ValueError("no gap pose received")
            return GapPose.from_quaternion(g[0], g[1], width_m=self.config.gap_width_m,
                                           height_m=self.config.gap_height_m)
        except ValueError as exc:
            self._abort(now_s, "bad_gap_pose", detail=str(exc))
            return None

    def _start_takeoff(self, now_s: float) -> None:
        cfg = self.config
        est = self.estimator.estimate(now_s)
        gap = self._gap_pose(now_s)
        if gap is None:
            return
        target = est.pos_m.copy()
        target[2] = max(target[2], cfg.takeoff_height_m, self._start_height_m)
        traj = solve(est.pos_m, est.vel_m_s, np.zeros(3), target, np.zeros(3), np.zeros(3),
                     cfg.takeoff_duration_s)
        # the turn starts from the heading commanded since the vehicle was first seen (the heading the
        # FC holds), not from the one measured now: a vehicle still turning would have its motion adopted
        # as the start of the turn and swing on past it
        yaw0 = self._abort_yaw
        yaw1 = yaw0 + _wrap(self._mission_yaw(est.pos_m, gap) - yaw0)
        self._takeoff = (traj, plan_with_gains(poly_packed(traj), self._gains), yaw0, yaw1, now_s)
        self.events.emit("takeoff", now_s, target_m=target, yaw_deg=round(math.degrees(yaw1), 1),
                         duration_s=cfg.takeoff_duration_s)
        self._go(Phase.TAKEOFF, now_s)

    def _takeoff_progress(self, now_s: float) -> None:
        cfg = self.config
        if now_s - self._phase_since_s < cfg.takeoff_duration_s + cfg.settle_s:
            return
        est = self.estimator.estimate(now_s)
        gap = self._gap_pose(now_s)
        if gap is None:
            return
        try:
            request = mission_request(self.config, est.pos_m, est.vel_m_s, gap)
            plan = request.checked_plan()
        except (PlanningError, ValueError) as exc:
            self._abort(now_s, "planning_failed", detail=str(exc))
            return
        self.plan, self.gap = plan, gap
        # (a pilot that offers it: the control step on this plan as one compiled call)
        compiled_step = getattr(self.pilot, "compiled_step", None)
        self._pilot_step = compiled_step(plan) if compiled_step is not None else None
        self._mission_start_s = now_s
        self.segment, self._segment_end_s = None, -math.inf
        self.events.emit("plan", now_s, start_m=est.pos_m, gap_centre_m=gap.centre,
                         t_gap_s=round(plan.t_gap_s, 3), t_hover_s=round(plan.t_hover_start_s, 3),
                         hover_m=np.array(plan.hover_m), crossing_speed_m_s=plan.traverse.crossing_speed_m_s,
                         approach_s=float(plan.approach.T), traverse_l_m=round(plan.traverse.l_m, 3),
                         approach=plan.approach_feasibility.name.lower(), tried=plan.candidates_tried,
                         search_ms=round(plan.search_time_s * 1e3, 3), request=request.to_dict())
        self._go(Phase.MISSION, now_s)

    def _mission_progress(self, now_s: float) -> None:
        plan = self.plan
        assert plan is not None
        t = now_s - self._mission_start_s
        if t >= self._segment_end_s:  # (the program's time never goes back: no segment lookup a tick)
            seg = plan.segment_at(t)
            self._segment_end_s = plan.segment_end_s(t)
            if seg is not self.segment:
                self.segment = seg
                est = self.estimator.estimate(now_s)
                self.events.emit("segment", now_s, segment=str(seg), mission_t_s=round(t, 3),
                                 pos_m=est.pos_m, vel_m_s=est.vel_m_s)
        if t >= plan.t_hover_start_s + self.config.hover_s:
            est = self.estimator.estimate(now_s)
            err = float(np.linalg.norm(est.pos_m - np.array(self.plan.hover_m)))
            self.events.emit("mission_done", now_s, pos_m=est.pos_m, hover_error_m=round(err, 3))
            self._go(Phase.HANDBACK, now_s)

    def _hold_request(self, now_s: float) -> bool | None:
        """Ask the FC for HOLD (again, until it confirms or the tries run out): True once it holds,
        False when it never confirmed, None while waiting."""
        if self._request is None:
            self._request = self._new_request(mav.MAV_CMD_DO_SET_MODE, self.link.request_hold, now_s,
                                              lambda: self._fc("holding"))
        done = self._request.update(self.link, now_s)
        if done is not None:
            self._request = None
        return done

    def _handback(self, now_s: float) -> None:
        done = self._hold_request(now_s)
        if done is None:
            return
        est = self.estimator.estimate(now_s)
        self._finish(Phase.DONE, EXIT_DONE, "done", hold=bool(done), pos_m=est.pos_m,
                     in_lab=self.lab.contains(est.pos_m))

    def _abort(self, now_s: float, reason: str, **fields: Any) -> None:
        """Abort to a safe hover (see the module docstring); only when the FC is armed."""
        self._request = None
        if self.estimator.ready:
            self._abort_yaw = float(self.estimator.estimate(now_s).euler_rad[2])
        self.events.emit("abort", now_s, reason=reason, phase=str(self.phase), **fields)
        armed = self._fc("armed")
        if not armed:
            self._finish(Phase.ABORTED, EXIT_ABORTED, "aborted", armed=False)
            return
        self._go(Phase.ABORTING, now_s)
        self._send_safe_hover()
        self._next_control_s = now_s + self.config.period_s

    def _aborting(self, now_s: float) -> None:
        done = self._hold_request(now_s)
        if done is None:
            return
        self._finish(Phase.ABORTED, EXIT_ABORTED, "hold" if done else "error",
                     **({} if done else {"reason": "FC did not confirm HOLD"}))

    # --- control ------------------------------------------------------------------------------
    def _send(self, roll_rad: float, pitch_rad: float, yaw_rad: float, thrust_n: float) -> None:
        """Send the setpoint (the angles in rad, thrust in N, as `AttitudeThrustCommand`'s, given as floats:
        no command object a control step); one that is not finite is refused (counted in
        ``commands_refused``) and, unless the program is aborting already, aborts to the safe hover."""
        try:
            self._send_attitude_target(roll_rad, pitch_rad, yaw_rad, thrust_n / self._full_thrust_n)
        except ValueError as exc:
            self.commands_refused += 1
            if self.phase is not _ABORTING:
                self._abort(self.clock.now_s(), "bad_command", detail=str(exc))
            return
        self._last_setpoint = (roll_rad, pitch_rad, yaw_rad, thrust_n)
        self.control_steps += 1

    def _send_command(self, cmd: AttitudeThrustCommand) -> None:
        """`_send` of a command object (a pilot's or the expert's)."""
        self._send(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad, cmd.thrust_n)

    def _send_safe_hover(self) -> None:
        self._send(0.0, 0.0, self._abort_yaw, self.config.hover_thrust_n)

    def _control(self, t_s: float, now_s: float) -> None:
        """One control step scheduled at ``t_s`` (s), with the estimate at ``now_s``; the pilot and the
        expert see the state and the reference ``control_lead_s`` ahead (module docstring)."""
        ph = self.phase
        if ph is _ABORTING:
            self._send_safe_hover()
            return
        lead = self._lead_s
        t_s += lead
        if ph is _TAKEOFF:
            # the take-off's step in one call (the state, the heading, the reference and the expert law)
            assert self._takeoff is not None
            traj, poly, yaw0, yaw1, t0 = self._takeoff
            duration = self._takeoff_duration_s
            roll, pitch, yaw, thrust = self._takeoff_step(poly, self._mass_kg, self._estimator_state,
                                                          now_s + lead, t_s, t0, duration, yaw0, yaw1)
            if math.isfinite(roll + pitch + thrust):
                self._send(roll, pitch, yaw, thrust)
            else:  # a bad input: the controller's checks name it
                pos, vel, _ = self.estimator.state_tuples(now_s + lead)
                tau, yaw = takeoff_heading(t_s, t0, duration, yaw0, yaw1)
                p, v, a = traj.state_tuples(tau)
                self._send_command(self.expert.command(p, v, a, yaw, pos, vel))
            return
        step, last = self._pilot_step, self._last_setpoint
        if step is not None and last is not None and ph in _PILOTED:
            # the pilot's whole step in one call (the state, its command, the tilt-step limit below); a
            # command that is not finite goes the long way, whose checks name it
            roll, pitch, yaw, thrust = step(self._estimator_state, now_s + lead, t_s - self._mission_start_s,
                                            last[0], last[1], self._tilt_step_rad)
            if math.isfinite(roll + pitch + thrust):
                self._send(roll, pitch, yaw, thrust)
                return
        pos, vel, acc = self.estimator.state_tuples(now_s + lead)  # (`estimate`'s numbers, no arrays)
        if ph in _LEVEL:
            armed = self._fc("armed")
            thrust = self.config.hover_thrust_n if armed else 0.0
            self._send(0.0, 0.0, self._abort_yaw, thrust)
        elif ph in _PILOTED:
            plan = self.plan
            assert plan is not None and self.gap is not None
            t_mission = t_s - self._mission_start_s
            cmd = self.pilot.command(FloatObservation.of_floats(
                t_mission, pos, vel, acc, self.estimator.quat_wxyz, self.gap, plan))
            # the command turns at most at the FC's body rate from the traverse on (the traverse, the
            # pull-out, the hover), not in the approach, which rolls the body into the gap's tilt before
            # the wall (the planner lets it ask up to twice the rate there)
            last = self._last_setpoint
            if last is not None and plan.segment_at(t_mission) is not _APPROACH:
                cmd = limit_tilt_step(cmd, last[0], last[1], self._tilt_step_rad)
            self._send_command(cmd)

    def _on_pose(self, body_id: int, stamp_s: float, pos_m: tuple[float, float, float],
                 quat_wxyz: tuple[float, float, float, float], received_s: float) -> None:
        # (the reader's numbers are plain floats: the estimator takes them without converting)
        if body_id == GAP_BODY_ID:
            self._gap_update(pos_m, quat_wxyz, received_s)
        elif body_id == VEHICLE_BODY_ID and not self._estimator_take(stamp_s, pos_m, quat_wxyz, received_s):
            mocap = self.mocap
            jumps = mocap.clock_jumps
            if jumps != mocap.intake_jumps:  # the reader follows a new mocap clock: so does the estimate
                mocap.intake_jumps = jumps  # (and from here the intake again)
                self.estimator.rebase(stamp_s, received_s)
                self.estimator.take(stamp_s, pos_m, quat_wxyz, received_s)

    # --- loops --------------------------------------------------------------------------------
    def run_realtime(self, max_duration_s: float | None = None) -> int:
        """Run on the wall clock until finished (or ``max_duration_s``); returns the exit code."""
        clock = WallClock()
        # where this clock's zero lies on the machine's monotonic clock (s): a harness on the same
        # machine puts the events' times on its own time line with it
        self._clock_zero_monotonic_s = time.monotonic() - clock.now_s()
        # (not the mocap's: it is read on the program's schedule, and unread bytes would wake it at once)
        fds = _fds(self.link.transport)
        while not self.finished:
            now = clock.now_s()
            if max_duration_s is not None and now > max_duration_s:
                self._finish(Phase.FAILED, EXIT_ERROR, "error", reason=f"out of time ({max_duration_s} s)")
                break
            self.step(now)
            wait = max(0.0, min(self.next_wake_s() - clock.now_s(), 0.05))
            if fds:
                select.select(fds, [], [], wait)
            else:
                time.sleep(min(wait, 0.001))
        return self.exit_code if self.exit_code is not None else EXIT_ERROR

    def lockstep_poll(self) -> list[float]:
        """Read the links and process every TIMESYNC tick that has arrived, one after the other
        (non-blocking; bytes arriving meanwhile wait for the next call); returns them."""
        done: list[float] = []
        link = self.link
        while self.phase not in FINAL_PHASES:  # (`finished`, without the property's call: per tick)
            try:
                ticks = link.read_ticks()  # in lockstep: the messages up to the next tick, and the ticks
                # the mocap link is read at the ticks only: bytes read between ticks would be stamped
                # with the previous tick's time, and how many there are depends on process scheduling
            except LinkError as exc:
                self._finish(Phase.FAILED, EXIT_ERROR, "link_lost", reason=str(exc))
                break
            if not ticks:
                break
            for tick in ticks:
                if tick <= self._last_tick_s:
                    # a repeat (sent again while this program started) or a tick sent again after a
                    # later one was done (the first copy lost to corrupt bytes): answer, do not act, as
                    # time never goes back
                    self.lockstep_tick(tick, repeat=True)
                    if self.phase in FINAL_PHASES:  # (the link lost)
                        break
                    continue
                self._last_tick_s = tick
                self.lockstep_tick(tick)
                done.append(tick)
                if self.phase in FINAL_PHASES:
                    break
            if not link.backlogged:
                # all read is acted on: what arrives next, a caller waits for (`run_lockstep` on the
                # link's descriptor) instead of a read per tick that finds nothing
                break
        return done

    def run_lockstep(self, tick_timeout_s: float = 10.0) -> int:
        """Run on the FC's TIMESYNC ticks until finished; ``tick_timeout_s`` of wall time without a tick
        ends the program with an error."""
        fds = _fds(self.link.transport)  # ticks come on the command link; the mocap waits for them
        spin_s = self.config.lockstep_spin_s
        poll = self.lockstep_poll
        # (asleep at once, without a spin: a poll object made once, no descriptor lists built a tick)
        waiter = select.poll()
        for fd in fds:
            waiter.register(fd, select.POLLIN)
        last_tick_wall = time.monotonic()
        while self.phase not in FINAL_PHASES:  # (`finished`, without the property's call: per tick)
            if poll():
                # answered: the next tick is not there yet (the FC waits for this answer), so wait for
                # it rather than reading the link again at once
                last_tick_wall = time.monotonic()
                if fds and self.phase not in FINAL_PHASES:
                    if spin_s > 0.0:
                        wait_readable(fds, 0.05, spin_s)
                    else:
                        waiter.poll(50)  # (ms: `wait_readable`'s 0.05 s)
                continue
            if time.monotonic() - last_tick_wall > tick_timeout_s:
                self._finish(Phase.FAILED, EXIT_ERROR, "error", reason=f"no tick for {tick_timeout_s} s")
                break
            if fds:
                select.select(fds, [], [], 0.05)
            else:
                time.sleep(0.001)
        return self.exit_code if self.exit_code is not None else EXIT_ERROR

    def log_summary(self) -> None:
        """Write the `summary` counters to the event log as a "summary" event (once; `close` does it)."""
        if not self._summary_logged:
            self._summary_logged = True
            self.events.emit("summary", self.clock.now_s(), **self.summary())

    def close(self) -> None:
        self.log_summary()
        self.link.close()
        self.mocap.close()
        self.events.close()

    def summary(self) -> dict[str, Any]:
        """Counters for the end of a run."""
        return {"phase": str(self.phase), "exit_code": self.exit_code, "control_steps": self.control_steps,
                "skipped_steps": self.skipped_steps, "commands_refused": self.commands_refused,
                self.link.protocol: self.link.codec.stats.as_dict(), "foreign": dict(self.link.foreign),
                "mocap": asdict(self.mocap.counters), "estimator_updates": self.estimator.updates,
                "estimator_rejected": self.estimator.rejected,
                "estimator_implausible": self.estimator.implausible,
                "gap_implausible": self.gap_check.implausible}


def _fds(*transports: Transport) -> list[int]:
    out = []
    for t in transports:
        with contextlib.suppress(NotImplementedError, OSError, ValueError):
            out.append(t.fileno())
    return out


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi

