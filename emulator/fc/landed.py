"""The FC's test of a body on the ground, compiled: its own landing detection and the batched steppers
that must stop where it would see a landing use this one function."""

from __future__ import annotations

from numba import njit

LANDED_MAX_SPEED_M_S = 0.3  # on the ground: near the resting height and climbing or sinking slower than this


@njit(cache=True)
def body_landed(z_m: float, vz_m_s: float, rest_z_m: float, margin_m: float) -> bool:
    """Whether a body at height ``z_m`` (m) climbing at ``vz_m_s`` (m/s) is on the ground: within
    ``margin_m`` (m) of its resting height ``rest_z_m`` (m) and slower than `LANDED_MAX_SPEED_M_S`."""
    return z_m - rest_z_m <= margin_m and abs(vz_m_s) < LANDED_MAX_SPEED_M_S
