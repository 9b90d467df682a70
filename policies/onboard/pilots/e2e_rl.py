"""The `e2e_rl` pilot: the end-to-end policy fine-tuned by TRPO in `CrossGap-v0` (``e2e_rl.onnx``, through
onnxruntime) flies the approach; traverse, recovery and hover as the traditional pilot, as `e2e` does.
Options: ``onnx=<path>``, ``acc_input=zero|measured``."""

from __future__ import annotations

from policies.learning.learned_pilots import EndToEndPilot, make_e2e
from policies.onboard.pilots import PilotContext


def make_pilot(context: PilotContext) -> EndToEndPilot:
    return make_e2e(context.mass_kg, context.options, context.max_tilt_deg, shipped="e2e_rl")
