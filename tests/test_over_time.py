"""Figures over time (`hil.runner.over_time`) and per mission segment (`hil.runner.flight_quality`): a
signal sampled as the recorder samples it (10 ms, 1 ms near the gap) gives the figures of the same signal
on a uniform grid, not the sample count's; windows that cut a sample's hold; a whole run's summary
against its own time series resampled on a 1 ms grid."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil.runner.flight_quality import segment_figures, segment_windows
from hil.runner.over_time import hold_weights_s, time_integral, time_max, time_mean, window_figures
from hil.runner.run import RunOptions, run_scenario
from hil.scenario import load_scenarios

SCENARIOS = Path(__file__).parent.parent / "scenarios"


def _variable_sampling() -> tuple[np.ndarray, np.ndarray]:
    """1.7 s at 10 ms with value 0, then 0.27 s at 1 ms with value 2, a last sample at 1.97 s: most samples
    are in the short part."""
    t = np.concatenate([np.arange(170) * 0.01, 1.7 + np.arange(270) * 0.001, [1.97]])
    return t, np.where((t >= 1.7 - 1e-12) & (t < 1.97 - 1e-12), 2.0, 0.0)


def test_a_time_mean_weighs_time_not_samples():
    t, v = _variable_sampling()
    end = 1.97
    assert float(np.mean(v)) == pytest.approx(2 * 270 / 441)  # the sample mean: 1.23, dominated by 1 ms
    assert time_mean(t, v, end_s=end) == pytest.approx(2 * 0.27 / 1.97)  # 0.274, as on any uniform grid
    grid = np.arange(0.0, end - 1e-9, 0.0005)
    on_grid = v[np.searchsorted(t, grid, side="right") - 1]  # the same signal held between samples
    assert time_mean(t, v, end_s=end) == pytest.approx(float(np.mean(on_grid)), rel=1e-9)
    assert time_integral(t, v, end_s=end) == pytest.approx(0.54)
    assert time_max(t, v) == 2.0 and time_max(t, v, 0.0, 1.5) == 0.0


def test_windows_cut_holds_and_masks_and_nans_leave_time_out():
    t = np.array([0.0, 0.01, 0.02, 0.03])
    v = np.array([1.0, 3.0, 5.0, 7.0])
    # [0.005, 0.025): half of sample 0's hold, all of 1's, half of 2's
    assert hold_weights_s(t, 0.005, 0.025) == pytest.approx([0.005, 0.01, 0.005, 0.0])
    assert time_mean(t, v, 0.005, 0.025) == pytest.approx((0.5 + 3 + 2.5) / 2)
    assert hold_weights_s(t)[-1] == 0.0 and hold_weights_s(t, end_s=0.05)[-1] == 0.0  # nothing known after
    assert time_mean(t, v, mask=np.array([True, False, True, True])) == pytest.approx(3.0)
    assert time_mean(t, np.array([1.0, np.nan, 5.0, 7.0])) == pytest.approx(3.0)
    assert time_mean(t, v, 1.0, 2.0) is None and time_max(t, v, 1.0, 2.0) is None
    assert time_integral(np.zeros(0), np.zeros(0)) is None


def test_segment_windows_from_the_programs_events():
    events = [{"event": "plan", "t_s": 3.84}, {"event": "segment", "segment": "approach", "t_s": 3.85},
              {"event": "segment", "segment": "traverse", "t_s": 5.55},
              {"event": "segment", "segment": "recovery", "t_s": 5.82},
              {"event": "abort", "t_s": 6.5}]
    w = segment_windows(events, 11.0)
    assert w == {"approach": (3.85, 5.55), "traverse": (5.55, 5.82), "recovery": (5.82, 6.5),
                 "crossing": (3.85, 5.82)}
    assert segment_windows(events[:2], 4.5) == {"approach": (3.85, 4.5)}  # the run ended there
    t, v = _variable_sampling()
    cols = {"t_s": t + 3.85, "body_rate_rad_s": v, "thrust_n": np.full(len(t), 9.0)}
    f = segment_figures(cols, (3.85, 5.82))
    assert f.mean_angular_rate_rad_s == pytest.approx(2 * 0.27 / 1.97)
    assert f.angular_rate_integral_rad == pytest.approx(0.54) and f.max_angular_rate_rad_s == 2.0
    assert f.mean_thrust_n == pytest.approx(9.0) and f.thrust_impulse_n_s == pytest.approx(9.0 * 1.97)
    assert f.to_dict()["duration_s"] == pytest.approx(1.97)


def test_a_runs_summary_is_its_time_series_over_time(tmp_path: Path):
    """The summary's means and segment figures equal those of its own columns held on a 1 ms grid."""
    [scenario] = load_scenarios(SCENARIOS / "gap_rl_case_roll60.scenario.yaml")
    run = run_scenario(scenario, tmp_path / "run", RunOptions(in_process=True, pilot="e2e"))
    summary = json.loads((run.out_dir / "summary.json").read_text())
    cols = dict(np.load(run.out_dir / "timeseries.npz"))
    t = cols["t_s"]
    assert np.diff(t).min() < 0.002 < 0.009 < np.diff(t).max()  # the recorder's two sampling steps

    def on_grid(name: str, t0: float, t1: float) -> float:
        grid = np.arange(t0, t1 - 1e-9, 0.001)
        return float(np.mean(cols[name][np.searchsorted(t, grid + 1e-9, side="right") - 1]))

    segs = summary["flight_quality"]["segments"]
    assert set(segs) >= {"approach", "traverse", "recovery", "crossing"}
    for seg in ("approach", "traverse", "crossing"):
        s = segs[seg]
        assert s["mean_angular_rate_rad_s"] == pytest.approx(
            on_grid("body_rate_rad_s", s["start_s"], s["end_s"]), rel=2e-3)
        assert s["mean_thrust_n"] == pytest.approx(on_grid("thrust_n", s["start_s"], s["end_s"]), rel=1e-3)
    assert summary["mean_angular_rate_rad_s"] == pytest.approx(on_grid("body_rate_rad_s", 0.0, t[-1]),
                                                               rel=2e-3)
    crossing = segs["crossing"]
    by_samples = float(np.mean(cols["body_rate_rad_s"][(t >= crossing["start_s"]) & (t < crossing["end_s"])]))
    assert not math.isclose(by_samples, crossing["mean_angular_rate_rad_s"], rel_tol=0.1)  # what it was
    page = (run.out_dir / "report.html").read_text()
    assert "Per segment, over time" in page and f"{segs['approach']['mean_thrust_n']:.4g}" in page


def test_window_figures_are_the_time_figures_of_each_signal():
    """One window's figures of several signals, its weights computed once: each signal's `time_mean`,
    `time_max` and `time_integral` there (a non-finite sample left out of one signal only)."""
    t, v = _variable_sampling()
    other = v * 3.0 - 1.0
    other[2] = np.nan
    for window in ((0.0, 1.97), (0.1, 0.5), (5.0, 6.0)):
        got = window_figures(t, (v, other), *window)
        assert got == [(time_mean(t, x, *window), time_max(t, x, *window), time_integral(t, x, *window))
                       for x in (v, other)]
