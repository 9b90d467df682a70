"""policies.onboard.estimator: the attitude of the latest pose, read when asked for."""

from __future__ import annotations

import math

import numpy as np

from policies.frames import quat_to_matrix
from policies.onboard.estimator import PoseEstimator


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
