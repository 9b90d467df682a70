"""The RL environment's actions as the FC takes them, compiled over its rows: the command a link would
carry, read by the FC as NED Euler angles with the plan's heading, roll and pitch within +-90 deg and
scaled back to the vehicle's tilt limit (the FC's own `limit_tilt`), the thrust within 0..full."""

from __future__ import annotations

import math

from numba import njit, prange

from emulator.fc.n3 import limit_tilt

HALF_PI = 0.5 * math.pi


@njit(cache=True, parallel=True)
def fc_targets(roll, pitch, thrust_n, ned_yaw, full_thrust_n, max_tilt_rad, out):  # pragma: no cover
    """Rows (N,) of ENU roll, pitch (rad) and thrust (N) as the FC's targets ``out`` (N, 4): NED roll,
    pitch, yaw ``ned_yaw`` (rad) and thrust (N)."""
    for i in prange(roll.shape[0]):
        r = min(max(roll[i], -HALF_PI), HALF_PI)
        p = -min(max(pitch[i], -HALF_PI), HALF_PI)
        out[i, 0], out[i, 1] = limit_tilt(r, p, max_tilt_rad)
        out[i, 2] = ned_yaw[i]
        out[i, 3] = min(max(thrust_n[i], 0.0), full_thrust_n)
