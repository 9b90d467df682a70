"""The onboard pose estimator: the scalar filter is the textbook Kalman filter, and bad poses are
refused without raising."""

from __future__ import annotations

import math

import numpy as np
import pytest

from policies.frames import quat_to_matrix
from policies.onboard.estimator import EstimatorConfig, PoseEstimator

RNG_SEED = 11


def _reference_filter(cfg: EstimatorConfig, poses: list[tuple[float, np.ndarray]]) -> np.ndarray:
    """A plain matrix constant-acceleration Kalman filter per axis (the estimator's model)."""
    x = P = None
    last = -math.inf
    for stamp, z in poses:
        dt = stamp - last
        if x is None or dt > cfg.reset_after_s:
            x = np.stack([z, np.zeros(3), np.zeros(3)])
            P = np.diag([cfg.pos_noise_m**2, 1.0, 10.0])
        else:
            F = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
            Q = cfg.jerk_psd * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6],
                                         [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                                         [dt**3 / 6, dt**2 / 2, dt]])
            x, P = F @ x, F @ P @ F.T + Q
            k = P[:, 0] / (P[0, 0] + cfg.pos_noise_m**2)
            x = x + np.outer(k, z - x[0])
            P = P - np.outer(k, P[0, :])
        last = stamp
    assert x is not None
    return x


def test_scalar_estimator_is_the_matrix_kalman_filter():
    rng = np.random.default_rng(RNG_SEED)
    cfg = EstimatorConfig()
    est = PoseEstimator(cfg)
    poses = []
    t = 0.0
    for k in range(400):
        t += 1 / 120 + (0.6 if k == 200 else 0.0)  # one silence long enough to restart the filter
        pos = np.array([math.sin(t), 0.5 * t * t, 2.0 - math.cos(2 * t)]) + rng.normal(0, 0.003, 3)
        poses.append((t, pos))
        assert est.update(t, pos, np.array([1.0, 0.0, 0.0, 0.0]), t + 0.028)
    x_ref = _reference_filter(cfg, poses)
    e = est.estimate(t + 0.028)  # received at t + latency, asked at once: predicted over the latency
    h = cfg.latency_s
    np.testing.assert_allclose(e.acc_m_s2, x_ref[2], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(e.vel_m_s, x_ref[1] + x_ref[2] * h, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(e.pos_m, x_ref[0] + x_ref[1] * h + x_ref[2] * h * h / 2, rtol=1e-9, atol=1e-9)


def test_estimator_rejects_bad_poses_without_raising():
    est = PoseEstimator()
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    assert not est.update(0.1, np.array([1.0, math.nan, 0.0]), quat, 0.12)
    assert not est.update(0.1, np.array([1.0, 2.0]), quat, 0.12)
    assert not est.update(0.1, np.zeros(3), np.zeros(4), 0.12)
    assert not est.update(0.1, "abc", quat, 0.12)  # type: ignore[arg-type]
    assert not est.ready and est.rejected == 4
    with pytest.raises(ValueError):
        est.estimate(0.2)
    assert est.update(0.1, np.zeros(3), np.array([0.0, 0.0, 0.0, 2.0]), 0.12)
    np.testing.assert_allclose(est.estimate(0.12).quat_wxyz, [0.0, 0.0, 0.0, 1.0])
    assert not est.update(0.1, np.zeros(3), quat, 0.13)  # the same stamp again


def _euler_of(rot: np.ndarray) -> tuple[float, float, float]:
    """ZYX (roll, pitch, yaw) of a body -> world rotation matrix (rad)."""
    return (math.atan2(rot[2, 1], rot[2, 2]), math.asin(-rot[2, 0]), math.atan2(rot[1, 0], rot[0, 0]))


def test_estimator_attitude_follows_the_latest_pose():
    est = PoseEstimator()
    rng = np.random.default_rng(3)
    for k in range(20):
        q = rng.normal(size=4)
        assert est.update(0.01 * (k + 1), np.array([0.1 * k, 0.0, 1.0]), q * 2.0, 0.01 * (k + 1) + 0.028)
        if k % 3:
            continue  # the attitude of poses nobody asked about is never computed, but must still be right
        e = est.estimate(0.01 * (k + 1) + 0.03)
        want = _euler_of(quat_to_matrix(q))
        assert np.allclose(e.euler_rad, want, atol=1e-12)
        assert np.allclose(e.quat_wxyz, q / np.linalg.norm(q), atol=1e-15)
    assert not est.update(1.0, (0.0, math.nan, 0.0), (1.0, 0.0, 0.0, 0.0), 1.0)
    assert not est.update(1.0, (0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 1.0)
    assert est.rejected == 2 and est.updates == 20
