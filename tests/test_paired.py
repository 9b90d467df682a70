"""Paired comparisons (`hil.report.paired`) and the comparison's findings (`hil.commands.compare`) on
synthetic pilots with known differences: the interval covers the true difference at its stated rate over
many experiments, a real difference is resolved, none is not, and each finding reads as it should."""

from __future__ import annotations

import numpy as np
import pytest

from hil.commands.compare import findings, paired_comparisons
from hil.report.paired import NOT_RESOLVED, paired_difference


def _experiment(rng: np.random.Generator, delta: float, units: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Figures of pilot a over ``units`` scenarios x seeds (spread between units 0.3) and of pilot b,
    a's plus ``delta`` plus per-run noise (sd 0.05)."""
    a = 1.0 + rng.normal(0.0, 0.3, units)
    return a, a + delta + rng.normal(0.0, 0.05, units)


def test_the_interval_covers_the_true_difference_at_about_its_rate():
    rng = np.random.default_rng(1)
    covered = 0
    for k in range(300):
        a, b = _experiment(rng, 0.02)
        d = paired_difference("a", "b", a.tolist(), b.tolist(), seed=k, draws=2000)
        covered += d.ci_low <= 0.02 <= d.ci_high
    assert 0.90 <= covered / 300 <= 0.98  # 95 % intended (a percentile bootstrap runs a little short)


def test_a_real_difference_is_resolved_and_none_is_not():
    rng = np.random.default_rng(2)
    lower = [paired_difference("e2e", "e2e_rl", *map(list, _experiment(rng, -0.04)), seed=k, draws=2000)
             for k in range(50)]
    assert all(d.verdict == "e2e_rl lower" for d in lower)
    assert all(d.b_lower_in > d.units / 2 for d in lower)
    same = [paired_difference("e2e", "e2e_rl", *map(list, _experiment(rng, 0.0)), seed=k, draws=2000)
            for k in range(100)]
    assert sum(d.verdict == NOT_RESOLVED for d in same) >= 88
    higher = paired_difference("e2e", "e2e_rl", *map(list, _experiment(rng, 0.04)))
    assert higher.verdict == "e2e_rl higher" and higher.ci_low > 0


def test_missing_figures_leave_their_unit_out_and_bad_input_is_refused():
    d = paired_difference("a", "b", [1.0, None, 2.0, float("nan")], [1.5, 3.0, None, 4.0])
    assert d.units == 1 and d.mean_difference == 0.5 and d.ci_low is None and d.verdict == NOT_RESOLVED
    assert paired_difference("a", "b", [None], [None]).units == 0
    with pytest.raises(ValueError, match="as many"):
        paired_difference("a", "b", [1.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="confidence"):
        paired_difference("a", "b", [1.0], [1.0], confidence=1.5)


def test_the_papers_findings_from_synthetic_pilots():
    """e2e_rl turns less than e2e by 0.03 rad/s (resolved: reproduced); its thrust is 0.02 N above
    traditional's (resolved the other way: not reproduced) and equal to e2e's (not resolved)."""
    rng = np.random.default_rng(3)
    units = []
    for _ in range(17 * 8):
        rate, thrust = rng.normal(0.7, 0.2), rng.normal(9.4, 0.2)
        run = {}
        for pilot, d_rate, d_thrust in (("traditional", -0.1, -0.02), ("e2e", 0.0, 0.0),
                                        ("e2e_rl", -0.03, 0.0)):
            run[pilot] = {"success": True,
                          "approach_mean_angular_rate_rad_s": rate + d_rate + rng.normal(0, 0.02),
                          "approach_mean_thrust_n": thrust + d_thrust + rng.normal(0, 0.01)}
        units.append(run)
    paired = paired_comparisons(units, ["traditional", "e2e", "e2e_rl"])
    assert set(paired) == {"e2e - traditional", "e2e_rl - traditional", "e2e_rl - e2e"}
    assert paired["e2e_rl - e2e"]["success"]["mean_difference"] == 0.0
    status = {f["finding"]: f["status"] for f in findings(paired)}
    assert list(status.values()) == ["reproduced", "not reproduced", "not resolved"]
    rate = paired["e2e_rl - e2e"]["approach_mean_angular_rate_rad_s"]
    assert rate["ci_low"] < -0.03 < rate["ci_high"] < 0
    assert findings(paired_comparisons(units, ["traditional", "e2e"])) == []  # no e2e_rl flown
