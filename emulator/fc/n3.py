"""The N3 attitude-thrust interface: OSDK control-flag semantics, the setpoint type and its validation.

Angles follow the aerospace convention of the N3's ground frame (north-east-down Euler angles): roll
positive = right side down, pitch positive = nose up, yaw = heading from north, clockwise. The vertical
channel is the total thrust in percent of ``profile.n3_full_thrust_n``. The modes this emulator flies:
HORIZONTAL_ANGLE + VERTICAL_THRUST (GROUND frame), and HORIZONTAL_VELOCITY or HORIZONTAL_POSITION (an
offset, m) with VERTICAL_VELOCITY or VERTICAL_POSITION (a height, m), GROUND or BODY frame (the Onboard
SDK's velocity and position-offset control); either yaw mode with each.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from emulator.kernel_cache import entry
from emulator.profile import VehicleProfile

# the control flag byte is the OPEN protocol's (`hil.link.dji_open` owns it)
from hil.link.dji_open import (
    ATTITUDE_THRUST_YAW_ANGLE,
    ATTITUDE_THRUST_YAW_RATE,
    FRAME_BODY,
    FRAME_GROUND,
    HORIZONTAL_ANGLE,
    HORIZONTAL_ANGULAR_RATE,
    HORIZONTAL_POSITION,
    HORIZONTAL_VELOCITY,
    STABLE_DISABLE,
    STABLE_ENABLE,
    VERTICAL_POSITION,
    VERTICAL_THRUST,
    VERTICAL_VELOCITY,
    YAW_ANGLE,
    YAW_RATE,
)

_HORIZONTAL_NAMES = {0x00: "ANGLE", 0x40: "VELOCITY", 0x80: "POSITION", 0xC0: "ANGULAR_RATE"}
_VERTICAL_NAMES = {0x00: "VELOCITY", 0x10: "POSITION", 0x20: "THRUST", 0x30: "RESERVED"}

#: the attitude-thrust control flags `check_flag` lets through (either yaw mode, stable mode on or off)
ATTITUDE_THRUST_FLAGS = frozenset(
    flag | stable
    for flag in (ATTITUDE_THRUST_YAW_ANGLE, ATTITUDE_THRUST_YAW_RATE)
    for stable in (STABLE_DISABLE, STABLE_ENABLE)
)
#: every control flag `check_flag` lets through
_FLOWN_FLAGS = ATTITUDE_THRUST_FLAGS | frozenset(
    horizontal | vertical | yaw | frame | stable
    for horizontal in (HORIZONTAL_VELOCITY, HORIZONTAL_POSITION)
    for vertical in (VERTICAL_VELOCITY, VERTICAL_POSITION)
    for yaw in (YAW_ANGLE, YAW_RATE)
    for frame in (FRAME_GROUND, FRAME_BODY)
    for stable in (STABLE_DISABLE, STABLE_ENABLE)
)
#: the Onboard SDK's limits of the velocity and position modes (dji_control.hpp): horizontal speed (m/s),
#: climb rate (m/s), height (m)
MAX_SPEED_M_S = 30.0
MAX_CLIMB_M_S = 5.0
MAX_HEIGHT_M = 120.0


class SetpointRejected(ValueError):
    """A setpoint the N3 will not fly; ``reason`` says why (short enough for a STATUSTEXT)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class N3Setpoint:
    """One flight-control setpoint as the onboard computer sends it (degrees, percent)."""

    flag: int
    roll_deg: float  # x
    pitch_deg: float  # y
    thrust_percent: float  # z, 0..100 % of n3_full_thrust_n
    yaw: float  # heading (deg) with YAW_ANGLE, or yaw rate (deg/s, clockwise) with YAW_RATE


@dataclass(frozen=True)
class AttitudeThrustTarget:
    """A validated setpoint in SI units (NED Euler angles, see the module docstring)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float  # heading; ignored when yaw_rate_rad_s is not None
    yaw_rate_rad_s: float | None
    thrust_n: float


@dataclass(frozen=True)
class MotionTarget:
    """A validated velocity or position-offset setpoint (the N3's ground frame: x north, y east; or its
    body frame: x forward, y right; z up)."""

    x: float  # m/s, or an offset (m) from where the vehicle is when the setpoint arrives
    y: float
    z: float  # climb rate (m/s), or height above the ground (m)
    horizontal_position: bool
    vertical_position: bool
    body_frame: bool
    yaw_rad: float  # heading; ignored when yaw_rate_rad_s is not None
    yaw_rate_rad_s: float | None


def check_flag(flag: int) -> None:
    """Raise SetpointRejected unless the flag selects a mode this N3 emulator flies."""
    if flag.__class__ is int and flag in _FLOWN_FLAGS:
        return  # (the per-setpoint case)
    if not isinstance(flag, int) or not 0 <= flag <= 0xFF:
        raise SetpointRejected(f"control flag must be a byte, got {flag!r}")
    horizontal, vertical = flag & 0xC0, flag & 0x30
    if horizontal == HORIZONTAL_ANGULAR_RATE:
        raise SetpointRejected("horizontal ANGULAR_RATE unsupported")
    if horizontal == HORIZONTAL_ANGLE and vertical != VERTICAL_THRUST:
        raise SetpointRejected(f"vertical {_VERTICAL_NAMES[vertical]} unsupported, use THRUST")
    if horizontal != HORIZONTAL_ANGLE and vertical not in (VERTICAL_VELOCITY, VERTICAL_POSITION):
        raise SetpointRejected(f"vertical {_VERTICAL_NAMES[vertical]} unsupported with "
                               f"{_HORIZONTAL_NAMES[horizontal]}, use VELOCITY or POSITION")
    if horizontal != HORIZONTAL_ANGLE:
        raise SetpointRejected("frame bits 0x04 reserved")
    raise SetpointRejected("BODY frame unsupported with ANGLE, use GROUND")


@njit(cache=True)
def tilt_of(roll_rad: float, pitch_rad: float) -> float:
    """Angle between the body's thrust axis and the vertical for these Euler angles (rad)."""
    return math.acos(max(-1.0, min(1.0, math.cos(roll_rad) * math.cos(pitch_rad))))


