"""Training data: seeded, within the paper's ranges, labelled exactly by the primitives and the expert,
augmented by exact symmetries, and cached on disk by parameters."""

from __future__ import annotations

import numpy as np
import pytest

from policies.controller import expert_command_batch
from policies.learning.data import (
    ControllerDataConfig,
    PlannerDataConfig,
    PlannerSampler,
    augment_planner,
    cache_dir,
    controller_data,
    label_controller,
    planner_data,
)
from policies.primitives import solve

SMALL = PlannerDataConfig(n_trajectories=300, samples_per_trajectory=50, seed=3)


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_CACHE_DIR", str(tmp_path / "cache"))


def _relabel(x: np.ndarray) -> np.ndarray:
    """Labels for planner inputs by solving each primitive afresh from the inputs alone."""
    dp, T = x[:, 2:5], np.linalg.norm(x[:, 2:5], axis=1) / x[:, 1]
    tr = solve(np.zeros(3), x[:, 5:8], x[:, 8:11], dp, x[:, 11:14], x[:, 14:17], T)
    return np.concatenate(tr.state(x[:, 0]), axis=1)


def test_planner_data_is_seeded_and_in_the_papers_ranges():
    a, b = planner_data(SMALL, use_cache=False), planner_data(SMALL, use_cache=False)
    other = planner_data(PlannerDataConfig(n_trajectories=300, samples_per_trajectory=50, seed=4),
                         use_cache=False)
    assert np.array_equal(a.dp_m, b.dp_m) and not np.array_equal(a.dp_m[:10], other.dp_m[:10])
    assert len(a) + a.n_dropped == 300 and 0 < a.n_dropped < 150
    assert np.abs(a.dp_m).max() <= 30 and np.abs(a.v0_m_s).max() <= 10 and np.abs(a.af_m_s2).max() <= 10
    v_bar = np.linalg.norm(a.dp_m, axis=1) / a.duration_s
    assert v_bar.min() >= 1.0 - 1e-9 and v_bar.max() <= 7.0 + 1e-9


def test_kept_trajectories_respect_the_outlier_thresholds():
    data = planner_data(SMALL, use_cache=False)
    x, y = data.all_samples()
    assert x.shape == (len(data) * 50, 17) and y.shape == (len(data) * 50, 9)
    assert np.abs(y[:, 0:3]).max() <= SMALL.max_pos_m
    assert np.abs(y[:, 3:6]).max() <= SMALL.max_vel_m_s
    assert np.abs(y[:, 6:9]).max() <= SMALL.max_acc_m_s2


def test_planner_labels_are_the_primitive_and_hit_the_boundary_states():
    data = planner_data(SMALL, use_cache=False)
    x, y = data.all_samples()
    np.testing.assert_allclose(y, _relabel(x), atol=1e-6)
    first, last = slice(0, None, 50), slice(49, None, 50)
    np.testing.assert_allclose(x[first, 0], 0.0)
    np.testing.assert_allclose(x[last, 0], data.duration_s)
    np.testing.assert_allclose(y[first, 3:9], np.concatenate([data.v0_m_s, data.a0_m_s2], 1), atol=1e-9)
    np.testing.assert_allclose(y[last], np.concatenate([data.dp_m, data.vf_m_s, data.af_m_s2], 1), atol=1e-6)


def test_augmentation_keeps_labels_exact():
    data = planner_data(SMALL, use_cache=False)
    x, y = PlannerSampler(data, np.random.default_rng(0), augment=False).batch(2000)
    xa, ya = augment_planner(x, y, np.random.default_rng(1))
    flipped = np.sign(xa[:, 2]) != np.sign(x[:, 2])
    scaled = ~np.isclose(xa[:, 1], x[:, 1])
    assert 0.3 < flipped.mean() < 0.7 and 0.3 < scaled.mean() < 0.7
    assert np.abs(xa[:, 1] / x[:, 1]).max() <= 5.0
    np.testing.assert_array_equal(xa[:, 0], x[:, 0])
    np.testing.assert_allclose(ya, _relabel(xa), atol=1e-5)


def test_end_fraction_samples_more_times_near_both_ends():
    data = planner_data(SMALL, use_cache=False)
    x_uni, _ = PlannerSampler(data, np.random.default_rng(0), augment=False).batch(20_000)
    ends = PlannerSampler(data, np.random.default_rng(0), augment=False, end_fraction=1.0)
    x_end, y_end = ends.batch(20_000)

    def tau(x: np.ndarray) -> np.ndarray:  # t / T, T = |dp| / v_bar
        return x[:, 0] / (np.linalg.norm(x[:, 2:5], axis=1) / x[:, 1])

    def near(t: np.ndarray) -> float:
        return float(np.mean((t < 0.1) | (t > 0.9)))

    tau_uni, tau_end = tau(x_uni), tau(x_end)
    assert near(tau_uni) == pytest.approx(0.2, abs=0.02)
    assert near(tau_end) == pytest.approx(0.41, abs=0.02)  # arcsine law: 2 * acos(0.8) / pi
    assert tau_end.min() >= 0.0 and tau_end.max() <= 1.0 + 1e-12
    np.testing.assert_allclose(y_end, _relabel(x_end), atol=1e-6)  # still exact labels on the grid
    with pytest.raises(ValueError, match="end_fraction"):
        PlannerSampler(data, np.random.default_rng(0), end_fraction=1.5)


def test_planner_data_is_cached_by_its_parameters():
    first = planner_data(SMALL)
    files = sorted(cache_dir().glob("planner-*.npz"))
    assert len(files) == 1
    again = planner_data(SMALL)
    np.testing.assert_array_equal(first.duration_s, again.duration_s)
    planner_data(PlannerDataConfig(n_trajectories=300, samples_per_trajectory=50, seed=5))
    assert len(list(cache_dir().glob("planner-*.npz"))) == 2


def test_controller_data_is_labelled_by_the_expert_over_both_ranges():
    cfg = ControllerDataConfig(n_per_set=5000, seed=1)
    x, y = controller_data(cfg)
    assert x.shape == (10_000, 12) and y.shape == (10_000, 3) and x.dtype == np.float32
    large, short = x[:5000], x[5000:]
    assert np.abs(large[:, 0:3]).max() > 9.0 and np.abs(large[:, 0:3]).max() <= 10.0
    assert np.abs(short[:, 0:3]).max() <= 0.2 and np.abs(short[:, 3:6]).max() <= 0.3
    assert np.abs(large[:, 9:12]).max() > 3.0 and np.abs(short[:, 9:12]).max() <= np.radians(30) + 1e-6
    zero = np.zeros((10_000, 3))
    roll, pitch, _, thrust = expert_command_batch(x[:, 0:3], x[:, 3:6], x[:, 6:9], 0.0, zero, zero, 0.9)
    np.testing.assert_allclose(y, np.stack([roll, pitch, thrust], 1), atol=1e-5)
    x2, _ = controller_data(cfg)
    np.testing.assert_array_equal(x, x2)
    assert len(list(cache_dir().glob("controller-*.npz"))) == 1


def test_controller_label_ignores_attitude_and_hovers_at_zero_error():
    x = np.zeros((2, 12))
    x[1, 9:12] = [0.5, -0.3, 2.0]
    y = label_controller(x)
    np.testing.assert_allclose(y[0], y[1])
    np.testing.assert_allclose(y[0], [0.0, 0.0, 0.9 * 9.8], atol=1e-9)
    with pytest.raises(ValueError, match=r"\(N, 12\)"):
        label_controller(np.zeros((3, 11)))
