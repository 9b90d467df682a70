"""The onboard state estimate: position, velocity and acceleration from timestamped mocap poses (a
constant-acceleration Kalman filter per axis), attitude straight from the mocap quaternion.

Mocap gives pose only; velocity and acceleration are estimated here, as on the real vehicle (where
position and velocity come from motion capture too). The filter runs on the mocap exposure stamps, so
link jitter does not enter the derivatives; the estimate handed to a pilot is predicted from the
latest stamp over the time since that pose arrived plus a configured exposure-to-arrival latency (the
two clocks need not agree, so the mean latency is a setting, not a measurement). The pose-to-pose
variation of that latency (radio jitter, 5 ms std by default) is measured, though: the arrival-minus-
stamp difference is averaged over ``delay_window_s``, and a pose that came later than the average is
predicted over the extra delay (clock offset and slow drift cancel in the difference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from policies.frames import matrix_to_euler, quat_to_matrix


@dataclass(frozen=True)
class EstimatorConfig:
    """Noise model: mocap position noise (m, 1 sigma), jerk spectral density ((m/s^3)^2 s), reset gap (s),
    the mean latency (s) from exposure to arrival that the estimate is predicted over, and the window (s)
    over which the arrival-minus-stamp difference is averaged to take out the jitter around that mean."""

    pos_noise_m: float = 0.003
    jerk_psd: float = 2000.0
    reset_after_s: float = 0.5  # a silence longer than this restarts the filter at rest
    # exposure -> arrival with the default links: camera 5.6 ms + processing 0.5 ms + UWB radio 20 ms
    # + air and UART time ~1 ms + reading ~1 ms (measured mean 28.3 ms, std 4.4 ms)
    latency_s: float = 0.028
    delay_window_s: float = 1.0  # time constant of the running mean of (arrival - stamp)

    def __post_init__(self) -> None:
        for name in ("pos_noise_m", "jerk_psd", "reset_after_s", "delay_window_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"EstimatorConfig.{name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.latency_s) and 0 <= self.latency_s < self.reset_after_s):
            raise ValueError(f"EstimatorConfig.latency_s must be in [0, reset_after_s), got {self.latency_s}")


@dataclass(frozen=True)
class StateEstimate:
    """Position (m), velocity (m/s), acceleration (m/s^2) in world ENU; ZYX Euler angles (rad) and the
    attitude quaternion (w, x, y, z) of body FLU -> world ENU."""

    pos_m: np.ndarray
    vel_m_s: np.ndarray
    acc_m_s2: np.ndarray
    euler_rad: np.ndarray
    quat_wxyz: np.ndarray


class PoseEstimator:
    """Feed poses with `update(stamp_s, pos_m, quat_wxyz, received_s)`; read `estimate(now_s)`."""

    def __init__(self, config: EstimatorConfig | None = None) -> None:
        self.config = config or EstimatorConfig()
        self._x: np.ndarray | None = None  # (3 states p, v, a) x (3 axes)
        self._P = np.zeros((3, 3))  # covariance, the same for every axis
        self._stamp_s = -math.inf
        self._received_s = -math.inf
        self._delay_s = 0.0  # arrival - stamp of the latest pose (s; includes any clock offset)
        self._mean_delay_s = 0.0  # its running mean over delay_window_s
        self._quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.updates = 0
        self.rejected = 0  # poses out of order, repeated or not finite

    @property
    def ready(self) -> bool:
        return self._x is not None

    def update(self, stamp_s: float, pos_m: np.ndarray, quat_wxyz: np.ndarray, received_s: float) -> bool:
        """Take one pose (exposure time ``stamp_s``, arrival ``received_s``, s); False if rejected."""
        pos = np.asarray(pos_m, dtype=float)
        quat = np.asarray(quat_wxyz, dtype=float)
        if (pos.shape != (3,) or quat.shape != (4,) or not np.all(np.isfinite(pos))
                or not np.all(np.isfinite(quat)) or not math.isfinite(stamp_s) or stamp_s <= self._stamp_s):
            self.rejected += 1
            return False
        dt = stamp_s - self._stamp_s
        delay = received_s - stamp_s
        if self._x is None or dt > self.config.reset_after_s:
            self._x = np.stack([pos, np.zeros(3), np.zeros(3)])
            r2 = self.config.pos_noise_m**2
            self._P = np.diag([r2, 1.0, 10.0])
            self._mean_delay_s = delay
        else:
            self._mean_delay_s += min(1.0, dt / self.config.delay_window_s) * (delay - self._mean_delay_s)
            F = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
            q = self.config.jerk_psd
            Q = q * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6],
                              [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                              [dt**3 / 6, dt**2 / 2, dt]])
            x = F @ self._x
            P = F @ self._P @ F.T + Q
            s = P[0, 0] + self.config.pos_noise_m**2
            k = P[:, 0] / s
            self._x = x + np.outer(k, pos - x[0])
            self._P = P - np.outer(k, P[0, :])
        self._stamp_s = stamp_s
        self._received_s = received_s
        self._delay_s = delay
        self._quat = quat / np.linalg.norm(quat)
        self.updates += 1
        return True

    def estimate(self, now_s: float) -> StateEstimate:
        """The state predicted to ``now_s`` (reader clock) from the latest pose: over its age, plus the
        configured mean latency, plus how much later than the average it arrived. ValueError if no
        pose has come yet."""
        if self._x is None:
            raise ValueError("no pose received yet")
        age = max(0.0, now_s - self._received_s)
        h = age + self.config.latency_s + (self._delay_s - self._mean_delay_s)
        h = min(max(h, 0.0), self.config.reset_after_s)
        p, v, a = self._x
        roll, pitch, yaw = matrix_to_euler(quat_to_matrix(self._quat))
        return StateEstimate(p + v * h + a * h * h / 2, v + a * h, a.copy(),
                             np.array([float(roll), float(pitch), float(yaw)]), self._quat.copy())