@njit(cache=True)
def limit_tilt(roll_rad: float, pitch_rad: float, max_tilt_rad: float) -> tuple[float, float]:
    """Scale roll and pitch together so that the tilt stays within ``max_tilt_rad`` (compiled: the FC's
    setpoint path and the RL environment's rows use it)."""
    if tilt_of(roll_rad, pitch_rad) <= max_tilt_rad:
        return roll_rad, pitch_rad
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if tilt_of(mid * roll_rad, mid * pitch_rad) > max_tilt_rad:
            hi = mid
        else:
            lo = mid
    return lo * roll_rad, lo * pitch_rad


def wrap_pi(angle_rad: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi


_wrap_pi = njit(cache=True)(wrap_pi)  # (the same function, for the kernels below)

#: what `attitude_thrust_values` says of a setpoint's fields: flown, or why not (`rejection`)
ACCEPTED_FIELDS, NON_FINITE, THRUST_OUTSIDE, TILT_BEYOND_90 = 0, 1, 2, 3


def rejection(verdict: int, roll_deg: object, pitch_deg: object, thrust_percent: object, yaw: object) -> str:
    """The reason a setpoint with these fields is refused (`attitude_thrust_values`'s ``verdict``)."""
    if verdict == NON_FINITE:
        return f"non-finite setpoint {(roll_deg, pitch_deg, thrust_percent, yaw)}"
    if verdict == THRUST_OUTSIDE:
        return f"thrust {thrust_percent:.1f} % outside 0..100 %"
    return f"roll/pitch {roll_deg:.0f}/{pitch_deg:.0f} deg beyond 90"


@njit(cache=True)
def yaw_fields(flag: int, yaw: float, max_yaw_rate_deg_s: float) -> tuple[float, float]:
    """(heading (rad), yaw rate (rad/s)) of a setpoint's yaw field (deg, or deg/s with `YAW_RATE` in
    ``flag``): the heading wrapped to [-pi, pi) and the rate NaN, or the heading 0 and the rate within
    ``max_yaw_rate_deg_s``."""
    if flag & YAW_RATE:
        limit = math.radians(max_yaw_rate_deg_s)
        return 0.0, max(-limit, min(limit, math.radians(yaw)))
    return _wrap_pi(math.radians(yaw)), math.nan


@njit(cache=True)
def attitude_thrust_values(flag: int, roll_deg: float, pitch_deg: float, thrust_percent: float, yaw: float,
                           max_tilt_deg: float, max_yaw_rate_deg_s: float
                           ) -> tuple[int, float, float, float, float]:
    """An attitude-thrust setpoint's fields (degrees, percent, see `N3Setpoint`) checked and in SI
    units, the tilt and yaw rate within the profile's limits: (verdict, roll, pitch (rad), heading (rad),
    yaw rate (rad/s, NaN without `YAW_RATE`)); a verdict other than `ACCEPTED_FIELDS` says why the
    setpoint is refused (`rejection`), the rest then 0."""
    if not (math.isfinite(roll_deg) and math.isfinite(pitch_deg) and math.isfinite(thrust_percent)
            and math.isfinite(yaw)):
        return NON_FINITE, 0.0, 0.0, 0.0, 0.0
    if not 0.0 <= thrust_percent <= 100.0:
        return THRUST_OUTSIDE, 0.0, 0.0, 0.0, 0.0
    if abs(roll_deg) > 90.0 or abs(pitch_deg) > 90.0:
        return TILT_BEYOND_90, 0.0, 0.0, 0.0, 0.0
    roll, pitch = limit_tilt(math.radians(roll_deg), math.radians(pitch_deg), math.radians(max_tilt_deg))
    heading, rate = yaw_fields(flag, yaw, max_yaw_rate_deg_s)
    return ACCEPTED_FIELDS, roll, pitch, heading, rate


_new = object.__new__
_set = object.__setattr__


def to_target(sp: N3Setpoint, profile: VehicleProfile) -> AttitudeThrustTarget | MotionTarget:
    """Validate ``sp`` against the flag semantics and the profile's limits; clamp tilt and yaw rate.

    Raises SetpointRejected for an unsupported flag, a non-finite value, a thrust outside 0..100 %, or a
    roll/pitch outside +-90 deg.
    """
    check_flag(sp.flag)
    return target_from_values(sp.flag, sp.roll_deg, sp.pitch_deg, sp.thrust_percent, sp.yaw, profile)


def target_from_values(
    flag: int, roll_deg: float, pitch_deg: float, thrust_percent: float, yaw: float, profile: VehicleProfile
) -> AttitudeThrustTarget | MotionTarget:
    """`to_target` of the setpoint with these fields (degrees, percent, see `N3Setpoint`; m/s and m in
    the velocity and position modes), its ``flag`` already accepted by `check_flag`: no setpoint object
    on the per-tick path (an attitude-thrust setpoint's plain floats go to `attitude_thrust_values`
    as they are; its thrust (N) is that of the thrust field as given, its type kept)."""
    thrust_field = thrust_percent
    floats = roll_deg.__class__ is pitch_deg.__class__ is thrust_percent.__class__ is yaw.__class__ is float
    if not (floats and flag & 0xC0 == HORIZONTAL_ANGLE):
        values = (roll_deg, pitch_deg, thrust_percent, yaw)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise SetpointRejected(rejection(NON_FINITE, *values))
        if flag & 0xC0 != HORIZONTAL_ANGLE:
            return _motion_target(flag, roll_deg, pitch_deg, thrust_percent, yaw, profile)
        roll_deg, pitch_deg, thrust_percent, yaw = map(float, values)
    # (the profile's limits as they are: the kernel's entry takes an int where a float goes as `float`)
    verdict, roll, pitch, heading, rate = _attitude_thrust(
        flag, roll_deg, pitch_deg, thrust_percent, yaw, profile.max_tilt_deg, profile.max_yaw_rate_deg_s)
    if verdict != ACCEPTED_FIELDS:
        raise SetpointRejected(rejection(verdict, roll_deg, pitch_deg, thrust_percent, yaw))
    return attitude_thrust_target(flag, roll, pitch, heading, rate, thrust_field, profile)


def attitude_thrust_target(flag: int, roll_rad: float, pitch_rad: float, heading_rad: float,
                           rate_rad_s: float, thrust_percent: float, profile: VehicleProfile
                           ) -> AttitudeThrustTarget:
    """The target of an accepted setpoint's `attitude_thrust_values` (its ``flag`` and thrust field)."""
    # AttitudeThrustTarget(roll, ...) with its fields given as one new dict (a frozen dataclass's own
    # __init__ sets each through object.__setattr__, once a setpoint): a plain dict, so that the
    # interpreter's cached attribute reads of the target (the FC's batch plan, the recorder) stay
    # specialised; the instance's own dict filled key by key was not (about 250 instructions a read)
    tg = _new(AttitudeThrustTarget)
    _set(tg, "__dict__", {"roll_rad": roll_rad, "pitch_rad": pitch_rad, "yaw_rad": heading_rad,
                          "yaw_rate_rad_s": rate_rad_s if flag & YAW_RATE else None,
                          "thrust_n": profile.thrust_percent_to_force_n(thrust_percent)})
    return tg


def _attitude_thrust_first(*args: object) -> tuple[int, float, float, float, float]:
    """`attitude_thrust_values` of ``args`` (an int, then floats), on its first call: puts the kernel's
    form for those types (`entry`, called without numba's type dispatch) in its own place."""
    global _attitude_thrust
    _attitude_thrust = entry(attitude_thrust_values, 0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0)
    return _attitude_thrust(*args)


_attitude_thrust = _attitude_thrust_first


def _motion_target(flag: int, x: float, y: float, z: float, yaw: float, profile: VehicleProfile
                   ) -> MotionTarget:
    """The velocity or position-offset target of a finite setpoint: speeds clipped to the SDK's limits,
    a height to 0..`MAX_HEIGHT_M`."""
    position = flag & 0xC0 == HORIZONTAL_POSITION
    if not position:
        speed = math.hypot(x, y)
        if speed > MAX_SPEED_M_S:
            x, y = x * MAX_SPEED_M_S / speed, y * MAX_SPEED_M_S / speed
    if flag & 0x30 == VERTICAL_POSITION:
        z = max(0.0, min(MAX_HEIGHT_M, z))
    else:
        z = max(-MAX_CLIMB_M_S, min(MAX_CLIMB_M_S, z))
    heading, rate = yaw_fields(flag, float(yaw), float(profile.max_yaw_rate_deg_s))
    return MotionTarget(x, y, z, position, flag & 0x30 == VERTICAL_POSITION, bool(flag & FRAME_BODY),
                        heading, rate if flag & YAW_RATE else None)
