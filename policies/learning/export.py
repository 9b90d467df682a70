"""Export the networks to ONNX (batch axis dynamic) and rebuild them from shipped state dicts."""

from __future__ import annotations

import copy
import json
import warnings
from pathlib import Path

import numpy as np
import torch

from policies.learning.deploy import deploy_module
from policies.learning.evaluate import paper_case, paper_case_errors
from policies.learning.features import CONTROLLER_IN, E2E_IN, PLANNER_IN
from policies.learning.networks import ControllerNet, EndToEndPolicy, PlannerNet
from policies.learning.onnx_runtime import OnnxModel

INPUT_NAME, OUTPUT_NAME = "x", "y"
N_INPUTS = {"planner": PLANNER_IN, "controller": CONTROLLER_IN, "e2e": E2E_IN}
# The planner's outputs reach hundreds of m, m/s, m/s^2 on the training ranges, where float32 cannot
# hold 1e-5, so the planner and the merged policy keep float64 in and out and wherever physical units
# are computed; the merged policy runs its hidden layers (O(1) activations) in float32 for one-sample
# speed (``deploy``), its parity being checked against the same mixed computation in torch. The
# controller alone is well within 1e-5 in float32.
EXPORT_DTYPES = {"planner": torch.float64, "controller": torch.float32, "e2e": torch.float64}
EXPORT_HIDDEN = {"planner": torch.float64, "controller": torch.float32, "e2e": torch.float32}


def inference_module(model: torch.nn.Module, dtype: torch.dtype = torch.float32,
                     hidden_dtype: torch.dtype | None = None) -> torch.nn.Module:
    """The torch module ``export_onnx(model, ..., dtype, hidden_dtype)`` writes (a copy, eval mode):
    in float64 the folded ``deploy`` form with hidden layers in ``hidden_dtype`` (default float64),
    in float32 the model itself."""
    model = copy.deepcopy(model).cpu().double().eval()
    if dtype == torch.float64 and isinstance(model, (PlannerNet, ControllerNet, EndToEndPolicy)):
        return deploy_module(model, hidden_dtype or torch.float64)
    return model.to(dtype).eval()


def export_onnx(model: torch.nn.Module, n_inputs: int, path: str | Path, dtype: torch.dtype = torch.float32,
                opset: int = 17, hidden_dtype: torch.dtype | None = None) -> Path:
    """Write ``inference_module(model, dtype, hidden_dtype)`` (input ``x`` (N, n_inputs) and output ``y``
    in ``dtype``) to ``path``.

    In float64 the networks are written in their folded inference form (``deploy.deploy_module``: the
    same function to about 1e-12 when the hidden layers are float64 too, fewer graph nodes); in float32
    as they are, since folding would move their rounding by about the 1e-5 parity bound."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = inference_module(model, dtype, hidden_dtype)
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


def load_e2e(path: str | Path) -> EndToEndPolicy:
    """An ``EndToEndPolicy`` from a state-dict file of the whole policy (e.g. ``e2e_rl.pt``)."""
    net = EndToEndPolicy(PlannerNet(), ControllerNet())
    net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    return net.eval()


def export_all(planner: PlannerNet, controller: ControllerNet, out_dir: str | Path) -> dict[str, Path]:
    """Write planner.onnx, controller.onnx and e2e.onnx (the merged policy) into ``out_dir``."""
    out = Path(out_dir)
    models = {"planner": planner, "controller": controller, "e2e": EndToEndPolicy(planner, controller)}
    return {name: export_onnx(m, N_INPUTS[name], out / f"{name}.onnx", EXPORT_DTYPES[name],
                              hidden_dtype=EXPORT_HIDDEN[name])
            for name, m in models.items()}


def _training_metrics(weights: Path, name: str) -> dict[str, object]:
    """The ``metrics.json`` next to a state dict (a training's, or a shipped one's ``name`` entry)."""
    path = weights.parent / "metrics.json"
    if not path.is_file():
        return {}
    metrics = json.loads(path.read_text())
    if not isinstance(metrics, dict):
        return {}
    metrics = dict(metrics.get(name, metrics))
    if "config" in metrics:  # the training's settings, without the folder it happened to write to
        config = dict(metrics.pop("config"))
        config.pop("out_dir", None)
        metrics["train_config"] = config
    return metrics


def export_metrics(planner_pt: str | Path, controller_pt: str | Path, out_dir: str | Path) -> Path:
    """Write ``out_dir/metrics.json``: the trainings' metrics (from the ``metrics.json`` beside each state
    dict), with the planner's paper-case errors recomputed from the exported ``out_dir/planner.onnx``
    (Euclidean and per-axis worst errors), so the file states what the shipped ONNX does."""
    out = Path(out_dir)
    planner_onnx = OnnxModel(out / "planner.onnx")
    planner = _training_metrics(Path(planner_pt), "planner")
    planner["paper_case"] = paper_case_errors(planner_onnx.predict)
    x, y = paper_case()
    err = np.abs(planner_onnx.predict(x) - y)
    planner["paper_case_per_axis"] = {"max_pos_m": float(err[:, 0:3].max()),
                                      "max_vel_m_s": float(err[:, 3:6].max()),
                                      "max_acc_m_s2": float(err[:, 6:9].max())}
    bare = load_planner(planner_pt).double()
    bare.odd_symmetric = False  # the MLP alone, as trained, for comparison

    def predict_bare(inputs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return bare(torch.as_tensor(inputs, dtype=torch.float64)).numpy()

    planner["paper_case_bare_mlp"] = {k: v for k, v in paper_case_errors(predict_bare).items()
                                      if not k.startswith("paper_")}
    metrics = {"planner": planner, "controller": _training_metrics(Path(controller_pt), "controller")}
    path = out / "metrics.json"
    path.write_text(json.dumps(metrics, indent=2, default=float) + "\n")
    return path
