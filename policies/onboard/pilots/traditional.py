"""The `traditional` pilot: the mission plan's reference (approach, traverse, recovery, hover) tracked by
the expert geometric controller, as in the paper's conventional pipeline."""

from __future__ import annotations

import math

from policies.controller import AttitudeThrustCommand, ExpertController, ExpertGains
from policies.onboard.pilots import Observation, PilotContext, flown_by


class TraditionalPilot:
    """Reference from ``obs.plan`` at ``obs.t_s``, expert controller on the estimated p and v."""

    def __init__(self, mass_kg: float = 0.9, max_tilt_deg: float = 75.0) -> None:
        self.controller = ExpertController(mass_kg, ExpertGains(tilt_max_rad=math.radians(max_tilt_deg)))
        self.flies = flown_by()

    def command(self, obs: Observation) -> AttitudeThrustCommand:
        p, v, a, yaw = obs.plan.reference_tuples(obs.t_s)  # `reference` in plain floats
        pos, vel = obs.pos_vel()  # (the same numbers; plain floats where the observation holds them so)
        return self.controller.command(p, v, a, yaw, pos, vel)


def make_pilot(context: PilotContext) -> TraditionalPilot:
    return TraditionalPilot(context.mass_kg, context.max_tilt_deg)
