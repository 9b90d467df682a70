"""The `traditional` pilot: the mission plan's reference (approach, traverse, recovery, hover) tracked by
the expert geometric controller, as in the paper's conventional pipeline."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from policies.compiling import Kernel
from policies.controller import (
    EXPERT_LAW,
    TILT_STEP_LIMITED,
    AttitudeThrustCommand,
    ExpertController,
    ExpertGains,
    _new_command,
    expert_law,
    tilt_step_limited,
)
from policies.gap_planning import (
    PLAN_FLOATS,
    PLAN_POLY_FLOATS,
    PLAN_REFERENCE,
    POLY_AXES,
    SEGMENT_INDEX,
    MissionPlan,
    _poly_axes,
    plan_reference,
    segment_index,
)
from policies.onboard.estimator import PREDICTED_STATE, STATE_FLOATS, predicted_state
from policies.onboard.pilots import Observation, PilotContext, flown_by


class TraditionalPilot:
    """Reference from ``obs.plan`` at ``obs.t_s``, expert controller on the estimated p and v (one
    compiled call a step: `traditional_command`)."""

    def __init__(self, mass_kg: float = 0.9, max_tilt_deg: float = 75.0) -> None:
        self.controller = ExpertController(mass_kg, ExpertGains(tilt_max_rad=math.radians(max_tilt_deg)))
        self.flies = flown_by()
        self._mass_kg, self._gains = self.controller.mass_kg, self.controller.gains_array
        #: the plan last flown (`MissionPlan.packed`) and it with these gains after it, as
        #: `traditional_command` reads them (one array argument a step, not two)
        self._plan: np.ndarray | None = None
        self._plan_gains = plan_with_gains(np.zeros(PLAN_FLOATS), self._gains)
        # (the compiled forms for that read-only array, the estimator's state array and floats: no
        # dispatch a call)
        self._step = TRADITIONAL_COMMAND.entry(self._plan_gains, *(0.0,) * 8)
        self._control_step = TRADITIONAL_STEP.entry(self._plan_gains, 0.0, np.zeros(STATE_FLOATS),
                                                    *(0.0,) * 5)

    def _gains_for(self, plan: MissionPlan) -> np.ndarray:
        """``plan`` packed with the gains after it (`plan_with_gains`), made once a plan."""
        packed = plan.packed
        if packed is not self._plan:
            self._plan, self._plan_gains = packed, plan_with_gains(packed, self._gains)
        return self._plan_gains

    def command(self, obs: Observation) -> AttitudeThrustCommand:
        pos, vel = obs.pos_vel()  # (plain floats where the observation holds them so, else the arrays)
        if pos.__class__ is not tuple:
            pos, vel = tuple(np.asarray(pos, float).tolist()), tuple(np.asarray(vel, float).tolist())
        (px, py, pz), (vx, vy, vz) = pos, vel
        roll, pitch, yaw, thrust = self._step(self._gains_for(obs.plan), obs.t_s, px, py, pz, vx, vy, vz,
                                              self._mass_kg)
        if not math.isfinite(roll + pitch + thrust):  # a bad input: the controller's checks name it
            p, v, a, yaw = obs.plan.reference_tuples(obs.t_s)
            return self.controller.command(p, v, a, yaw, pos, vel)
        return _new_command(roll, pitch, thrust, yaw)

    def compiled_step(self, plan: MissionPlan) -> Callable[..., tuple[float, float, float, float]]:
        """The program's control step with this pilot on ``plan`` as one compiled call (`traditional_step`
        with the plan, the gains and the mass bound): ``(state, now_s, t_s, last_roll_rad, last_pitch_rad,
        max_step_rad) -> (roll, pitch, yaw, thrust)``; the numbers of `command` on the estimator's state
        at ``now_s`` followed by the tilt-step limit."""
        return functools.partial(self._control_step, self._gains_for(plan), self._mass_kg)


def plan_with_gains(plan: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """The plan packed in ``plan`` (`MissionPlan.packed`, `PLAN_FLOATS`) followed by the gains ``gains``
    (`policies.controller.gains_array`), as `traditional_command` reads them (read-only); or so a take-off
    trajectory (`gap_planning.poly_packed`, `PLAN_POLY_FLOATS`), as `takeoff_step` reads it."""
    k = np.concatenate((plan, gains))
    k.flags.writeable = False
    return k


def traditional_command(plan_gains: np.ndarray, t_s: float, px: float, py: float, pz: float, vx: float,
                        vy: float, vz: float, mass_kg: float) -> tuple[float, float, float, float]:
    """The pilot's command at mission time ``t_s`` (s) for the plan and the gains packed in ``plan_gains``
    (`plan_with_gains`) and the state ``p`` (m), ``v`` (m/s): `expert_law` on `plan_reference`, roll,
    pitch, yaw (rad) and thrust (N). Compiled by numba (`policies.compiling`), which is how it runs."""
    prx, pry, prz, vrx, vry, vrz, arx, ary, arz, yaw = plan_reference(plan_gains, t_s)
    roll, pitch, thrust = expert_law(prx, pry, prz, vrx, vry, vrz, arx, ary, arz, px, py, pz, vx, vy, vz, yaw,
                                     mass_kg, plan_gains[PLAN_FLOATS:])
    return roll, pitch, yaw, thrust


def traditional_step(plan_gains: np.ndarray, mass_kg: float, st: np.ndarray, now_s: float, t_s: float,
                     last_roll_rad: float, last_pitch_rad: float,
                     max_step_rad: float) -> tuple[float, float, float, float]:
    """The onboard program's control step with this pilot, in one compiled call: the state predicted to
    ``now_s`` (s, reader clock) from the estimator's state ``st`` (`predicted_state`), `traditional_command`
    at mission time ``t_s`` (s), and from the traverse on (the plan's segment at ``t_s``) its roll and pitch
    moved at most ``max_step_rad`` (rad) from the last command's (`tilt_step_limited`); a command that is
    not finite is returned as it is (the caller's checks name it). Roll, pitch, yaw (rad), thrust (N)."""
    px, py, pz, vx, vy, vz, _, _, _ = predicted_state(st, now_s)
    roll, pitch, yaw, thrust = traditional_command(plan_gains, t_s, px, py, pz, vx, vy, vz, mass_kg)
    if math.isfinite(roll + pitch + thrust) and \
            segment_index(t_s, plan_gains[0], plan_gains[1], plan_gains[2]) != 0:
        roll, pitch = tilt_step_limited(roll, pitch, last_roll_rad, last_pitch_rad, max_step_rad)
    return roll, pitch, yaw, thrust


def tracking_command(poly: np.ndarray, t_s: float, yaw: float, px: float, py: float, pz: float, vx: float,
                     vy: float, vz: float, mass_kg: float, gains: np.ndarray) -> tuple[float, float, float]:
    """`expert_law` on the reference of the trajectory packed in ``poly`` (`gap_planning.poly_packed`) at
    ``t_s`` (s) with the yaw ``yaw`` (rad), for the state ``p`` (m), ``v`` (m/s): roll, pitch (rad) and
    thrust (N) (the onboard program's take-off). Compiled by numba (`policies.compiling`), which is how it
    runs."""
    prx, pry, prz, vrx, vry, vrz, arx, ary, arz = _poly_axes(poly, 0, t_s)
    return expert_law(prx, pry, prz, vrx, vry, vrz, arx, ary, arz, px, py, pz, vx, vy, vz, yaw, mass_kg,
                      gains)


def takeoff_heading(t_s: float, t0_s: float, duration_s: float, yaw0_rad: float,
                    yaw1_rad: float) -> tuple[float, float]:
    """The onboard program's take-off at ``t_s`` (s) of one started at ``t0_s`` (s) lasting ``duration_s``
    (s): the time along its trajectory (s, within [0, duration_s]) and its heading (rad), from ``yaw0_rad``
    to ``yaw1_rad`` on a smoothstep of that time."""
    tau = t_s - t0_s
    tau = 0.0 if tau < 0.0 else tau  # (as min(max(t_s - t0_s, 0), duration_s), without the two calls)
    tau = duration_s if duration_s < tau else tau
    x = tau / duration_s
    x = 0.0 if x < 0.0 else x
    x = 1.0 if x > 1.0 else x
    return tau, yaw0_rad + (yaw1_rad - yaw0_rad) * (x * x * (3 - 2 * x))


def takeoff_step(poly_gains: np.ndarray, mass_kg: float, st: np.ndarray, now_s: float, t_s: float,
                 t0_s: float, duration_s: float, yaw0_rad: float,
                 yaw1_rad: float) -> tuple[float, float, float, float]:
    """The onboard program's take-off step in one compiled call: the state predicted to ``now_s`` (s, reader
    clock) from the estimator's state ``st`` (`predicted_state`), `tracking_command` on the trajectory and
    the gains packed in ``poly_gains`` (`plan_with_gains`: one array argument, not two) at the time and
    heading `takeoff_heading` gives for ``t_s`` (s). Roll, pitch, yaw (rad), thrust (N); a command that is
    not finite is returned as it is (the caller's checks name it)."""
    px, py, pz, vx, vy, vz, _, _, _ = predicted_state(st, now_s)
    tau, yaw = takeoff_heading(t_s, t0_s, duration_s, yaw0_rad, yaw1_rad)
    roll, pitch, thrust = tracking_command(poly_gains[:PLAN_POLY_FLOATS], tau, yaw, px, py, pz, vx, vy, vz,
                                           mass_kg, poly_gains[PLAN_POLY_FLOATS:])
    return roll, pitch, yaw, thrust


def make_pilot(context: PilotContext) -> TraditionalPilot:
    return TraditionalPilot(context.mass_kg, context.max_tilt_deg)


#: the pilot's command, compiled: `traditional_command`
TRADITIONAL_COMMAND = Kernel(traditional_command, plan_reference=PLAN_REFERENCE, expert_law=EXPERT_LAW)
#: the program's control step with this pilot, compiled: `traditional_step`
TRADITIONAL_STEP = Kernel(traditional_step, predicted_state=PREDICTED_STATE,
                          traditional_command=TRADITIONAL_COMMAND, segment_index=SEGMENT_INDEX,
                          tilt_step_limited=TILT_STEP_LIMITED)
#: the take-off's command, compiled: `tracking_command`
TRACKING_COMMAND = Kernel(tracking_command, _poly_axes=POLY_AXES, expert_law=EXPERT_LAW)
#: the onboard program's take-off step, compiled: `takeoff_step`
TAKEOFF_STEP = Kernel(takeoff_step, predicted_state=PREDICTED_STATE, takeoff_heading=Kernel(takeoff_heading),
                      tracking_command=TRACKING_COMMAND)
