"""`hil compare`: the paper's RL case flown by the traditional, e2e and e2e_rl pilots through ptys, the
paper's finding that holds asserted (the measured figures of the one that does not are in the model
card), one HTML page and JSON per comparison, the crossing's window and pooling, bad input refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.cli import main as hil_main
from hil.commands.compare import compare, crossing_window, held_out_scenarios, pooled
from hil.runner import RunOptions
from hil.scenario import load_scenarios

ROOT = Path(__file__).resolve().parents[1]
RL_CASE = ROOT / "scenarios" / "gap_rl_case_roll60.scenario.yaml"


@pytest.mark.slow
def test_the_papers_rl_case_through_ptys(tmp_path):
    (scenario,) = load_scenarios(RL_CASE)
    result = compare([scenario], ["traditional", "e2e", "e2e_rl"], tmp_path, RunOptions(in_process=False),
                     progress=lambda _: None)
    runs = result["scenarios"][scenario.id]["pilots"]
    assert all(r["success"] for r in runs.values())
    # the paper's second finding: the policy fine-tuned by RL turns less than the imitation policy (here
    # 1.59 against 1.64 rad/s over the approach and traverse; deterministic in lockstep). Its first, a
    # lower mean thrust than the traditional pipeline's, does not hold for the shipped weights (6.47
    # against 6.46 N): reported in the model card, not asserted.
    assert runs["e2e_rl"]["mean_angular_rate_rad_s"] < runs["e2e"]["mean_angular_rate_rad_s"]
    assert runs["e2e_rl"]["flight_mean_angular_rate_rad_s"] < runs["e2e"]["flight_mean_angular_rate_rad_s"]
    saved = json.loads((tmp_path / "compare.json").read_text())
    assert saved["pooled"]["e2e_rl"]["runs"] == 1 and saved["pooled"]["e2e_rl"]["success_rate"] == 1.0
    page = (tmp_path / "compare.html").read_text()
    assert page.count("<svg") == 2 and all(p in page for p in ("traditional", "e2e_rl"))
    assert "<script" not in page
    for r in runs.values():  # trajectories through the gap, for the overlay
        xs = [p[0] for p in r["trajectory_m"]]
        assert min(xs) < 2.0 < max(xs)


def test_crossing_window_and_pooling():
    events = [{"source": "onboard", "time_s": 3.8, "text": "plan"},
              {"source": "onboard", "time_s": 3.85, "text": "segment: approach"},
              {"source": "onboard", "time_s": 5.5, "text": "segment: traverse"},
              {"source": "fc", "time_s": 5.6, "text": "segment: recovery"},
              {"source": "onboard", "time_s": 5.8, "text": "segment: recovery"}]
    assert crossing_window({"events": events}) == (3.85, 5.8)
    assert crossing_window({"events": events[:3]}) is None  # aborted before the recovery
    run = {"success": True, "min_clearance_m": 0.02, "mean_angular_rate_rad_s": 1.0, "mean_thrust_n": 6.0,
           "flight_mean_angular_rate_rad_s": 0.5, "flight_mean_thrust_n": 8.0}
    failed = {**run, "success": False, "min_clearance_m": -0.1, "mean_angular_rate_rad_s": None,
              "mean_thrust_n": None}
    p = pooled([run, failed])
    assert p["success_rate"] == 0.5 and p["min_clearance_m"] == -0.1
    assert p["mean_angular_rate_rad_s"] == 1.0 and p["flight_mean_thrust_n"] == 8.0


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
