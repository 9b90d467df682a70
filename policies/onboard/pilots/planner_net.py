"""The `planner_net` pilot: the approach planned by the shipped planner network (onnxruntime), tracked by
the expert controller; traverse, recovery and hover as the traditional pilot."""

from __future__ import annotations

from policies.learning.learned_pilots import PlannerNetPilot, make_planner_net
from policies.onboard.pilots import PilotContext


def make_pilot(context: PilotContext) -> PlannerNetPilot:
    return make_planner_net(context.mass_kg, context.options, context.max_tilt_deg)
