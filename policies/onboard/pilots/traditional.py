"""The `traditional` pilot: the mission plan's reference (approach, traverse, recovery, hover) tracked by
the expert geometric controller, as in the paper's conventional pipeline."""

from __future__ import annotations

import math

import numpy as np

from policies.compiling import Kernel
from policies.controller import (
    EXPERT_LAW,
    AttitudeThrustCommand,
    ExpertController,
    ExpertGains,
    _new_command,
    expert_law,
)
from policies.gap_planning import PLAN_FLOATS, PLAN_REFERENCE, POLY_AXES, _poly_axes, plan_reference
from policies.onboard.pilots import Observation, PilotContext, flown_by


class TraditionalPilot:
    """Reference from ``obs.plan`` at ``obs.t_s``, expert controller on the estimated p and v (one
    compiled call a step: `traditional_command`)."""

    def __init__(self, mass_kg: float = 0.9, max_tilt_deg: float = 75.0) -> None:
        self.controller = ExpertController(mass_kg, ExpertGains(tilt_max_rad=math.radians(max_tilt_deg)))
        self.flies = flown_by()
        self._mass_kg, self._gains = self.controller.mass_kg, self.controller.gains_array
        # (the compiled form for a plan's packed array (read-only), floats and these gains: no dispatch)
        plan = np.zeros(PLAN_FLOATS)
        plan.flags.writeable = False
        self._step = TRADITIONAL_COMMAND.entry(plan, *(0.0,) * 8, self._gains)

    def command(self, obs: Observation) -> AttitudeThrustCommand:
        pos, vel = obs.pos_vel()  # (plain floats where the observation holds them so, else the arrays)
        if pos.__class__ is not tuple:
            pos, vel = tuple(np.asarray(pos, float).tolist()), tuple(np.asarray(vel, float).tolist())
        (px, py, pz), (vx, vy, vz) = pos, vel
        roll, pitch, yaw, thrust = self._step(obs.plan.packed, obs.t_s, px, py, pz, vx, vy, vz, self._mass_kg,
                                              self._gains)
        if not math.isfinite(roll + pitch + thrust):  # a bad input: the controller's checks name it
            p, v, a, yaw = obs.plan.reference_tuples(obs.t_s)
            return self.controller.command(p, v, a, yaw, pos, vel)
        return _new_command(roll, pitch, thrust, yaw)


def traditional_command(plan: np.ndarray, t_s: float, px: float, py: float, pz: float, vx: float, vy: float,
                        vz: float, mass_kg: float, gains: np.ndarray) -> tuple[float, float, float, float]:
    """The pilot's command at mission time ``t_s`` (s) for the plan packed in ``plan`` (`MissionPlan.packed`)
    and the state ``p`` (m), ``v`` (m/s): `expert_law` on `plan_reference`, roll, pitch, yaw (rad) and
    thrust (N). Compiled by numba (`policies.compiling`), which is how it runs."""
    prx, pry, prz, vrx, vry, vrz, arx, ary, arz, yaw = plan_reference(plan, t_s)
    roll, pitch, thrust = expert_law(prx, pry, prz, vrx, vry, vrz, arx, ary, arz, px, py, pz, vx, vy, vz, yaw,
                                     mass_kg, gains)
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


def make_pilot(context: PilotContext) -> TraditionalPilot:
    return TraditionalPilot(context.mass_kg, context.max_tilt_deg)


#: the pilot's command, compiled: `traditional_command`
TRADITIONAL_COMMAND = Kernel(traditional_command, plan_reference=PLAN_REFERENCE, expert_law=EXPERT_LAW)
#: the take-off's command, compiled: `tracking_command`
TRACKING_COMMAND = Kernel(tracking_command, _poly_axes=POLY_AXES, expert_law=EXPERT_LAW)
