"""The FC's gains from the vehicle profile, as a tuned flight controller would have them, and the
refusal of a profile whose motors are too slow for any attitude loop worth flying.

The rule (loop shaping on the profile's motor lag, inertia and torque authority; the constants make
the n3_tx2 profile's gains exactly those it flew with before they were derived):
- rate loop (roll, pitch): ``1.75 / motor_time_constant_s`` (rad/s^2 per rad/s): crossover near the
  motor bandwidth 1/tau, about 40 deg of phase margin. The loop commands angular acceleration and the
  inner loop multiplies by the inertia, so the gain itself needs no inertia.
- attitude loop (roll, pitch): ``0.22 x`` the rate loop (rad/s per rad), but no faster than the
  airframe's torque can turn it to the tilt limit in three time constants: ``3 / t_tilt`` with
  ``t_tilt = 2 sqrt(tilt / alpha)`` (bang-bang), ``alpha = 2 (f_max - f_idle) arm sin 45deg / Ixx``.
- yaw: rate loop ``0.24 x`` the roll rate loop, attitude loop a third of that.
- hold and landing (velocity hold): horizontal ``0.136 x`` the attitude loop (1/s), vertical twice it.
Each gain is rounded to three significant digits, as an FC's parameters are written. A profile may
set any of them (`fc_attitude_p_per_s`, `fc_rate_p_per_s`, `fc_hold_p_per_s`).

Refused (a `ProfileError` naming the field and why): an attitude loop below 4 /s (time constant over
0.25 s: the motors or the torque cannot turn the vehicle fast enough to follow attitude setpoints), a
rate loop above 3 / tau (the motors cannot follow it: phase margin under 30 deg), an attitude loop
above half the rate loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from emulator.fc.hold import HoldGains
from emulator.fc.inner_loop import InnerLoopGains
from emulator.profile import ProfileError, VehicleProfile

RATE_LOOP_PER_MOTOR_BANDWIDTH = 1.75
ATTITUDE_PER_RATE_LOOP = 0.22
TILT_TIME_CONSTANTS = 3.0
YAW_RATE_PER_RATE_LOOP = 0.24
YAW_ATTITUDE_PER_YAW_RATE = 1.0 / 3.0
HOLD_PER_ATTITUDE_LOOP = 1.5 / 11.0
HOLD_VERTICAL_PER_HORIZONTAL = 2.0
MIN_ATTITUDE_P_PER_S = 4.0
MAX_RATE_LOOP_PER_MOTOR_BANDWIDTH = 3.0
MAX_ATTITUDE_PER_RATE_LOOP = 0.5
IDLE_THROTTLE = 0.05


@dataclass(frozen=True)
class FcGains:
    """All of the FC's loop gains: the inner loop (attitude, rate) and the velocity hold."""

    inner: InnerLoopGains
    hold: HoldGains


def roll_accel_authority_rad_s2(profile: VehicleProfile, idle_throttle: float = IDLE_THROTTLE) -> float:
    """Largest roll (or pitch) angular acceleration (rad/s^2): half the rotors at full thrust, half at
    idle, about the smaller of Ixx, Iyy."""
    f_max = profile.max_thrust_per_rotor_n
    arm = profile.arm_length_m * math.sqrt(0.5)
    return 2.0 * f_max * (1.0 - idle_throttle) * arm / min(profile.fc_tuned_inertia_kgm2[:2])  # as tuned


def derived_gains(profile: VehicleProfile) -> FcGains:
    """The gains the rule of the module docstring gives ``profile`` (its overrides ignored)."""
    rate = RATE_LOOP_PER_MOTOR_BANDWIDTH / profile.motor_time_constant_s
    t_tilt = 2.0 * math.sqrt(math.radians(profile.max_tilt_deg) / roll_accel_authority_rad_s2(profile))
    att = min(ATTITUDE_PER_RATE_LOOP * rate, TILT_TIME_CONSTANTS / t_tilt)
    yaw_rate = YAW_RATE_PER_RATE_LOOP * rate
    hold = HOLD_PER_ATTITUDE_LOOP * att
    r = _three_digits
    return FcGains(
        InnerLoopGains(
            (r(att), r(att), r(YAW_ATTITUDE_PER_YAW_RATE * yaw_rate)),
            (r(rate), r(rate), r(yaw_rate)),
            IDLE_THROTTLE,
        ),
        HoldGains(r(hold), r(HOLD_VERTICAL_PER_HORIZONTAL * hold)),
    )


def _three_digits(x: float) -> float:
    return float(f"{x:.3g}")


def fc_gains(profile: VehicleProfile) -> FcGains:
    """The FC's gains for ``profile``: derived, with the profile's overrides; ProfileError when the FC
    cannot stabilise the vehicle with them (the reason names the field to change)."""
    g = derived_gains(profile)
    inner = InnerLoopGains(
        profile.fc_attitude_p_per_s or g.inner.attitude_p_per_s,
        profile.fc_rate_p_per_s or g.inner.rate_p_per_s,
        g.inner.idle_throttle,
    )
    hold = g.hold if profile.fc_hold_p_per_s is None else HoldGains(*profile.fc_hold_p_per_s)
    check_gains(profile, inner)
    return FcGains(inner, hold)


def check_gains(profile: VehicleProfile, inner: InnerLoopGains) -> None:
    """ProfileError when ``inner`` cannot stabilise ``profile`` (see the module docstring)."""
    src, tau = f"vehicle profile {profile.name}", profile.motor_time_constant_s
    att, rate = min(inner.attitude_p_per_s[:2]), max(inner.rate_p_per_s[:2])
    field = "fc_attitude_p_per_s" if profile.fc_attitude_p_per_s else "motor_time_constant_s"
    if att < MIN_ATTITUDE_P_PER_S:
        authority = roll_accel_authority_rad_s2(profile)
        raise ProfileError(
            src,
            field,
            f"the FC cannot stabilise this vehicle: its attitude loop would be {att:.2f} /s (time constant "
            f"{1 / att:.2f} s), below the {MIN_ATTITUDE_P_PER_S:g} /s needed to follow attitude setpoints; "
            f"the motors' {tau:g} s time constant allows a rate loop of "
            f"{RATE_LOOP_PER_MOTOR_BANDWIDTH / tau:.1f} /s and the torque {authority:.0f} rad/s^2 of angular "
            f"acceleration to the {profile.max_tilt_deg:g} deg tilt limit (faster motors, less inertia or "
            "a lower tilt limit)",
        )
    if rate * tau > MAX_RATE_LOOP_PER_MOTOR_BANDWIDTH:
        raise ProfileError(
            src,
            "fc_rate_p_per_s",
            f"the rate loop {rate:g} /s is faster than the motors can follow ({tau:g} s time constant: at "
            f"most {MAX_RATE_LOOP_PER_MOTOR_BANDWIDTH / tau:.1f} /s, phase margin under 30 deg above it)",
        )
    slowest_rate = min(inner.rate_p_per_s[:2])
    if max(inner.attitude_p_per_s[:2]) > MAX_ATTITUDE_PER_RATE_LOOP * slowest_rate:
        raise ProfileError(
            src,
            "fc_attitude_p_per_s",
            f"the attitude loop {max(inner.attitude_p_per_s[:2]):g} /s is more than half the rate loop "
            f"{slowest_rate:g} /s it runs through",
        )
