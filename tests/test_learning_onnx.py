"""ONNX export and onnxruntime inference: parity with torch on 10k random inputs, input checks, and the
shipped weights (present, small, consistent with their state dicts, and accurate on the paper's case)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from policies.learning.data import (
    PlannerDataConfig,
    PlannerSampler,
    draw_controller_inputs,
    planner_data,
)
from policies.learning.evaluate import PAPER_WORST_ERRORS, paper_case_errors
from policies.learning.export import EXPORT_DTYPES, export_all, load_controller, load_planner
from policies.learning.features import LARGE_RANGE
from policies.learning.networks import ControllerNet, EndToEndPolicy, PlannerNet
from policies.learning.onnx_runtime import OnnxModel, load_shipped, shipped_path

torch.set_num_threads(2)
N = 10_000


def _inputs() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(11)  # planner and merged policy in float64, controller in float32
    cfg = PlannerDataConfig(n_trajectories=500, samples_per_trajectory=200, seed=9)
    data = planner_data(cfg, use_cache=False)
    x17, _ = PlannerSampler(data, rng).batch(N)  # augmented: outputs up to hundreds of m, m/s, m/s^2
    x12 = draw_controller_inputs(LARGE_RANGE, N, rng)
    return {"planner": x17, "controller": x12, "e2e": np.concatenate([x12, x17], axis=1)}


def _torch_out(net: torch.nn.Module, x: np.ndarray, dtype: torch.dtype) -> np.ndarray:
    with torch.no_grad():
        return net.to(dtype)(torch.as_tensor(x, dtype=dtype)).double().numpy()


def _check_parity(nets: dict[str, torch.nn.Module], onnx: dict[str, OnnxModel]) -> None:
    for name, x in _inputs().items():
        ref = _torch_out(nets[name], x, EXPORT_DTYPES[name])
        out = onnx[name].predict(x)
        assert out.shape == ref.shape == (N, onnx[name].n_outputs)
        assert np.abs(out - ref).max() <= 1e-5, name


def test_export_matches_torch_within_1e_5_on_10k_random_inputs(tmp_path):
    torch.manual_seed(5)
    planner, controller = PlannerNet(), ControllerNet()
    paths = export_all(planner, controller, tmp_path)
    nets = {"planner": planner, "controller": controller, "e2e": EndToEndPolicy(planner, controller)}
    _check_parity(nets, {name: OnnxModel(path) for name, path in paths.items()})


def test_shipped_onnx_files_match_the_shipped_state_dicts():
    weights = shipped_path("planner").parent
    for name in ("planner", "controller", "e2e"):
        assert shipped_path(name).stat().st_size < 1_000_000
    planner, controller = load_planner(weights / "planner.pt"), load_controller(weights / "controller.pt")
    nets = {"planner": planner, "controller": controller, "e2e": EndToEndPolicy(planner, controller)}
    _check_parity(nets, {name: load_shipped(name) for name in nets})


def test_shipped_planner_on_the_papers_test_case_is_what_the_model_card_says():
    """The shipped planner's worst errors on the paper's test case are those recorded in
    policies/weights/metrics.json (and MODEL_CARD.md), and within 3x of the paper's network.

    The paper's own figures (0.058 m, 0.125 m/s, 0.505 m/s^2) are not reached by the shipped weights
    (see MODEL_CARD.md); tighten the bound here when better weights are shipped."""
    card = json.loads((shipped_path("planner").parent / "metrics.json").read_text())["planner"]["paper_case"]
    errors = paper_case_errors(load_shipped("planner").predict)
    for key, paper in (("max_pos_m", "pos_m"), ("max_vel_m_s", "vel_m_s"), ("max_acc_m_s2", "acc_m_s2")):
        assert errors[key] == pytest.approx(card[key], rel=1e-6)
        assert errors[key] < 3.0 * PAPER_WORST_ERRORS[paper]


def test_onnx_model_rejects_bad_inputs(tmp_path):
    model = load_shipped("controller")
    assert model.predict(np.zeros(12)).shape == (3,)
    with pytest.raises(ValueError, match=r"\(12,\) or \(N, 12\)"):
        model.predict(np.zeros(11))
    with pytest.raises(ValueError, match="finite"):
        model.predict(np.full(12, np.nan))
    with pytest.raises(FileNotFoundError):
        OnnxModel(tmp_path / "missing.onnx")
    with pytest.raises(ValueError, match="unknown network"):
        shipped_path("nope")
