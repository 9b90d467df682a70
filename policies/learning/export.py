"""Export the networks to ONNX (batch axis dynamic) and rebuild them from shipped state dicts."""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import torch

from policies.learning.features import CONTROLLER_IN, E2E_IN, PLANNER_IN
from policies.learning.networks import ControllerNet, EndToEndPolicy, PlannerNet

INPUT_NAME, OUTPUT_NAME = "x", "y"
N_INPUTS = {"planner": PLANNER_IN, "controller": CONTROLLER_IN, "e2e": E2E_IN}
# The planner's outputs reach hundreds of m, m/s, m/s^2 on the training ranges, and the merged policy
# amplifies its planner's rounding through the controller gains (float32 differs from float64 by up to
# 1e-3 N there), so both ship in float64 to hold 1e-5; the controller alone is well within that in
# float32, where onnxruntime's one-sample latency is about a third of float64's.
EXPORT_DTYPES = {"planner": torch.float64, "controller": torch.float32, "e2e": torch.float64}


def export_onnx(model: torch.nn.Module, n_inputs: int, path: str | Path, dtype: torch.dtype = torch.float32,
                opset: int = 17) -> Path:
    """Write a copy of ``model`` in ``dtype`` (input ``x`` (N, n_inputs), output ``y``) to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = copy.deepcopy(model).cpu().to(dtype).eval()
    example = torch.zeros(1, n_inputs, dtype=dtype)
    example[:, 1] = 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (example,), str(path), input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                          dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
                          opset_version=opset, dynamo=False, do_constant_folding=True)
    return path


def load_planner(path: str | Path) -> PlannerNet:
    """A ``PlannerNet`` from a state-dict file."""
    net = PlannerNet()
    net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    return net.eval()


def load_controller(path: str | Path) -> ControllerNet:
    """A ``ControllerNet`` from a state-dict file."""
    net = ControllerNet()
    net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    return net.eval()


def export_all(planner: PlannerNet, controller: ControllerNet, out_dir: str | Path) -> dict[str, Path]:
    """Write planner.onnx, controller.onnx and e2e.onnx (the merged policy) into ``out_dir``."""
    out = Path(out_dir)
    models = {"planner": planner, "controller": controller, "e2e": EndToEndPolicy(planner, controller)}
    return {name: export_onnx(m, N_INPUTS[name], out / f"{name}.onnx", EXPORT_DTYPES[name])
            for name, m in models.items()}
