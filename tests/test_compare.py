"""`hil compare`: the paper's RL case flown by the traditional, e2e and e2e_rl pilots through ptys with
two seeds and compared paired (the statistics themselves: tests/test_paired.py), one HTML page and JSON
per comparison, the figures read from the runs' summaries and pooled, bad input refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hil.cli import main as hil_main
from hil.commands.compare import compare, flight_figures, held_out_scenarios, pooled
from hil.runner import RunOptions
from hil.scenario import load_scenarios

ROOT = Path(__file__).resolve().parents[1]
RL_CASE = ROOT / "scenarios" / "gap_rl_case_roll60.scenario.yaml"


@pytest.mark.slow
def test_the_papers_rl_case_through_ptys_paired_over_seeds(tmp_path):
    """Two seeds through ptys: every run crosses, each run's approach figures are its summary's, the
    paired differences and the paper's findings carry an interval and a verdict, whatever they show
    (the measured figures are in the model card)."""
    (scenario,) = load_scenarios(RL_CASE)
    result = compare([scenario], ["traditional", "e2e", "e2e_rl"], tmp_path, RunOptions(in_process=False),
                     progress=lambda _: None, seeds=[0, 5])
    runs = result["scenarios"][scenario.id]["seeds"]
    assert set(runs) == {"0", "5"}
    for seed, per in runs.items():
        for pilot, r in per.items():
            assert r["success"]
            where = tmp_path / scenario.id / f"seed{seed}" / pilot
            summary = json.loads((where / "summary.json").read_text())
            approach = summary["flight_quality"]["segments"]["approach"]
            assert r["approach_mean_angular_rate_rad_s"] == approach["mean_angular_rate_rad_s"] > 0
            assert 1.5 < approach["duration_s"] < 2.0  # the policy's part of the paper's case
    saved = json.loads((tmp_path / "compare.json").read_text())
    assert saved["pooled"]["e2e_rl"]["runs"] == 2 and saved["pooled"]["e2e_rl"]["success_rate"] == 1.0
    d = saved["paired"]["all"]["e2e_rl - e2e"]["approach_mean_angular_rate_rad_s"]
    assert d["units"] == 2 and d["ci_low"] <= d["mean_difference"] <= d["ci_high"]
    statuses = [f["status"] for f in saved["findings"]]
    assert len(statuses) == 3 and set(statuses) <= {"reproduced", "not reproduced", "not resolved"}
    page = (tmp_path / "compare.html").read_text()
    assert page.count("<svg") == 2 and all(p in page for p in ("traditional", "e2e_rl", "95 % interval"))
    assert "<script" not in page
    for r in runs["0"].values():  # trajectories through the gap, for the overlay
        xs = [p[0] for p in r["trajectory_m"]]
        assert min(xs) < 2.0 < max(xs)


def test_figures_come_from_the_summarys_segments_and_pool():
    seg = {"start_s": 3.85, "end_s": 5.55, "mean_angular_rate_rad_s": 0.75, "mean_thrust_n": 9.5,
           "max_angular_rate_rad_s": 2.0}
    summary = {"crossed_gap": True, "collision": None, "min_clearance_m": 0.02,
               "mean_angular_rate_rad_s": 0.5, "mean_thrust_n": 8.0,
               "flight_quality": {"segments": {"approach": seg}}}
    t = np.arange(0, 11, 0.01)
    cols = {"t_s": t, "pos_m_x": t, "pos_m_y": 0 * t, "pos_m_z": 0 * t + 1}
    run = flight_figures(summary, cols)
    assert run["approach_mean_angular_rate_rad_s"] == 0.75 and run["approach_max_angular_rate_rad_s"] == 2.0
    assert run["traverse_mean_angular_rate_rad_s"] is None and run["trajectory_m"] == []  # no crossing flown
    assert run["flight_mean_thrust_n"] == 8.0
    failed = {**run, "success": False, "min_clearance_m": -0.1, "approach_mean_angular_rate_rad_s": None}
    p = pooled([run, failed])
    assert p["success_rate"] == 0.5 and p["min_clearance_m"] == -0.1 and p["runs"] == 2
    assert p["approach_mean_angular_rate_rad_s"] == 0.75 and p["flight_mean_thrust_n"] == 8.0


def test_held_out_crossings_are_seeded_scenarios():
    a, b = held_out_scenarios(3, 11), held_out_scenarios(3, 11)
    assert [s.gap for s in a] == [s.gap for s in b] and len({s.gap.roll_deg for s in a}) == 3
    assert held_out_scenarios(1, 12)[0].gap != a[0].gap


def test_bad_input_is_refused(tmp_path, capsys):
    assert hil_main(["compare", str(RL_CASE), "--pilots", "nobody", "--out", str(tmp_path)]) == 2
    assert "unknown pilot(s) nobody" in capsys.readouterr().err
    assert hil_main(["compare", str(tmp_path / "missing.scenario.yaml"), "--out", str(tmp_path)]) == 2
    assert hil_main(["compare", "--out", str(tmp_path)]) == 2
    assert "no scenario" in capsys.readouterr().err
    assert hil_main(["compare", "--held-out", "-3", "--out", str(tmp_path)]) == 2
    assert "--held-out must be 0 or more crossings, got -3" in capsys.readouterr().err
    assert hil_main(["compare", str(RL_CASE), "--seeds", "0", "--out", str(tmp_path)]) == 2
    assert "--seeds must be 1 or more, got 0" in capsys.readouterr().err
