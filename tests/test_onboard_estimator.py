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


def test_integer_and_numpy_numbers_are_taken_as_their_float_values():
    """The compiled intake and prediction run for float arguments; other real numbers count as the floats
    they are equal to."""
    floats, others = PoseEstimator(max_accel_m_s2=30.0), PoseEstimator(max_accel_m_s2=30.0)
    for k in range(1, 5):
        stamp = k * 0.01
        assert floats.take(stamp, (1.0, -2.0, 1.0), (0.0, 0.0, 0.0, 2.0), stamp + 0.03)
        assert others.take(np.float64(stamp), (1, -2, 1), (0, 0, 0, 2), np.float64(stamp + 0.03))
    assert others.state_tuples(0.07) == floats.state_tuples(0.07)
    assert others.state_tuples(np.float64(0.07)) == floats.state_tuples(0.07)
    assert others.quat_wxyz == floats.quat_wxyz and others.updates == floats.updates == 4


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


def _flight(est: PoseEstimator, n: int, t0: float = 0.0) -> float:
    """``n`` poses at 120 Hz of a vehicle speeding up at 5 m/s^2 along x, with 0.2 mm noise; the last t."""
    rng = np.random.default_rng(RNG_SEED)
    t = t0
    for _ in range(n):
        t += 1 / 120
        pos = np.array([2.5 * t * t, 0.0, 1.0]) + rng.normal(0, 0.2e-3, 3)
        assert est.update(t, pos, np.array([1.0, 0.0, 0.0, 0.0]), t + 0.028)
    return t


N3_ACCEL_M_S2 = 24.0 / 0.9 + 9.81  # the n3_tx2's thrust / mass + g


def test_a_pose_the_vehicle_cannot_reach_is_refused_and_counted():
    """A 3 m jump in one frame (375 m/s): refused, counted; the next true pose is taken again."""
    est = PoseEstimator(EstimatorConfig(), max_accel_m_s2=N3_ACCEL_M_S2)
    t = _flight(est, 120)
    true = np.array([2.5 * t * t, 0.0, 1.0])
    before = est.estimate(t + 0.028).pos_m
    t += 1 / 120
    assert not est.update(t, true + np.array([3.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0]), t + 0.028)
    assert (est.rejected, est.implausible, est.implausible_run) == (1, 1, 1)
    assert est.latest_jump_m == pytest.approx(3.0, abs=0.05)
    np.testing.assert_allclose(est.estimate(t + 0.028).pos_m, before, atol=0.1)  # not flown on
    t += 1 / 120
    assert est.update(t, np.array([2.5 * t * t, 0.0, 1.0]), np.array([1.0, 0.0, 0.0, 0.0]), t + 0.028)
    assert est.implausible_run == 0 and est.implausible == 1
    # without the vehicle's limit (the default) a jump is taken: the check needs the vehicle's physics
    free = PoseEstimator()
    t = _flight(free, 120)
    assert free.update(t + 1 / 120, np.array([2.5 * t * t + 3.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0, 0.0]),
                       t + 0.036)


def test_a_drift_of_a_metre_a_frame_is_refused_frame_after_frame():
    est = PoseEstimator(EstimatorConfig(), max_accel_m_s2=N3_ACCEL_M_S2)
    t = _flight(est, 120)
    for k in range(1, 13):
        t += 1 / 120
        pos = np.array([2.5 * t * t + k * 1.0, 0.0, 1.0])
        assert not est.update(t, pos, np.array([1.0, 0.0, 0.0, 0.0]), t + 0.028)
    assert est.implausible == est.implausible_run == 12 and est.updates == 120


def test_a_crash_on_the_floor_and_a_restart_in_flight_are_not_implausible():
    """What a vehicle can do is taken: stopped by the floor from a 5 m/s fall within one frame, and a
    filter restarted at rest (after a silence) on a vehicle flying at 5 m/s."""
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    est = PoseEstimator(EstimatorConfig(), max_accel_m_s2=N3_ACCEL_M_S2)
    t, z = 0.0, 3.0
    for _ in range(60):  # falling at 5 m/s
        t, z = t + 1 / 120, z - 5.0 / 120
        assert est.update(t, np.array([0.0, 0.0, z]), quat, t + 0.028)
    for _ in range(10):  # on the floor
        t += 1 / 120
        assert est.update(t, np.array([0.0, 0.0, z]), quat, t + 0.028)
    t += 1.0  # a silence: the filter restarts at rest
    for _ in range(10):
        t += 1 / 120
        assert est.update(t, np.array([5.0 * t, 0.0, 1.0]), quat, t + 0.028)
    assert est.implausible == 0


def test_a_static_body_refuses_a_swapped_or_turned_pose():
    from policies.onboard.estimator import StaticPoseCheck

    check = StaticPoseCheck(jump_m=0.05, turn_rad=math.radians(2.0))
    level = (1.0, 0.0, 0.0, 0.0)
    assert check.update((0.0, 0.5, 2.1), level, 0.0)
    assert check.update((0.0002, 0.5, 2.1), level, 0.01)  # the tracker's noise
    assert not check.update((-2.0, -1.0, 0.5), level, 0.02)  # the vehicle's pose, swapped in
    half = math.radians(5.0) / 2
    assert not check.update((0.0, 0.5, 2.1), (math.cos(half), math.sin(half), 0.0, 0.0), 0.03)  # turned 5 deg
    assert (check.implausible, check.implausible_run) == (2, 2)
    assert check.pose is not None and check.pose[0][0] == 0.0002 and check.received_s == 0.01
    assert check.update((0.0, 0.5, 2.1), level, 0.04) and check.implausible_run == 0
