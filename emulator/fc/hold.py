"""The FC's own hover and landing controller: hold a climb rate and zero horizontal velocity by
choosing the attitude and thrust the inner loop then flies (one numba function for every caller)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from emulator.profile import GRAVITY_M_S2, VehicleProfile


@dataclass(frozen=True)
class HoldGains:
    """Gains and limits of the velocity hold (hover and landing)."""

    horizontal_p_per_s: float  # horizontal acceleration (m/s^2) per m/s of velocity error
    vertical_p_per_s: float  # vertical acceleration (m/s^2) per m/s of climb-rate error
    max_horizontal_accel_m_s2: float = 3.0
    max_vertical_accel_m_s2: float = 4.0

    def __post_init__(self) -> None:
        for name in ("horizontal_p_per_s", "vertical_p_per_s", "max_horizontal_accel_m_s2",
                     "max_vertical_accel_m_s2"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"HoldGains.{name} must be a positive finite number, got {v!r}")


def pack_hold(
    gains: HoldGains, profile: VehicleProfile, max_tilt_deg: float, hover_throttle: float | None = None
) -> np.ndarray:
    """The float64 array `hold_command` reads: gains, limits, mass (kg), tan of the tilt limit,
    largest total thrust (N). ``hover_throttle``: the per-rotor throttle (0..1) the FC believes holds
    the weight (None: the profile's own); the mass it flies with follows from it."""
    mass_kg = profile.mass_kg
    if hover_throttle is not None:
        mass_kg = hover_throttle * profile.max_total_thrust_n / GRAVITY_M_S2
    return np.array(
        [
            gains.horizontal_p_per_s,
            gains.vertical_p_per_s,
            gains.max_horizontal_accel_m_s2,
            gains.max_vertical_accel_m_s2,
            mass_kg,
            math.tan(math.radians(max_tilt_deg)),
            profile.max_total_thrust_n,
        ]
    )


@njit(cache=True, nogil=True)
def hold_command(ve, vn, vu, climb, yaw, h, ve_sp, vn_sp):  # pragma: no cover
    """(roll, pitch (NED, rad), thrust (N)) that bring the velocity (east ``ve``, north ``vn``, up
    ``vu``, m/s) to ``ve_sp``, ``vn_sp`` horizontally (0, 0: hover) and ``climb`` (m/s, up)
    vertically, heading ``yaw`` (NED, rad); ``h`` from `pack_hold`."""
    ax, ay = h[0] * (vn_sp - vn), h[0] * (ve_sp - ve)  # NED north, east (m/s^2)
    norm = math.hypot(ax, ay)
    if norm > h[2]:
        ax, ay = ax * h[2] / norm, ay * h[2] / norm
    az = max(-h[3], min(h[3], -h[1] * (climb - vu)))  # NED down
    m = h[4]
    fx, fy, fz = m * ax, m * ay, m * (az - GRAVITY_M_S2)
    max_h = abs(fz) * h[5]
    fh = math.hypot(fx, fy)
    if fh > max_h:
        fx, fy = fx * max_h / fh, fy * max_h / fh
    thrust = math.sqrt(fx * fx + fy * fy + fz * fz)
    zx, zy, zz = -fx / thrust, -fy / thrust, -fz / thrust  # body z (down) in NED
    cy, sy = math.cos(yaw), math.sin(yaw)
    hx, hy = cy * zx + sy * zy, -sy * zx + cy * zy  # rotate into the heading frame
    roll = math.asin(max(-1.0, min(1.0, -hy)))
    pitch = math.atan2(hx, zz)
    return roll, pitch, min(thrust, h[6])
