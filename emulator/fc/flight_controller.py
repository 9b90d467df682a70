"""The N3-style flight controller: setpoint intake, arming, offboard authority, failsafe, inner loop.

`FlightController.update(state)` is called every physics step and returns the four motor throttles.
Commands (`arm`, `disarm`, `request_offboard`, `request_hold`, `request_land`) and setpoints
(`set_setpoint`) carry the simulated time at which they arrived; every state change is an `FcEvent`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, fields, replace

import numpy as np

from emulator.fc.hold import hold_command, pack_hold
from emulator.fc.inner_loop import InnerLoop
from emulator.fc.landed import body_landed
from emulator.fc.modes import (
    ACCEPTED,
    FAILSAFE_HOVER,
    OFFBOARD,
    CommandResult,
    FcEvent,
    FcState,
    LandedState,
    StateMachine,
)
from emulator.fc.n3 import (
    AttitudeThrustTarget,
    MotionTarget,
    N3Setpoint,
    check_flag,
    target_from_values,
    to_target,
    wrap_pi,
)
from emulator.fc.tuning import FcGains, fc_gains
from emulator.physics.state import VehicleState
from emulator.profile import VehicleProfile

PX4_OFFBOARD_LOSS_TIMEOUT_S = 1.0  # PX4's COM_OF_LOSS_T default
TAKEOFF_FINAL_CLIMB_M_S = 0.2  # the take-off's slowest climb, as it reaches its height
#: what the FC does when the setpoints stop: hover (``failsafe_hover_s``, then land) or land at once
FAILSAFE_ACTIONS = ("hover", "land")
#: the states flown by the FC's own hover/land controller while in the air (heading held on entry)
HOLD_STATES = frozenset((FcState.HOLD, FcState.FAILSAFE_HOVER, FcState.LAND, FcState.FAILSAFE_LAND))
LANDING_STATES = (FcState.LAND, FcState.FAILSAFE_LAND)
#: the states whose heading the FC holds itself (latched on entry, see `hold_heading_rad`)
HEADING_STATES = HOLD_STATES | {FcState.TAKEOFF, FcState.GO_HOME}


def steps_before(room_s: float, dt_s: float, n_max: int) -> int:
    """How many of the next ``n_max`` steps of ``dt_s`` (s) begin within ``room_s`` (s) from now (each
    checked at its start time; inf: all). Plain arithmetic on floats and ints: a batched stepper's
    kernel compiles it (`emulator.loops.batched_steps`)."""
    room_steps = room_s / dt_s if room_s > 0 else 0.0  # (NaN: none)
    if room_steps >= n_max:
        return n_max  # (inf, or a room past any int: all of them)
    return int(room_steps)


def heading_ned_rad(quat_wxyz: np.ndarray) -> float:
    """Heading (NED yaw, rad) of a body FLU -> world ENU attitude: yaw_ned = pi/2 - yaw_enu."""
    w, x, y, z = quat_wxyz.tolist() if isinstance(quat_wxyz, np.ndarray) else quat_wxyz
    yaw_enu = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return wrap_pi(math.pi / 2 - yaw_enu)


@dataclass(frozen=True)
class FcConfig:
    """Flight-controller settings (SI units)."""

    failsafe_timeout_s: float = PX4_OFFBOARD_LOSS_TIMEOUT_S  # setpoint silence before the failsafe
    failsafe_hover_s: float = 5.0  # hover this long after setpoint loss, then land
    land_speed_m_s: float = 0.7  # descent rate when landing
    hover_max_tilt_deg: float = 30.0  # tilt limit of the FC's own hover/land controller
    min_offboard_rate_hz: float = 2.0  # PX4 rule: stream faster than this before OFFBOARD is accepted
    ground_z_m: float = 0.0  # ground height (world ENU z)
    landed_margin_m: float = 0.05  # body within this of its resting height counts as on the ground
    auto_disarm_s: float = 1.0  # on the ground this long in a landing state: disarm
    failsafe_action: str = "hover"  # on setpoint loss: one of FAILSAFE_ACTIONS
    #: the throttle (0..1 per rotor) the FC's own hover controller takes to balance the weight; None:
    #: the profile's true hover throttle (a wrong one makes the hover sag or climb until corrected)
    hover_throttle: float | None = None
    gains: FcGains | None = None  # None: tuned from the vehicle profile (emulator.fc.tuning)
    #: the FC's own take-off (an N3's task 1): motors spin this long on the ground, then it climbs at
    #: ``takeoff_speed_m_s`` to ``takeoff_height_m`` above its resting height and hovers
    takeoff_spinup_s: float = 1.0
    takeoff_speed_m_s: float = 1.0
    takeoff_height_m: float = 1.2
    #: position-offset control: speed (m/s) per metre to go, horizontally and vertically, and the
    #: largest speed it asks (m/s); the climb rate also stops at the SDK's 5 m/s
    position_gain_per_s: float = 1.0
    position_speed_m_s: float = 2.0
    #: go home: within this of the home point (m, horizontally) it lands
    home_radius_m: float = 0.3

    def __post_init__(self) -> None:
        if self.failsafe_action not in FAILSAFE_ACTIONS:
            raise ValueError(f"FcConfig.failsafe_action must be one of {FAILSAFE_ACTIONS}, "
                             f"got {self.failsafe_action!r}")
        if self.hover_throttle is not None and not 0.0 < self.hover_throttle < 1.0:
            raise ValueError(f"FcConfig.hover_throttle must be in (0, 1), got {self.hover_throttle!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float | int) and not (math.isfinite(v) and (v > 0 or f.name == "ground_z_m")):
                raise ValueError(f"FcConfig.{f.name} must be a positive finite number, got {v!r}")


class FlightController:
    """One N3-style flight controller for ``profile`` (see the module docstring)."""

    def __init__(self, profile: VehicleProfile, config: FcConfig | None = None) -> None:
        self.profile = profile  # the setpoint limits are this one's (`set_limits` changes them)
        self.base_profile = profile  # the vehicle's, as built
        self.config = config or FcConfig()
        self.machine = StateMachine()
        #: the FC's loop gains; ProfileError when the FC cannot stabilise ``profile``
        self.gains = self.config.gains or fc_gains(profile)
        self.inner = InnerLoop(profile, self.gains.inner)
        #: the velocity hold's parameters as `emulator.fc.hold.hold_command` reads them
        self.hold_params = self._pack_hold()
        self.offboard_selected = False  # OFFBOARD chosen while disarmed: arming goes straight to it
        self.target: AttitudeThrustTarget | MotionTarget | None = None
        #: a position-offset target's goal (world ENU east, north, m), fixed at the first step after
        #: the setpoint arrived (None: to be fixed)
        self._goal_en_m: tuple[float, float] | None = None
        #: where GO_HOME flies (world ENU east, north, m), given by `request_go_home`
        self.home_en_m: tuple[float, float] | None = None
        self.last_setpoint_s = -math.inf
        self.setpoints_accepted = 0
        self._arrivals: deque[float] = deque(maxlen=2)
        self._yaw_sp_rad = 0.0
        self._yaw_sp_fresh = True
        #: the heading (NED yaw, rad) held by the FC's own hover/land controller: latched from the
        #: attitude at its first step after a hold state is entered (None until then), as PX4's Hold
        self._hold_yaw_rad: float | None = None
        self._last_t: float | None = None
        #: the body's height (m, world ENU z) when it rests on the ground
        self.rest_height_m = self.config.ground_z_m + 0.5 * profile.body_box_m[2]
        self._landed_since_s: float | None = 0.0
        self.landed = True
        #: the landed test's resting height and margin (m) as a compiled stepper reads them
        #: (`emulator.fc.landed.body_landed`); kept in place by `reconfigure`
        self.landed_test = np.array([self.rest_height_m, self.config.landed_margin_m])
        self._off = np.zeros(4)
        self._idle = np.full(4, self.gains.inner.idle_throttle)
        self.motor_cmd = self._off
        #: the offboard attitude target a batched stepper may fly outside `update`: (roll, pitch, yaw
        #: (NED, rad), thrust (N), the setpoint-loss failsafe's time (s), and the landed test's resting
        #: height and margin (m, `landed_test`'s, as plain numbers)), None when none may be; made again
        #: where its inputs change (a setpoint, a change of state, `reconfigure`), see `batch_target`;
        #: while there is one, its yaw is the heading the FC steers to (`heading_setpoint_rad`)
        self.batch_plan: tuple[float, float, float, float, float, float, float] | None = None

    def _pack_hold(self) -> np.ndarray:
        cfg = self.config
        return pack_hold(self.gains.hold, self.profile, cfg.hover_max_tilt_deg, cfg.hover_throttle)

    def reconfigure(self, **changes: object) -> None:
        """Change settings in flight (`FcConfig` fields, validated: ValueError with the reason); they
        act from the next step. ``gains`` and ``ground_z_m`` are fixed once built."""
        for name in changes:
            if name in ("gains", "ground_z_m"):
                raise ValueError(f"FcConfig.{name} cannot change in flight")
        self.config = replace(self.config, **changes)
        self.hold_params[:] = self._pack_hold()  # in place: a batched stepper holds these arrays
        self.landed_test[1] = self.config.landed_margin_m
        self._plan_batch()

    def set_limits(self, **changes: float) -> None:
        """Change the setpoint limits taken from the profile (``max_tilt_deg``, ``max_yaw_rate_deg_s``,
        validated as a profile: ValueError with the reason); they act on the next setpoint."""
        for name in changes:
            if name not in ("max_tilt_deg", "max_yaw_rate_deg_s"):
                raise ValueError(f"{name} is not a setpoint limit")
        self.profile = self.profile.with_changes(**changes)

    # --- read-outs -------------------------------------------------------------------------
    @property
    def state(self) -> FcState:
        return self.machine.state

    @property
    def events(self) -> list[FcEvent]:
        return self.machine.events

    @property
    def landed_state(self) -> LandedState:
        if self.landed:
            return LandedState.ON_GROUND
        if self.state in LANDING_STATES:
            return LandedState.LANDING
        return LandedState.IN_AIR

    def stream_ok(self, time_s: float) -> bool:
        """True when setpoints arrive faster than ``min_offboard_rate_hz`` (the last two, and now)."""
        period = 1.0 / self.config.min_offboard_rate_hz
        return (
            len(self._arrivals) == 2
            and self._arrivals[1] - self._arrivals[0] < period
            and time_s - self._arrivals[1] < period
        )

    # --- inputs ----------------------------------------------------------------------------
    def set_setpoint(self, sp: N3Setpoint, time_s: float) -> AttitudeThrustTarget | MotionTarget:
        """Take a setpoint that arrived at ``time_s``; raises SetpointRejected with the reason."""
        return self.take_target(to_target(sp, self.profile), time_s)

    def set_setpoint_values(
        self, flag: int, roll_deg: float, pitch_deg: float, thrust_percent: float, yaw: float, time_s: float
    ) -> AttitudeThrustTarget | MotionTarget:
        """`set_setpoint` of the N3Setpoint with these fields (degrees, percent), without building it."""
        check_flag(flag)
        return self.take_target(
            target_from_values(flag, roll_deg, pitch_deg, thrust_percent, yaw, self.profile), time_s
        )

    def take_target(self, target: AttitudeThrustTarget | MotionTarget, time_s: float
              ) -> AttitudeThrustTarget | MotionTarget:
        """Make a validated ``target`` that arrived at ``time_s`` (s) the one flown."""
        self._goal_en_m = None
        if target.yaw_rate_rad_s is not None:
            old = self.target
            if old is None or old.yaw_rate_rad_s is None:  # a yaw-rate stream starts: from the heading
                self._yaw_sp_fresh = True
        self.target = target
        self.last_setpoint_s = time_s
        self._arrivals.append(time_s)
        self.setpoints_accepted += 1
        self._plan_batch()
        return target

    def arm(self, time_s: float) -> CommandResult:
        if self.state.armed:
            return ACCEPTED
        if self.offboard_selected and self.stream_ok(time_s):
            self._go(FcState.OFFBOARD, time_s, "armed in offboard")
        else:
            self.offboard_selected = False
            self._go(FcState.HOLD, time_s, "armed")
        return ACCEPTED

    def disarm(self, time_s: float, force: bool = False) -> CommandResult:
        if not self.state.armed:
            return ACCEPTED
        if not self.landed and not force:
            return CommandResult(False, "disarm refused: vehicle in the air")
        self.offboard_selected = False
        self._go(FcState.DISARMED, time_s, "disarmed (forced)" if force else "disarmed")
        return ACCEPTED

    def request_offboard(self, time_s: float) -> CommandResult:
        """Give control authority to the onboard computer (PX4 OFFBOARD)."""
        if not self.stream_ok(time_s):
            rate = self.config.min_offboard_rate_hz
            return CommandResult(False, f"offboard refused: need setpoints above {rate:g} Hz first")
        if not self.state.armed:
            self.offboard_selected = True
            return ACCEPTED
        self._go(FcState.OFFBOARD, time_s, "offboard control granted")
        return ACCEPTED

    def request_hold(self, time_s: float, reason: str = "hold requested") -> CommandResult:
        """Take authority back and hover (PX4 HOLD)."""
        if not self.state.armed:
            self.offboard_selected = False
            return ACCEPTED
        self._go(FcState.HOLD, time_s, reason)
        return ACCEPTED

    def request_takeoff(self, time_s: float) -> CommandResult:
        """The FC's own take-off from the ground: arm, spin up, climb to the take-off height, hover."""
        if self.state is FcState.TAKEOFF:
            return CommandResult(False, "take-off refused: already taking off")
        if not self.landed:
            return CommandResult(False, "take-off refused: in the air")
        self.offboard_selected = False
        self._go(FcState.TAKEOFF, time_s, "take-off")
        return ACCEPTED

    def request_go_home(self, time_s: float, home_en_m: tuple[float, float]) -> CommandResult:
        """Fly back over ``home_en_m`` (world ENU east, north, m) at the height now, then land (an N3's go
        home, without its climb to a return altitude: a lab has no room for one)."""
        if self.landed or not self.state.armed:
            return CommandResult(False, "go home refused: not in the air")
        self.home_en_m = home_en_m
        if self.state not in LANDING_STATES:
            self._go(FcState.GO_HOME, time_s, "go home")
        return ACCEPTED

    def request_land(self, time_s: float) -> CommandResult:
        if not self.state.armed:
            return CommandResult(False, "land refused: not armed")
        if self.state not in LANDING_STATES:
            self._go(FcState.LAND, time_s, "land requested")
        return ACCEPTED

    def motor_failsafe(self, action: str, time_s: float, reason: str) -> None:
        """A motor path failed (an ESC silent on its bus): ``action`` "land" lands (FAILSAFE_LAND),
        "disarm" stops the motors; nothing when disarmed."""
        if not self.state.armed:
            return
        if action == "disarm":
            self.offboard_selected = False
            self._go(FcState.DISARMED, time_s, f"{reason}: disarm")
        elif action == "land" and self.state is not FcState.FAILSAFE_LAND:
            self._go(FcState.FAILSAFE_LAND, time_s, f"{reason}: land")

    def _go(self, to_state: FcState, time_s: float, reason: str) -> None:
        """Change state; entering the FC's own hover/land from anything else releases the held heading
        (the next step latches the heading it finds, see `hold_heading_rad`)."""
        if to_state in HEADING_STATES and self.machine.state not in HEADING_STATES:
            self._hold_yaw_rad = None
        self.machine.go(to_state, time_s, reason)
        self._plan_batch()

    def hold_heading_rad(self, quat_wxyz: np.ndarray) -> float:
        """The heading (NED yaw, rad) the FC's own hover/land holds: the one of ``quat_wxyz`` (the body
        FLU -> world ENU attitude it flies from) at its first step after entering hold, then kept."""
        yaw = self._hold_yaw_rad
        if yaw is None:
            yaw = self._hold_yaw_rad = heading_ned_rad(quat_wxyz)
        return yaw

    def heading_setpoint_rad(self) -> float:
        """The heading (NED yaw, rad) the FC steers to now: the offboard target's yaw (or its integrated
        yaw rate), the held heading in hold, hover and land; NaN when it steers none (disarmed, idle on
        the ground, or hold entered and not yet stepped)."""
        st = self.machine.state
        if st is FcState.OFFBOARD and self.target is not None:
            if self.target.yaw_rate_rad_s is None:
                return self.target.yaw_rad
            return math.nan if self._yaw_sp_fresh else self._yaw_sp_rad
        if st in HEADING_STATES and not self.landed and self._hold_yaw_rad is not None:
            return self._hold_yaw_rad
        return math.nan

    # --- the step ----------------------------------------------------------------------------
    def update(self, state: VehicleState) -> np.ndarray:
        """Motor throttles (4,) in [0, 1] for the next physics step from ``state``."""
        t = state.time_s
        dt = 0.0 if self._last_t is None else max(0.0, t - self._last_t)
        self._last_t = t
        self._detect_landed(state, t)
        self._check_transitions(t)
        st = self.machine.state
        if st is FcState.DISARMED:
            cmd = self._off
        elif st is FcState.OFFBOARD:
            cmd = self._fly_target(state, dt)
        elif st is FcState.TAKEOFF:
            cmd = self._take_off(state, t)
        elif st is FcState.GO_HOME:
            cmd = self._go_home(state, t)
        elif self.landed and (st is FcState.HOLD or st in LANDING_STATES):
            cmd = self._idle
        else:  # HOLD in the air, FAILSAFE_HOVER, landing in the air
            cmd = self._velocity_hold(state, self.hold_climb_m_s())
        self.motor_cmd = cmd
        return cmd

    def hold_climb_m_s(self) -> float:
        """The climb rate (m/s, up) the FC's own hover/land controller holds in the state now."""
        return -self.config.land_speed_m_s if self.machine.state in LANDING_STATES else 0.0

    def held_target(self) -> AttitudeThrustTarget | None:
        """The offboard attitude target a stepper outside `update` may fly with the inner loop alone (in
        OFFBOARD, a held heading, no yaw rate to integrate), else None; with `quiet_steps` for how long."""
        return None if self.batch_target(0.0, 1.0, 0) is None else self.target  # type: ignore[return-value]

    def batch_target(self, time_s: float, dt_s: float, n_max: int
                     ) -> tuple[float, float, float, float, int] | None:
        """`held_target` and its `quiet_steps` in one call, for a batched stepper: (roll, pitch, yaw (NED,
        rad), thrust (N), steps (of the next ``n_max`` of ``dt_s`` (s) from ``time_s`` (s))), or None
        when no target may be flown outside `update` (a view of `batch_plan`)."""
        plan = self.batch_plan
        if plan is None:
            return None
        roll, pitch, yaw, thrust_n, until_s, _, _ = plan
        return roll, pitch, yaw, thrust_n, steps_before(until_s - time_s, dt_s, n_max)

    def _plan_batch(self) -> None:
        """Make `batch_plan` from the state, the target and the failsafe's timeout now."""
        tg = self.target
        if (self.machine.state is not OFFBOARD or tg.__class__ is not AttitudeThrustTarget
                or tg.yaw_rate_rad_s is not None):  # type: ignore[union-attr]
            self.batch_plan = None
            return
        # the setpoint-loss failsafe's time (`quiet_until_s` in OFFBOARD)
        cfg = self.config
        until_s = self.last_setpoint_s + cfg.failsafe_timeout_s
        self.batch_plan = (tg.roll_rad, tg.pitch_rad, tg.yaw_rad, tg.thrust_n,  # type: ignore[union-attr]
                           until_s, self.rest_height_m, cfg.landed_margin_m)

    def quiet_steps(self, time_s: float, dt_s: float, n_max: int) -> int:
        """How many of the next ``n_max`` steps of ``dt_s`` (s) from ``time_s`` (s) begin before a timed
        change of state (the setpoint-loss failsafe, the failsafe hover's end): steps that a batched
        stepper may fly without `update`'s checks. Landing and arming are not timed here."""
        return steps_before(self.quiet_until_s() - time_s, dt_s, n_max)

    def quiet_until_s(self) -> float:
        """When the next timed change of state is due (s; inf: none): the setpoint-loss failsafe in
        OFFBOARD, the failsafe hover's end (see `quiet_steps`)."""
        cfg, m = self.config, self.machine
        if m.state is OFFBOARD:
            return self.last_setpoint_s + cfg.failsafe_timeout_s
        if m.state is FAILSAFE_HOVER:
            return m.since_s + cfg.failsafe_hover_s
        return math.inf

    def stepped_outside(self, last_step_s: float, z_m: float, vz_m_s: float, detect_landed: bool = True
                        ) -> None:
        """The bookkeeping `update` keeps, after steps flown outside it with this FC's loops (a batched
        stepper): the last step began at ``last_step_s`` (s); with ``detect_landed``, the body's height
        ``z_m`` (m) and climb rate ``vz_m_s`` (m/s) after it update ``landed``; the throttles flown are
        the inner loop's ``motor_cmd``."""
        if detect_landed:
            self.detect_landed(z_m, vz_m_s, last_step_s)
        self.flew_outside(last_step_s, None)

    def flew_outside(self, last_step_s: float, landed: bool | None) -> None:
        """`stepped_outside` for a stepper that ran the landed test itself (`body_landed` of the body
        after the last step, with `landed_test`): ``landed`` its answer, None when not run."""
        self._last_t = last_step_s
        if landed is not None and landed is not self.landed:  # (the same answer again changes nothing)
            self._take_landed(landed, last_step_s)
        self.motor_cmd = self.inner.motor_cmd

    def _check_transitions(self, t: float) -> None:
        cfg, m, go = self.config, self.machine, self._go
        if m.state is FcState.OFFBOARD and t - self.last_setpoint_s > cfg.failsafe_timeout_s:
            if cfg.failsafe_action == "land":
                go(FcState.FAILSAFE_LAND, t, f"setpoints lost for {cfg.failsafe_timeout_s:g} s: land")
            else:
                go(FcState.FAILSAFE_HOVER, t, f"setpoints lost for {cfg.failsafe_timeout_s:g} s: hover")
        elif m.state is FcState.FAILSAFE_HOVER and t - m.since_s >= cfg.failsafe_hover_s:
            go(FcState.FAILSAFE_LAND, t, f"no control for {cfg.failsafe_hover_s:g} s: land")
        elif (
            m.state in LANDING_STATES
            and self._landed_since_s is not None
            and t - self._landed_since_s >= cfg.auto_disarm_s
        ):
            go(FcState.DISARMED, t, "landed: disarmed")
        if m.state is FcState.DISARMED and self.offboard_selected and not self.stream_ok(t):
            self.offboard_selected = False

    def _detect_landed(self, state: VehicleState, t: float) -> None:
        self.detect_landed(state.pos_m[2], state.vel_m_s[2], t)

    def detect_landed(self, z_m: float, vz_m_s: float, t: float) -> None:
        """Update ``landed`` from the body height ``z_m`` (m) and climb rate ``vz_m_s`` (m/s) at ``t``."""
        self._take_landed(bool(body_landed(z_m, vz_m_s, self.rest_height_m, self.config.landed_margin_m)), t)

    def _take_landed(self, landed: bool, t: float) -> None:
        """``landed``, the landed test's answer at ``t`` (s): the flag and since when it holds (None
        while not landed)."""
        if landed and not self.landed:
            self._landed_since_s = t
        elif not landed:
            self._landed_since_s = None
        self.landed = landed

    def _fly_target(self, state: VehicleState, dt: float) -> np.ndarray:
        tg = self.target
        if tg is None:  # cannot happen: OFFBOARD needs a stream
            return self._velocity_hold(state, 0.0)
        if tg.yaw_rate_rad_s is not None:
            if self._yaw_sp_fresh:
                self._yaw_sp_rad, self._yaw_sp_fresh = heading_ned_rad(state.quat_wxyz), False
            self._yaw_sp_rad = wrap_pi(self._yaw_sp_rad + tg.yaw_rate_rad_s * dt)
            yaw = self._yaw_sp_rad
        else:
            yaw = tg.yaw_rad
        if isinstance(tg, MotionTarget):
            return self._fly_motion(state, tg, yaw)
        return self.inner.update(
            state.quat_wxyz, state.omega_rad_s, tg.roll_rad, tg.pitch_rad, yaw, tg.thrust_n
        )

    def _fly_motion(self, state: VehicleState, tg: MotionTarget, yaw: float) -> np.ndarray:
        """A velocity or position-offset target, flown by the velocity controller of the FC's hover."""
        cfg = self.config
        x, y = tg.x, tg.y
        if tg.body_frame:  # forward, right -> north, east by the heading now
            psi = heading_ned_rad(state.quat_wxyz)
            x, y = x * math.cos(psi) - y * math.sin(psi), x * math.sin(psi) + y * math.cos(psi)
        pos = state.pos_m
        if tg.horizontal_position:
            if self._goal_en_m is None:
                self._goal_en_m = (float(pos[0]) + y, float(pos[1]) + x)
            ve_sp = cfg.position_gain_per_s * (self._goal_en_m[0] - float(pos[0]))
            vn_sp = cfg.position_gain_per_s * (self._goal_en_m[1] - float(pos[1]))
            speed = math.hypot(ve_sp, vn_sp)
            if speed > cfg.position_speed_m_s:
                ve_sp, vn_sp = ve_sp * cfg.position_speed_m_s / speed, vn_sp * cfg.position_speed_m_s / speed
        else:
            ve_sp, vn_sp = y, x
        climb = tg.z
        if tg.vertical_position:
            climb = cfg.position_gain_per_s * (cfg.ground_z_m + tg.z - float(pos[2]))
            climb = max(-cfg.position_speed_m_s, min(cfg.position_speed_m_s, climb))
        return self._velocity_hold(state, climb, yaw, ve_sp, vn_sp)

    def _go_home(self, state: VehicleState, t: float) -> np.ndarray:
        """Fly back over the home point at the height now; land once within ``home_radius_m``."""
        cfg = self.config
        assert self.home_en_m is not None  # (`request_go_home` asks for one)
        de, dn = self.home_en_m[0] - float(state.pos_m[0]), self.home_en_m[1] - float(state.pos_m[1])
        if math.hypot(de, dn) < cfg.home_radius_m:
            self._go(FcState.LAND, t, "home: landing")
            return self._velocity_hold(state, -cfg.land_speed_m_s)
        ve, vn = cfg.position_gain_per_s * de, cfg.position_gain_per_s * dn
        speed = math.hypot(ve, vn)
        if speed > cfg.position_speed_m_s:
            ve, vn = ve * cfg.position_speed_m_s / speed, vn * cfg.position_speed_m_s / speed
        return self._velocity_hold(state, 0.0, None, ve, vn)

    def _take_off(self, state: VehicleState, t: float) -> np.ndarray:
        """The FC's own take-off: the motors idle through the spin-up, then it climbs to the take-off
        height, where it hands over to HOLD."""
        cfg = self.config
        if t - self.machine.since_s < cfg.takeoff_spinup_s:
            return self._idle
        to_go = self.rest_height_m + cfg.takeoff_height_m - float(state.pos_m[2])
        if to_go <= 0.0:
            self._go(FcState.HOLD, t, "take-off complete")
            return self._velocity_hold(state, 0.0)
        # slowing down over the last metres (the position gain, not under 0.2 m/s), to stop at the height
        climb = max(TAKEOFF_FINAL_CLIMB_M_S, min(cfg.takeoff_speed_m_s, cfg.position_gain_per_s * to_go))
        return self._velocity_hold(state, climb)

    def _velocity_hold(self, state: VehicleState, climb_m_s: float, yaw: float | None = None,
                       ve_sp: float = 0.0, vn_sp: float = 0.0) -> np.ndarray:
        """The FC's velocity controller: horizontal velocity ``ve_sp``, ``vn_sp`` (m/s, east, north; 0:
        the hover) and climb rate ``climb_m_s``, heading ``yaw`` (NED, rad; None: the held one)."""
        ve, vn, vu = state.vel_m_s
        if yaw is None:
            yaw = self.hold_heading_rad(state.quat_wxyz)
        roll, pitch, thrust = hold_command(float(ve), float(vn), float(vu), climb_m_s, yaw, self.hold_params,
                                           ve_sp, vn_sp)
        return self.inner.update(state.quat_wxyz, state.omega_rad_s, roll, pitch, yaw, thrust)
