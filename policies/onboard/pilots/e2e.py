"""The `e2e` pilot: the shipped end-to-end policy network (onnxruntime) flies the approach; traverse,
recovery and hover as the traditional pilot. Options: ``onnx=<path>``, ``acc_input=zero|measured``."""

from __future__ import annotations

from policies.learning.learned_pilots import EndToEndPilot, make_e2e
from policies.onboard.pilots import PilotContext


def make_pilot(context: PilotContext) -> EndToEndPilot:
    return make_e2e(context.mass_kg, context.options, context.max_tilt_deg)
