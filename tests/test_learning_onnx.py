"""ONNX export and onnxruntime inference: parity with torch on 10k random inputs, the folded inference
forms computing the trained functions, the one-sample fast path, input checks, and the shipped weights
(present, small, consistent with their state dicts, and accurate on the paper's case)."""

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
from policies.learning.evaluate import PAPER_WORST_ERRORS, paper_case, paper_case_errors
from policies.learning.export import (
    EXPORT_DTYPES,
    EXPORT_HIDDEN,
    export_all,
    inference_module,
    load_controller,
    load_planner,
)
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
    """Outputs of ``net`` (already in its dtypes) for inputs ``x`` given in ``dtype``."""
    with torch.no_grad():
        return net(torch.as_tensor(x, dtype=dtype)).double().numpy()


def _check_parity(nets: dict[str, torch.nn.Module], onnx: dict[str, OnnxModel]) -> None:
    """onnxruntime against torch running what was exported (``inference_module``: for the merged
    policy, float32 hidden layers between float64 physical units)."""
    for name, x in _inputs().items():
        ref = _torch_out(inference_module(nets[name], EXPORT_DTYPES[name], EXPORT_HIDDEN[name]), x,
                         EXPORT_DTYPES[name])
        out = onnx[name].predict(x)
        assert out.shape == ref.shape == (N, onnx[name].n_outputs)
        assert np.abs(out - ref).max() <= 1e-5, name


def test_export_matches_torch_within_1e_5_on_10k_random_inputs(tmp_path):
    torch.manual_seed(5)
    planner, controller = PlannerNet(), ControllerNet()
    paths = export_all(planner, controller, tmp_path)
    nets = {"planner": planner, "controller": controller, "e2e": EndToEndPolicy(planner, controller)}
    _check_parity(nets, {name: OnnxModel(path) for name, path in paths.items()})


def test_inference_forms_compute_the_trained_functions():
    """The folded float64 forms equal the networks to rounding; the merged policy with float32 hidden
    layers stays within 1e-4 N / 1e-5 rad of the float64 policy near the paper's test case."""
    torch.manual_seed(6)
    planner, controller = PlannerNet().double(), ControllerNet().double()
    policy = EndToEndPolicy(planner, controller)
    x = _inputs()
    for name, net in (("planner", planner), ("e2e", policy)):
        folded = inference_module(net, torch.float64)
        ref, out = _torch_out(net, x[name], torch.float64), _torch_out(folded, x[name], torch.float64)
        assert np.all(np.abs(out - ref) <= 1e-9 * (1.0 + np.abs(ref))), name
    x17, _ = paper_case(200)
    rng = np.random.default_rng(3)
    state = np.concatenate([rng.normal(0.0, 0.3, (200, 9)), rng.normal(0.0, 0.3, (200, 3))], axis=1)
    xe = np.concatenate([state, x17], axis=1)
    mixed = inference_module(policy, torch.float64, EXPORT_HIDDEN["e2e"])
    diff = np.abs(_torch_out(mixed, xe, torch.float64) - _torch_out(policy, xe, torch.float64))
    assert diff[:, 0:2].max() <= 1e-5 and diff[:, 2].max() <= 1e-4


def test_one_sample_fast_path_matches_batched_inference(tmp_path):
    torch.manual_seed(7)
    paths = export_all(PlannerNet(), ControllerNet(), tmp_path)
    x = _inputs()["e2e"][:20]
    model = OnnxModel(paths["e2e"])
    batch = model.predict(x)
    for row, want in zip(x, batch, strict=True):
        got = model.run_one(row)
        assert got.shape == (3,)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(model.predict(row), want)
    kept = model.predict(x[0])  # predict returns a copy: a later call does not overwrite it
    model.run_one(x[1])
    np.testing.assert_array_equal(kept, batch[0])
    with pytest.raises(ValueError, match="threads"):
        OnnxModel(paths["e2e"], threads=0)


def test_shipped_onnx_files_match_the_shipped_state_dicts():
    weights = shipped_path("planner").parent
    for name in ("planner", "controller", "e2e"):
        assert shipped_path(name).stat().st_size < 1_000_000
    planner, controller = load_planner(weights / "planner.pt"), load_controller(weights / "controller.pt")
    nets = {"planner": planner, "controller": controller, "e2e": EndToEndPolicy(planner, controller)}
    _check_parity(nets, {name: load_shipped(name) for name in nets})


def test_shipped_planner_on_the_papers_test_case_beats_the_papers_network():
    """The shipped planner's worst errors on the paper's test case are below the paper's network's
    (0.058 m, 0.125 m/s, 0.505 m/s^2) and are those recorded in policies/weights/metrics.json."""
    card = json.loads((shipped_path("planner").parent / "metrics.json").read_text())["planner"]["paper_case"]
    errors = paper_case_errors(load_shipped("planner").predict)
    for key, paper in (("max_pos_m", "pos_m"), ("max_vel_m_s", "vel_m_s"), ("max_acc_m_s2", "acc_m_s2")):
        assert errors[key] == pytest.approx(card[key], rel=1e-6)
        assert errors[key] < PAPER_WORST_ERRORS[paper]


def test_the_planner_returns_the_odd_part_of_its_mlp():
    # reversing every boundary state (dp, v0, a0, vf, af) reverses the plan exactly, as the primitive's
    x, _ = paper_case()
    flipped = x.copy()
    flipped[:, 2:] *= -1
    model = load_shipped("planner")
    np.testing.assert_allclose(model.predict(flipped), -model.predict(x), rtol=0, atol=1e-9)


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
