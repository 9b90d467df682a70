"""Training loops and `hil train`: files written, metrics in physical units, resume continues where the
checkpoint stopped, bad options give a clear error."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from hil.cli import main as hil_main
from policies.learning.data import ControllerDataConfig, PlannerDataConfig
from policies.learning.onnx_runtime import OnnxModel
from policies.learning.train import TrainConfig, lr_at, train_controller, train_planner

TINY_PLANNER = PlannerDataConfig(n_trajectories=60, samples_per_trajectory=100, seed=2)


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_CACHE_DIR", str(tmp_path / "cache"))


def _cfg(out, **kw) -> TrainConfig:
    base = {"out_dir": str(out), "epochs": 1.0, "batch_size": 256, "log_every": 2, "progress": False}
    return TrainConfig(**{**base, **kw})


def test_planner_training_writes_weights_metrics_curve_and_resumes(tmp_path):
    first = train_planner(TINY_PLANNER, _cfg(tmp_path / "p"), holdout_trajectories=5)
    steps_one_epoch = first.steps
    assert steps_one_epoch == int(np.ceil(len_kept(first) * 100 / 256))
    for name in ("planner.pt", "checkpoint.pt", "metrics.json", "curve.png"):
        assert (tmp_path / "p" / name).is_file()
    metrics = json.loads((tmp_path / "p" / "metrics.json").read_text())
    for key in ("mean_pos_m", "max_pos_m", "mean_vel_m_s", "max_acc_m_s2"):
        assert np.isfinite(metrics["holdout"][key]) and metrics["holdout"][key] > 0
    assert metrics["paper_case"]["paper_max_pos_m"] == 0.058
    history = torch.load(tmp_path / "p" / "checkpoint.pt", weights_only=False)["history"]
    assert history[0][3] > history[-1][3]  # validation loss went down
    second = train_planner(TINY_PLANNER, _cfg(tmp_path / "p", epochs=2.0), holdout_trajectories=5)
    assert second.steps == 2 * steps_one_epoch  # resumed: only the second epoch was run
    fresh = train_planner(TINY_PLANNER, _cfg(tmp_path / "p", epochs=2.0, resume=False),
                          holdout_trajectories=5)
    assert fresh.steps == 2 * steps_one_epoch


def test_lr_schedules_run_from_lr_to_the_final_fraction():
    for schedule in ("exp", "cosine"):
        cfg = TrainConfig(lr=2e-3, lr_final_frac=0.01, schedule=schedule)
        assert lr_at(cfg, 0.0) == pytest.approx(2e-3) and lr_at(cfg, 1.0) == pytest.approx(2e-5)
        values = [lr_at(cfg, f) for f in np.linspace(0.0, 1.0, 11)]
        assert all(a > b for a, b in itertools.pairwise(values))
    # the cosine schedule keeps a higher rate for longer: at half time, about half of lr
    assert lr_at(TrainConfig(lr=2e-3, schedule="cosine"), 0.5) == pytest.approx(1e-3 * 1.01)
    with pytest.raises(ValueError, match="schedule"):
        TrainConfig(schedule="linear")


def len_kept(result) -> int:
    return int(result.metrics["data"]["trajectories"])


def test_controller_training_reports_angle_and_thrust_errors(tmp_path):
    result = train_controller(ControllerDataConfig(n_per_set=4000, seed=1), _cfg(tmp_path / "c", epochs=3.0),
                              holdout_per_set=500)
    assert result.steps == 3 * int(np.ceil(8000 / 256))
    for part in ("holdout_large", "holdout_short"):
        m = result.metrics[part]
        assert 0 < m["mean_angle_deg"] <= m["max_angle_deg"] <= 180
        assert 0 < m["mean_thrust_n"] <= m["max_thrust_n"]
    history = torch.load(tmp_path / "c" / "checkpoint.pt", weights_only=False)["history"]
    assert history[0][3] > history[-1][3]
    # a planner checkpoint in the same folder is refused, not silently loaded
    with pytest.raises(ValueError, match="planner"):
        train_planner(TINY_PLANNER, _cfg(tmp_path / "c"), holdout_trajectories=5)


def test_hil_train_cli_trains_exports_and_rejects_bad_options(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = hil_main(["train", "planner", "--trajectories", "40", "--samples-per-trajectory", "10",
                   "--epochs", "1", "--batch-size", "128", "--out", str(out), "--no-progress",
                   "--schedule", "cosine", "--end-fraction", "0.5"])
    assert rc == 0
    printed = json.loads(capsys.readouterr().out.split("\nwrote")[0])
    assert printed["steps"] >= 1 and "max_pos_m" in printed["paper_case"]
    model = OnnxModel(out / "planner.onnx")
    assert model.n_inputs == 17 and model.n_outputs == 9
    rc = hil_main(["train", "controller", "--samples-per-set", "1000", "--epochs", "1", "--batch-size", "256",
                   "--out", str(tmp_path / "ctl"), "--no-progress"])
    assert rc == 0
    capsys.readouterr()
    rc = hil_main(["train", "export", "--planner", str(out / "planner.pt"), "--controller",
                   str(tmp_path / "ctl" / "controller.pt"), "--out", str(tmp_path / "onnx")])
    assert rc == 0 and OnnxModel(tmp_path / "onnx" / "e2e.onnx").n_inputs == 29
    exported = json.loads((tmp_path / "onnx" / "metrics.json").read_text())
    assert exported["planner"]["steps"] == printed["steps"]  # the training's metrics carried over
    assert exported["planner"]["paper_case"]["max_pos_m"] == pytest.approx(printed["paper_case"]["max_pos_m"],
                                                                           rel=1e-4)
    assert "holdout_large" in exported["controller"]
    rc = hil_main(["train", "planner", "--batch-size", "0", "--out", str(tmp_path / "bad"), "--no-progress"])
    assert rc == 1
    assert "batch_size" in capsys.readouterr().err


def test_a_bfloat16_phase_trains_and_the_metrics_show_both_planner_forms(tmp_path):
    cfg = _cfg(tmp_path / "bf", epochs=2.0, bf16_fraction=0.5)
    r = train_planner(TINY_PLANNER, cfg, holdout_trajectories=5)
    history = torch.load(tmp_path / "bf" / "checkpoint.pt", weights_only=False)["history"]
    assert all(np.isfinite(row[2]) for row in history) and history[0][3] > history[-1][3]
    metrics = r.metrics
    # the deployed planner (the MLP's odd part) and the bare MLP, each on held-out data and the paper case
    for key in ("holdout", "holdout_bare_mlp", "paper_case", "paper_case_bare_mlp"):
        assert np.isfinite(metrics[key]["max_pos_m"]) and metrics[key]["max_pos_m"] > 0
    assert metrics["holdout"]["max_pos_m"] != metrics["holdout_bare_mlp"]["max_pos_m"]
    with pytest.raises(ValueError, match="bf16_fraction"):
        TrainConfig(bf16_fraction=1.5)
