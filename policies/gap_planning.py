"""Gap planning after the paper (traverse after Falanga et al.): traverse, approach, recovery, timeline.

Gap frame (REFERENCE, the paper's release): R maps gap to world, ``R = Rz(yaw) Ry(pitch) Rx(roll)``;
e0 = R [0,1,0] is the long side (width), e1 = R [1,0,0] the crossing direction (gap normal),
e2 = e0 x e1. Flying with thrust along e2 keeps body z orthogonal to the long side; the only
acceleration left is gravity's part in the e0-e1 plane, a_tr = g - (g . e2) e2 (g = (0, 0, -9.8)).

The traverse used here is the ballistic arc (thrust fixed along e2) whose apex along the long side is
at the gap centre: the vehicle passes the centre moving along the crossing direction u (= +-e1, towards
the far side from the start) at the chosen crossing speed s, the "approach speed" (1-3 m/s typical).
With tau = t - t_c (t_c: time from the traverse start to the centre):
    p(tau) = p_g + s u tau + a_tr tau^2 / 2,   v(tau) = s u + a_tr tau,   a = a_tr.
At tau = -t_c the start lies l = |g . e0| t_c^2 / 2 along the long side from the centre and about
d = s t_c before the gap plane, i.e. the paper's p0 = p_g - l e0 - d e1 with t_c = sqrt(2 l / |g . e0|)
(e0 taken pointing up). l is searched over (0, 0.5] for the lowest start speed |v(-t_c)| with
d >= d_min (0.1 m) and every traverse speed within the vehicle's limit; at tilt 0 (g . e0 = 0) there is
no drop and the traverse is straight: t_c = d_min / s. The traverse ends ``exit_m`` past the plane.

Approach: a motion primitive from the current state to the traverse start state, 2.6 s by default.
Recovery: the paper's search over 0.5-3.0 s in 0.3 s steps to the hover point (1 m above ground, 2.5 m
past the centre along the crossing direction projected horizontally), taking the first duration whose
trajectory stays in the lab, beyond the gap plane, and passes the input-feasibility test. A minimum-jerk
recovery's start jerk is free: from a steep traverse's low thrust (4.9 m/s^2 at 60 deg) it turns the body
at once (body rate = |jerk| / thrust, 8 rad/s and more after a 60 deg gap). Where the vehicle's FC
cannot turn that fast, the search may go on to minimum-snap recoveries (degree 7) whose jerk is
continuous with the traverse's (zero) and zero at the hover: the body starts turning from rest.

The mission (`plan_mission`) is searched the same way: crossing speed, then the traverse's l, then the
approach duration, each starting from what was asked for, the first candidate whose three segments keep
the vehicle's body box (`BodyClearance`: its half diagonal plus a margin) off the floor, the lab's faces
and the wall wins. Every test is a `FloatTrajectory.planes_ok` plane test or the input-feasibility test.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from policies.compiling import Kernel
from policies.frames import GRAVITY_VEC_M_S2, euler_to_matrix, quat_to_matrix
from policies.primitives import Feasibility, FloatTrajectory, Plane, Trajectory, _poly_state, solve_floats

Vec3 = tuple[float, float, float]


#: gravity along the long side below which a gap counts as level (m/s^2; 0.2 is a tilt of about 1.2 deg)
NEAR_LEVEL_G0_M_S2 = 0.2


class PlanningError(ValueError):
    """No plan satisfies the constraints; the message says which one failed."""


class PassageError(PlanningError):
    """The plan crosses at a speed whose attitude error the body cannot pass the opening with
    (`MissionRequest.checked_plan`): a steep gap is often planned faster than asked."""


def _vec3(name: str, value: object) -> Vec3:
    if value.__class__ is tuple and len(value) == 3:  # the planner's own (x, y, z) floats: as they are
        x, y, z = value
        if (x.__class__ is float and y.__class__ is float and z.__class__ is float
                and math.isfinite(x + y + z)):
            return value  # type: ignore[return-value]
    elif value.__class__ is np.ndarray and value.shape == (3,) and value.dtype == np.float64:
        x, y, z = value.tolist()
        if math.isfinite(x + y + z):
            return (x, y, z)
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class GapPose:
    """The gap as the onboard side knows it: centre (m, world ENU), rotation gap -> world, size (m).

    ``width_m`` is the long side (along e0), ``height_m`` the short side (along e2).
    """

    centre_m: Vec3
    rotation: tuple[Vec3, Vec3, Vec3]
    width_m: float
    height_m: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre_m", _vec3("centre_m", self.centre_m))
        rot = np.asarray(self.rotation, dtype=float)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise ValueError("rotation must be a finite 3x3 matrix")
        if np.abs(rot @ rot.T - np.eye(3)).max() > 1e-6 or np.linalg.det(rot) < 0:
            raise ValueError("rotation must be a proper rotation matrix (orthonormal, det +1)")
        object.__setattr__(self, "rotation", tuple(tuple(float(x) for x in row) for row in rot))
        if not (math.isfinite(self.width_m) and math.isfinite(self.height_m)
                and self.width_m > 0 and self.height_m > 0):
            raise ValueError("width_m and height_m must be positive")

    @classmethod
    def from_euler(cls, centre_m: object, roll_rad: float, pitch_rad: float = 0.0, yaw_rad: float = 0.0,
                   *, width_m: float, height_m: float) -> GapPose:
        """Gap with rotation Rz(yaw) Ry(pitch) Rx(roll) (rad); the paper's tilt is the roll."""
        rot = euler_to_matrix(roll_rad, pitch_rad, yaw_rad)
        return cls(_vec3("centre_m", centre_m), tuple(map(tuple, rot)), width_m, height_m)

    @classmethod
    def from_deg(cls, centre_m: object, roll_deg: float, pitch_deg: float = 0.0, yaw_deg: float = 0.0,
                 *, width_m: float, height_m: float) -> GapPose:
        """As ``from_euler`` with angles in degrees."""
        return cls.from_euler(centre_m, math.radians(roll_deg), math.radians(pitch_deg),
                              math.radians(yaw_deg), width_m=width_m, height_m=height_m)

    @classmethod
    def from_quaternion(cls, centre_m: object, q_wxyz: object, *, width_m: float, height_m: float) -> GapPose:
        """Gap from a mocap pose: centre (m) and quaternion (w, x, y, z) gap -> world."""
        rot = quat_to_matrix(np.asarray(q_wxyz, dtype=float))
        return cls(_vec3("centre_m", centre_m), tuple(map(tuple, rot)), width_m, height_m)

    @property
    def centre(self) -> np.ndarray:
        return np.array(self.centre_m)

    @property
    def R(self) -> np.ndarray:
        return np.array(self.rotation)

    @property
    def e0(self) -> np.ndarray:
        """Long-side direction R [0, 1, 0]."""
        return self.R[:, 1]

    @property
    def e1(self) -> np.ndarray:
        """Crossing direction (gap normal) R [1, 0, 0]."""
        return self.R[:, 0]

    @property
    def e2(self) -> np.ndarray:
        """e0 x e1 (= -R [0, 0, 1]); the traverse thrust is along +-e2."""
        (b0, a0, _), (b1, a1, _), (b2, a2, _) = self.rotation  # a = e0, b = e1
        return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])  # np.cross's operations

    @property
    def tilt_rad(self) -> float:
        """How far the opening is tilted from level (rad): the angle of e2 from the vertical."""
        return math.acos(min(1.0, abs(float(self.e2[2]))))


@dataclass(frozen=True)
class LabVolume:
    """Axis-aligned lab box (m, world ENU) the planner must stay inside; mirrors the emulator's."""

    min_m: Vec3
    max_m: Vec3

    def __post_init__(self) -> None:
        lo, hi = _vec3("min_m", self.min_m), _vec3("max_m", self.max_m)
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(f"lab min_m {lo} must be below max_m {hi} on every axis")
        object.__setattr__(self, "min_m", lo)
        object.__setattr__(self, "max_m", hi)

    def contains(self, pos_m: object, margin_m: float = 0.0) -> bool:
        """Whether the point (m) is at least ``margin_m`` inside every face."""
        p = pos_m.tolist() if isinstance(pos_m, np.ndarray) else pos_m
        return all(lo + margin_m <= x <= hi - margin_m
                   for x, lo, hi in zip(p, self.min_m, self.max_m, strict=True))  # type: ignore[call-overload]

    def half_spaces(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The six (point, inward normal) pairs bounding the box."""
        lo, hi, eye = np.array(self.min_m), np.array(self.max_m), np.eye(3)
        return [(lo, eye[i]) for i in range(3)] + [(hi, -eye[i]) for i in range(3)]


@dataclass(frozen=True)
class VehicleLimits:
    """What the planner may ask of the vehicle: mass-normalised thrust (m/s^2), body rate, speed, tilt."""

    f_min_m_s2: float = 2.0
    f_max_m_s2: float = 25.0
    max_body_rate_rad_s: float = 15.0
    max_speed_m_s: float = 6.0
    max_tilt_rad: float = math.radians(75.0)
    min_dt_s: float = 0.005  # smallest interval of the input-feasibility recursion (s)

    def __post_init__(self) -> None:
        if not (0 < self.f_min_m_s2 < self.f_max_m_s2 and self.max_body_rate_rad_s > 0
                and self.max_speed_m_s > 0 and 0 < self.max_tilt_rad < math.pi / 2 and self.min_dt_s > 0):
            raise ValueError(f"inconsistent vehicle limits: {self}")


@dataclass(frozen=True)
class BodyClearance:
    """The room the planner keeps between the vehicle's centre point and the floor (z = 0), the lab's
    faces and the wall: the body box's reach plus ``margin_m``.

    The reach is the box's half diagonal, the farthest any corner gets from the centre along any
    direction at any attitude (0.38 m for the 0.52 x 0.52 x 0.18 m box of the paper's vehicle).
    """

    body_box_m: Vec3 = (0.52, 0.52, 0.18)  # length x width x height in body FLU (m), centred
    margin_m: float = 0.05

    def __post_init__(self) -> None:
        box = _vec3("body_box_m", self.body_box_m)
        if min(box) < 0 or not (math.isfinite(self.margin_m) and self.margin_m >= 0):
            raise ValueError(f"body box {box} m and the margin {self.margin_m} m must be >= 0")
        object.__setattr__(self, "body_box_m", box)

    @property
    def reach_m(self) -> float:
        """The box's half diagonal (m)."""
        x, y, z = self.body_box_m
        return math.sqrt(x * x + y * y + z * z) / 2

    @property
    def clearance_m(self) -> float:
        """Distance (m) the centre keeps from the floor, the lab's faces and the wall."""
        return self.reach_m + self.margin_m


#: the centre point alone, no room around it (the paper release's checks, for its test case)
POINT_BODY = BodyClearance((0.0, 0.0, 0.0), 0.0)


#: the attitude error the body box passes the opening with, per degree of the gap's tilt and per m/s of
#: crossing speed (deg / (deg m/s)): the FC trailing the bank and the crossing's position error taken
#: together, fitted to the smallest clearances the shipped gap scenarios fly in lockstep (the 15-60 deg
#: ones within 1 cm; at 70 deg the 0.65 m openings leave 2-3 cm where this leaves 10-15)
ATTITUDE_ERROR_DEG_PER_DEG_M_S = 0.185


@dataclass(frozen=True)
class Passage:
    """What the body box needs of an opening to pass it (m) at the attitude it reaches there: off the
    gap's orientation by what the vehicle cannot bank beyond its tilt limit, and by the error of a
    crossing at that speed (`ATTITUDE_ERROR_DEG_PER_DEG_M_S`). The box turned by that error in the
    opening's plane spans ``long sin + height cos`` along the short side, ``long cos + height sin``
    along the long one."""

    width_m: float  # the opening's long side
    height_m: float  # its short side
    attitude_error_deg: float  # the body's expected error to the gap's orientation at the crossing
    needs_width_m: float
    needs_height_m: float

    @property
    def refusal(self) -> str | None:
        """Why the body cannot pass (the sizes, the attitude, what is short), or None when it can."""
        sides = (("long side", self.width_m, self.needs_width_m),
                 ("short side", self.height_m, self.needs_height_m))
        short = [f"{what} {have:.2f} m, needs {need:.2f} m" for what, have, need in sides if have < need]
        if not short:
            return None
        return (f"the {self.width_m:.2f} x {self.height_m:.2f} m opening is too small for the body at its "
                f"expected {self.attitude_error_deg:.1f} deg attitude error there: " + "; ".join(short))


def passage(width_m: float, height_m: float, tilt_rad: float, crossing_speed_m_s: float,
            body: BodyClearance, max_tilt_rad: float) -> Passage:
    """The `Passage` of ``body``'s box through a ``width_m`` x ``height_m`` opening tilted ``tilt_rad``,
    crossed at ``crossing_speed_m_s``, by a vehicle that banks ``max_tilt_rad`` at most (the plans'
    ``margin_m`` is not added: the fitted error holds the crossing's position error)."""
    tilt_deg = math.degrees(abs(tilt_rad))
    shortfall_deg = max(0.0, tilt_deg - math.degrees(max_tilt_rad))
    error_deg = min(90.0, shortfall_deg + ATTITUDE_ERROR_DEG_PER_DEG_M_S * tilt_deg * abs(crossing_speed_m_s))
    err = math.radians(error_deg)
    length, height = max(body.body_box_m[:2]), body.body_box_m[2]
    return Passage(width_m, height_m, error_deg,
                   length * math.cos(err) + height * math.sin(err),
                   length * math.sin(err) + height * math.cos(err))


@dataclass(frozen=True)
class Traverse:
    """The ballistic traverse: t in [0, duration_s] from its start; the centre is passed at t_c_s."""

    gap_centre_m: Vec3
    direction: Vec3  # u: unit crossing direction (+-e1)
    acc_m_s2: Vec3  # a_tr = g - (g . e2) e2
    crossing_speed_m_s: float
    t_c_s: float
    duration_s: float
    l_m: float  # distance of the start from the centre along the long side
    d_m: float  # distance of the start before the gap plane

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (m), velocity (m/s), acceleration (m/s^2) at ``t`` (s) from the traverse start."""
        p, v, a = self.state_tuples(t)
        return np.array(p), np.array(v), np.array(a)

    def state_tuples(self, t: float) -> tuple[Vec3, Vec3, Vec3]:
        """`state` as (x, y, z) tuples of plain floats (the per-step path)."""
        (cx, cy, cz), (ux, uy, uz), (ax, ay, az) = self.gap_centre_m, self.direction, self.acc_m_s2
        px, py, pz, vx, vy, vz = ballistic_state(float(t) - self.t_c_s, self.crossing_speed_m_s, cx, cy, cz,
                                                 ux, uy, uz, ax, ay, az)
        return (px, py, pz), (vx, vy, vz), (ax, ay, az)

    def packed(self) -> tuple[float, ...]:
        """`ballistic_state`'s constants after the time: t_c_s, the speed, the centre, u, a_tr."""
        return (self.t_c_s, self.crossing_speed_m_s, *self.gap_centre_m, *self.direction, *self.acc_m_s2)

    @property
    def start_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.state(0.0)

    def float_trajectory(self) -> FloatTrajectory:
        """The traverse as a `FloatTrajectory` (a quintic whose jerk is zero), for its plane tests."""
        p, v, a = self.state_tuples(0.0)
        T = self.duration_s
        axes = tuple((p[k], v[k], a[k], 0.0, 0.0, 0.0) for k in range(3))
        return FloatTrajectory(axes, T, T**3, T**4, T**5)

    @property
    def end_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.state(self.duration_s)


def ballistic_state(tau: float, s: float, cx: float, cy: float, cz: float, ux: float, uy: float, uz: float,
                    ax: float, ay: float, az: float) -> tuple[float, float, float, float, float, float]:
    """Position (m) and velocity (m/s) on the ballistic arc ``tau`` (s) after the centre ``c`` (m) is
    passed at speed ``s`` (m/s) along ``u`` under the acceleration ``a`` (m/s^2): (px, py, pz, vx, vy, vz)."""
    vx, vy, vz = s * ux, s * uy, s * uz
    return (cx + vx * tau + ax * tau * tau / 2, cy + vy * tau + ay * tau * tau / 2,
            cz + vz * tau + az * tau * tau / 2, vx + ax * tau, vy + ay * tau, vz + az * tau)


@functools.lru_cache(maxsize=8)
def _l_grid(l_max_m: float) -> np.ndarray:
    """The traverse search's grid over l (m), read-only."""
    grid = np.linspace(l_max_m / 1000, l_max_m, 1000)
    grid.flags.writeable = False
    return grid


def plan_traverse(gap: GapPose, crossing_speed_m_s: float = 2.0, limits: VehicleLimits | None = None,
                  direction_sign: float = 1.0, d_min_m: float = 0.1, exit_m: float = 0.3,
                  l_max_m: float = 0.5, l_m: float | None = None) -> Traverse:
    """The traverse through ``gap`` at ``crossing_speed_m_s`` along ``direction_sign * e1``.

    Searches l in (0, l_max_m] (see the module docstring), or takes ``l_m`` (m) as given. Raises
    PlanningError when the tilt, thrust or speed limits, or d >= d_min_m, cannot be met.
    """
    limits = limits or VehicleLimits()
    s = float(crossing_speed_m_s)
    if not (math.isfinite(s) and 0 < s <= limits.max_speed_m_s):
        raise PlanningError(f"crossing speed {s} m/s must be in (0, {limits.max_speed_m_s}]")
    g = GRAVITY_VEC_M_S2
    e2 = gap.e2
    u = gap.e1 * (1.0 if direction_sign >= 0 else -1.0)
    tilt = math.acos(min(1.0, abs(float(e2[2]))))
    if tilt > limits.max_tilt_rad:
        raise PlanningError(f"gap tilt {math.degrees(tilt):.1f} deg exceeds the tilt limit "
                            f"{math.degrees(limits.max_tilt_rad):.1f} deg")
    a_tr = g - float(g @ e2) * e2
    thrust = abs(float(g @ e2))
    if not limits.f_min_m_s2 <= thrust <= limits.f_max_m_s2:
        raise PlanningError(f"traverse thrust {thrust:.2f} m/s^2 is outside the vehicle's limits")
    g0 = abs(float(g @ gap.e0))
    a_u = float(a_tr @ u)
    if g0 < NEAR_LEVEL_G0_M_S2:  # (nearly) level: no drop worth an arc, a straight traverse of d_min
        # (a gap measured a few mrad off level would otherwise get an l = 0.5 m arc metres long)
        disc = s * s - 2 * a_u * d_min_m
        t_c_all = np.array([2 * d_min_m / (s + math.sqrt(disc)) if disc >= 0 else d_min_m / s])
    elif l_m is not None:  # the one l asked for
        if not (math.isfinite(l_m) and 0 < l_m <= l_max_m):
            raise ValueError(f"l_m must be in (0, {l_max_m}] m, got {l_m!r}")
        t_c_all = np.array([math.sqrt(2 * l_m / g0)])
    else:  # grid over l plus the value where d = d_min exactly (the usual optimum)
        l_grid = _l_grid(l_max_m)
        t_c_all = np.sqrt(2 * l_grid / g0)
        disc = s * s - 2 * a_u * d_min_m
        if disc >= 0:
            t_exact = 2 * d_min_m / (s + math.sqrt(disc))
            if g0 * t_exact**2 / 2 <= l_max_m:
                t_c_all = np.append(t_c_all, t_exact)
    d_all = s * t_c_all - a_u * t_c_all**2 / 2
    # |v(-t_c)| per candidate: norm(s u - a_tr t_c, axis=1) of the (n, 3) layout, in the same order
    vel = (s * u)[:, None] - a_tr[:, None] * t_c_all
    v_start = np.sqrt((vel * vel).sum(axis=0))
    ok = (d_all >= d_min_m - 1e-12) & (v_start <= limits.max_speed_m_s)
    if not np.any(ok):
        raise PlanningError(f"no traverse length l in (0, {l_max_m}] m keeps d >= {d_min_m} m and the "
                            f"speed <= {limits.max_speed_m_s} m/s at crossing speed {s} m/s")
    k = int(np.argmin(np.where(ok, v_start, np.inf)))
    t_c = float(t_c_all[k])
    # exit: s tau + a_u tau^2 / 2 = exit_m, smallest positive root
    if abs(a_u) < 1e-12:
        tau_end = exit_m / s
    else:
        disc = s * s + 2 * a_u * exit_m
        if disc < 0:
            raise PlanningError("the traverse turns back before clearing the gap plane")
        tau_end = (-s + math.sqrt(disc)) / a_u
    v_end = float(np.linalg.norm(s * u + a_tr * tau_end))
    if v_end > limits.max_speed_m_s:
        raise PlanningError(f"traverse exit speed {v_end:.2f} m/s exceeds {limits.max_speed_m_s} m/s")
    return Traverse(gap.centre_m, _vec3("u", u), _vec3("a", a_tr), s, t_c, t_c + tau_end,
                    g0 * t_c * t_c / 2, float(d_all[k]))


@dataclass(frozen=True)
class RecoveryResult:
    """Outcome of the recovery search: the trajectory and what the search did."""

    trajectory: Trajectory
    duration_s: float
    tried: int  # durations examined: the index of the first good one + 1
    search_time_s: float


RECOVERY_DURATIONS_S = np.round(np.arange(0.5, 3.0 + 1e-9, 0.3), 10)


def hover_point(gap: GapPose, direction: np.ndarray, distance_m: float = 2.5,
                height_m: float = 1.0) -> np.ndarray:
    """Hover target: ``distance_m`` past the gap centre along the horizontal crossing direction, at
    ``height_m`` above ground."""
    horiz = np.array([direction[0], direction[1], 0.0])
    norm = float(np.linalg.norm(horiz))
    if norm < 1e-6:
        raise PlanningError("the crossing direction is vertical: no horizontal hover direction")
    target = gap.centre + distance_m * horiz / norm
    target[2] = height_m
    return target


def search_recovery(pos_m: object, vel_m_s: object, acc_m_s2: object, hover_m: object, lab: LabVolume,
                    limits: VehicleLimits | None = None, wall: tuple[object, object] | None = None,
                    durations_s: np.ndarray = RECOVERY_DURATIONS_S, margin_m: float = 0.0,
                    wall_margin_m: float = 0.0, jerk_m_s3: object | None = None) -> RecoveryResult:
    """The paper's recovery search from the current state to hover at ``hover_m``: the durations are
    tried in order and the first that passes wins.

    A duration passes when its trajectory stays ``margin_m`` inside ``lab``, ``wall_margin_m`` on the
    normal's side of ``wall`` = (point, normal) if given, and is FEASIBLE under ``limits``. With the
    current jerk ``jerk_m_s3`` (m/s^3) given, where no minimum-jerk recovery passes, the minimum-snap
    ones from it to the hover at rest (jerk zero) are tried in the same durations (``tried`` counts
    both). Raises PlanningError if none.
    """
    limits = limits or VehicleLimits()
    start = time.perf_counter()
    hover = _vec3("hover_m", hover_m)
    if not lab.contains(hover, margin_m):
        raise PlanningError(f"hover point {np.asarray(hover).round(3).tolist()} is outside the lab")
    p0, v0, a0 = _vec3("pos_m", pos_m), _vec3("vel_m_s", vel_m_s), _vec3("acc_m_s2", acc_m_s2)
    durations = np.asarray(durations_s, dtype=float)
    T_all = durations.tolist()
    if durations.ndim != 1 or not all(math.isfinite(T) and T > 0 for T in T_all):
        raise ValueError(f"durations_s must be one row of finite and positive durations (s), got {T_all}")
    planes = list(_lab_planes(lab, float(margin_m) - 1e-9))
    if wall is not None:
        planes.append(Plane(_vec3("wall point", wall[0]), _vec3("wall normal", wall[1]),
                            float(wall_margin_m) - 1e-9))
    zero = (0.0, 0.0, 0.0)
    j0 = None if jerk_m_s3 is None else _vec3("jerk_m_s3", jerk_m_s3)

    def candidates() -> Iterator[FloatTrajectory]:
        yield from solve_floats(p0, v0, a0, hover, zero, zero, T_all)
        if j0 is not None:  # (solved only where no minimum-jerk one passed)
            yield from solve_floats(p0, v0, a0, hover, zero, zero, T_all, j0, zero)

    for i, cand in enumerate(candidates()):
        if cand.planes_ok(planes) and cand.input_feasible(
                limits.f_min_m_s2, limits.f_max_m_s2, limits.max_body_rate_rad_s,
                limits.min_dt_s) is Feasibility.FEASIBLE:
            return RecoveryResult(cand.trajectory(), cand.T, i + 1, time.perf_counter() - start)
    raise PlanningError(f"no recovery duration in {np.asarray(durations_s).round(2).tolist()} s stays in "
                        "the lab and within the thrust and body-rate limits")


@functools.lru_cache(maxsize=32)
def _lab_planes(lab: LabVolume, threshold_m: float) -> tuple[Plane, ...]:
    """The lab's six walls (``lab.half_spaces()``) as planes passed at ``threshold_m``."""
    return tuple(Plane(tuple(p.tolist()), tuple(n.tolist()), threshold_m) for p, n in lab.half_spaces())


class Segment(StrEnum):
    """Mission phase names."""

    APPROACH = "approach"
    TRAVERSE = "traverse"
    RECOVERY = "recovery"
    HOVER = "hover"


# the members as module constants for the per-step lookups (Python 3.11 reads a member through its class
# with a descriptor call, about 0.4 us)
_APPROACH, _TRAVERSE, _RECOVERY, _HOVER = Segment.APPROACH, Segment.TRAVERSE, Segment.RECOVERY, Segment.HOVER


@dataclass(frozen=True)
class Reference:
    """The reference at one time: position (m), velocity (m/s), acceleration (m/s^2), yaw (rad)."""

    pos_m: np.ndarray
    vel_m_s: np.ndarray
    acc_m_s2: np.ndarray
    yaw_rad: float
    segment: Segment


@dataclass(frozen=True)
class MissionPlan:
    """Approach -> traverse -> recovery -> hover, on one time axis (s, from the approach start)."""

    gap: GapPose
    approach: Trajectory
    traverse: Traverse
    recovery: RecoveryResult
    hover_m: Vec3
    yaw_rad: float
    approach_feasibility: Feasibility
    candidates_tried: int = 1  # approaches the search examined: the index of the one flown + 1
    search_time_s: float = 0.0  # wall time of the whole search (s)
    t_traverse_start_s: float = field(init=False)
    t_recovery_start_s: float = field(init=False)
    t_hover_start_s: float = field(init=False)

    def __post_init__(self) -> None:
        t1 = float(self.approach.T)
        t2 = t1 + self.traverse.duration_s
        object.__setattr__(self, "t_traverse_start_s", t1)
        object.__setattr__(self, "t_recovery_start_s", t2)
        object.__setattr__(self, "t_hover_start_s", t2 + self.recovery.duration_s)

    @property
    def t_gap_s(self) -> float:
        """When the reference passes the gap centre (s)."""
        return self.t_traverse_start_s + self.traverse.t_c_s

    def segment_at(self, t: float) -> Segment:
        i = segment_index(t, self.t_traverse_start_s, self.t_recovery_start_s, self.t_hover_start_s)
        return _SEGMENTS[i]

    def segment_end_s(self, t: float) -> float:
        """When the segment at mission time ``t`` (s) ends (s; inf for the hover): until then `segment_at`
        gives the same segment, so a caller stepping through time asks it again only from there."""
        i = segment_index(t, self.t_traverse_start_s, self.t_recovery_start_s, self.t_hover_start_s)
        return (self.t_traverse_start_s, self.t_recovery_start_s, self.t_hover_start_s, math.inf)[i]

    def reference(self, t: float) -> Reference:
        """The reference at mission time ``t`` (s); before 0 the start state, after the end hover."""
        p, v, a, yaw = self.reference_tuples(t)
        ref = object.__new__(Reference)  # a frozen dataclass, filled without its per-field __setattr__
        ref.__dict__.update(pos_m=np.array(p), vel_m_s=np.array(v), acc_m_s2=np.array(a),
                            yaw_rad=yaw, segment=self.segment_at(t))
        return ref

    def reference_tuples(self, t: float) -> tuple[Vec3, Vec3, Vec3, float]:
        """`reference` in plain floats: position (m), velocity (m/s), acceleration (m/s^2) as (x, y, z)
        tuples and the yaw (rad); the same numbers, for the per-step paths (`plan_reference`)."""
        r = self._reference(self.packed, float(t))
        return (r[0], r[1], r[2]), (r[3], r[4], r[5]), (r[6], r[7], r[8]), r[9]

    def reference_positions(self, times: Sequence[float]) -> np.ndarray:
        """`reference_tuples`' positions (m) at each of the mission times ``times`` (s, floats): (N, 3), in
        one compiled call (`plan_positions`; a run's checks ask for a reference a sample)."""
        out = np.empty((len(times), 3))
        PLAN_POSITIONS.get()(self.packed, np.asarray(times, dtype=np.float64), out)
        return out

    def segment_indices(self, times: Sequence[float]) -> np.ndarray:
        """`segment_index` at each of the mission times ``times`` (s): (N,), the index of the segment
        `segment_at` gives in `Segment`'s order (0 the approach .. 3 the hover), in one compiled call."""
        out = np.empty(len(times), dtype=np.int64)
        SEGMENT_INDICES.get()(np.asarray(times, dtype=np.float64), self.t_traverse_start_s,
                              self.t_recovery_start_s, self.t_hover_start_s, out)
        return out

    @functools.cached_property
    def _reference(self) -> Any:
        """`plan_reference` compiled, looked up once a plan (a run's checks ask for a reference a sample)."""
        return PLAN_REFERENCE.get()

    @functools.cached_property
    def packed(self) -> np.ndarray:
        """The plan as `plan_reference` reads it (made once; read-only): the segments' start times (s),
        the yaw (rad), the approach's and the recovery's polynomials (`PLAN_POLY_FLOATS` each), the
        traverse (`Traverse.packed`), the hover point (m)."""
        k = np.zeros(PLAN_FLOATS)
        k[:4] = self.t_traverse_start_s, self.t_recovery_start_s, self.t_hover_start_s, self.yaw_rad
        k[_PLAN_APPROACH:_PLAN_RECOVERY] = poly_packed(self.approach)
        k[_PLAN_RECOVERY:_PLAN_TRAVERSE] = poly_packed(self.recovery.trajectory)
        k[_PLAN_TRAVERSE:_PLAN_HOVER] = self.traverse.packed()
        k[_PLAN_HOVER:] = self.hover_m
        k.flags.writeable = False
        return k


#: `MissionPlan.packed`: where each part starts; a polynomial is its coefficient count (6: quintic, 8:
#: degree 7), then per axis x, y, z the 8 coefficients in `_poly_state`'s order (p0, v0, a0, alpha, beta,
#: gamma, delta, epsilon; zeros past the count)
PLAN_POLY_FLOATS = 25
_PLAN_APPROACH = 4
_PLAN_RECOVERY = _PLAN_APPROACH + PLAN_POLY_FLOATS
_PLAN_TRAVERSE = _PLAN_RECOVERY + PLAN_POLY_FLOATS
_PLAN_HOVER = _PLAN_TRAVERSE + 11
PLAN_FLOATS = _PLAN_HOVER + 3
_SEGMENTS = (_APPROACH, _TRAVERSE, _RECOVERY, _HOVER)


def poly_packed(traj: Trajectory) -> np.ndarray:
    """A single trajectory (batch shape ()) as `_poly_axes` reads it (`PLAN_POLY_FLOATS`)."""
    k = np.zeros(PLAN_POLY_FLOATS)
    coeffs = traj._coefficients()
    k[0] = len(coeffs)
    for j, c in enumerate(coeffs):
        k[1 + j:25:8] = c
    return k


def segment_index(t: float, t_traverse_s: float, t_recovery_s: float, t_hover_s: float) -> int:
    """Which segment mission time ``t`` (s) is in, given their start times (s): 0 the approach (also
    before 0), 1 the traverse, 2 the recovery, 3 the hover."""
    if t < t_traverse_s:
        return 0
    if t < t_recovery_s:
        return 1
    if t < t_hover_s:
        return 2
    return 3


def _poly_axes(k: np.ndarray, at: int, t: float) -> tuple[float, ...]:
    """Position (m), velocity (m/s), acceleration (m/s^2) of the polynomial packed at ``k[at]`` at ``t`` (s):
    (px, py, pz, vx, vy, vz, ax, ay, az)."""
    c = k[at + 1:at + 25]
    if k[at] == 6.0:
        x = _poly_state(t, c[0], c[1], c[2], c[3], c[4], c[5])
        y = _poly_state(t, c[8], c[9], c[10], c[11], c[12], c[13])
        z = _poly_state(t, c[16], c[17], c[18], c[19], c[20], c[21])
    else:
        x = _poly_state(t, c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7])
        y = _poly_state(t, c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15])
        z = _poly_state(t, c[16], c[17], c[18], c[19], c[20], c[21], c[22], c[23])
    return x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]


def plan_reference(k: np.ndarray, t: float) -> tuple[float, ...]:
    """The reference of the plan packed in ``k`` (`MissionPlan.packed`) at mission time ``t`` (s):
    position (m), velocity (m/s), acceleration (m/s^2) as x, y, z each, then the yaw (rad). Before 0 the
    start state, after the end the hover. Compiled by numba (`policies.compiling`), which is how it runs."""
    seg = segment_index(t, k[0], k[1], k[2])
    if seg == 0:
        px, py, pz, vx, vy, vz, ax, ay, az = _poly_axes(k, _PLAN_APPROACH, 0.0 if t < 0.0 else t)
    elif seg == 1:
        tr = k[_PLAN_TRAVERSE:_PLAN_HOVER]
        px, py, pz, vx, vy, vz = ballistic_state(t - k[0] - tr[0], tr[1], tr[2], tr[3], tr[4], tr[5], tr[6],
                                                 tr[7], tr[8], tr[9], tr[10])
        ax, ay, az = tr[8], tr[9], tr[10]
    elif seg == 2:
        px, py, pz, vx, vy, vz, ax, ay, az = _poly_axes(k, _PLAN_RECOVERY, t - k[1])
    else:
        px, py, pz = k[_PLAN_HOVER], k[_PLAN_HOVER + 1], k[_PLAN_HOVER + 2]
        vx = vy = vz = ax = ay = az = 0.0
    return px, py, pz, vx, vy, vz, ax, ay, az, k[3]


def plan_positions(k: np.ndarray, times: np.ndarray, out: np.ndarray) -> None:
    """`plan_reference`'s position (m) at each of the mission times ``times`` (s) into ``out`` (N, 3).
    Compiled (`PLAN_POSITIONS`)."""
    for i in range(len(times)):
        r = plan_reference(k, times[i])
        out[i, 0], out[i, 1], out[i, 2] = r[0], r[1], r[2]


def segment_indices(times: np.ndarray, t_traverse_s: float, t_recovery_s: float, t_hover_s: float,
                    out: np.ndarray) -> None:
    """`segment_index` at each of the mission times ``times`` (s) into ``out`` (N,). Compiled
    (`SEGMENT_INDICES`)."""
    for i in range(len(times)):
        out[i] = segment_index(times[i], t_traverse_s, t_recovery_s, t_hover_s)


_POLY_STATE = Kernel(_poly_state)
#: `_poly_axes` compiled (the take-off's command reads its polynomial with it too)
POLY_AXES = Kernel(_poly_axes, _poly_state=_POLY_STATE)
#: `segment_index` compiled
SEGMENT_INDEX = Kernel(segment_index)
#: `plan_reference` compiled
PLAN_REFERENCE = Kernel(plan_reference, segment_index=SEGMENT_INDEX, _poly_axes=POLY_AXES,
                        ballistic_state=Kernel(ballistic_state))
#: `plan_positions` compiled (a run's position errors: a reference a sample)
PLAN_POSITIONS = Kernel(plan_positions, plan_reference=PLAN_REFERENCE)
#: `segment_indices` compiled
SEGMENT_INDICES = Kernel(segment_indices, segment_index=SEGMENT_INDEX)


#: approach durations (s) the search tries after the one asked for, nearest to it first (the recovery's step)
APPROACH_DURATIONS_S = np.round(np.arange(1.1, 4.1 + 1e-9, 0.3), 10)
#: traverse lengths l (m) the search tries after the one of the lowest start speed
TRAVERSE_LENGTHS_M = (0.1, 0.2, 0.3, 0.4, 0.5)
#: crossing speeds (m/s) the search may choose, nearest to the one asked for first
CROSSING_SPEED_RANGE_M_S = (1.0, 5.0)
CROSSING_SPEED_STEP_M_S = 0.5


def _nearest_first(first: float, grid: object) -> list[float]:
    """``first``, then the values of ``grid`` nearest to it first (the lower of a tie first)."""
    rest = sorted((float(x) for x in grid if abs(float(x) - first) > 1e-9), key=lambda x: (abs(x - first), x))
    return [first, *rest]


def plan_mission(start_pos_m: object, gap: GapPose, lab: LabVolume, *, start_vel_m_s: object = (0, 0, 0),
                 start_acc_m_s2: object = (0, 0, 0), approach_duration_s: float = 2.6,
                 crossing_speed_m_s: float = 2.0, limits: VehicleLimits | None = None,
                 d_min_m: float = 0.1, exit_m: float = 0.3, hover_distance_m: float = 2.5,
                 hover_height_m: float = 1.0, body: BodyClearance | None = None,
                 crossing_speed_range_m_s: tuple[float, float] = CROSSING_SPEED_RANGE_M_S,
                 recovery_limits: VehicleLimits | None = None, smooth_recovery: bool = False) -> MissionPlan:
    """Plan the whole crossing from the current state (the paper's pipeline), searched for a plan the
    body can fly.

    The crossing direction is the gap normal pointing away from the start. Candidates are tried in
    order, the first that passes wins: the crossing speed asked for, then the others of
    ``crossing_speed_range_m_s`` (0.5 m/s apart, nearest first); per speed the traverse of the lowest
    start speed, then l = 0.1 ... 0.5 m; per traverse the approach duration asked for, then
    `APPROACH_DURATIONS_S` nearest first. A candidate passes when every segment keeps ``body``'s
    clearance from the floor (z = 0) and the lab's faces, the approach stays before the wall (no nearer
    it than the traverse start), the traverse ends, and the recovery stays, the clearance past the wall,
    the approach is not INFEASIBLE (INDETERMINABLE is accepted and recorded) and a recovery duration
    passes `search_recovery`. With ``smooth_recovery`` the recovery search goes on to the jerk-continuous
    recoveries (`search_recovery`'s minimum-snap ones from the traverse's jerk, zero) where no
    minimum-jerk one passes; with ``recovery_limits`` (tighter than ``limits``) it searches within those
    first (minimum-jerk, then jerk-continuous), then the minimum-jerk ones within ``limits``. Raises
    PlanningError, saying why the requested candidate failed, if none.
    """
    started = time.perf_counter()
    limits = limits or VehicleLimits()
    traverse_jerk = (0.0, 0.0, 0.0) if smooth_recovery else None  # the ballistic traverse's
    # (limits, start jerk) of each recovery search, in order
    recovery_tiers = [(limits, traverse_jerk)] if recovery_limits is None else [
        (recovery_limits, traverse_jerk), (limits, None)]
    body = body or BodyClearance()
    p_start = _vec3("start_pos_m", start_pos_m)
    if not (math.isfinite(approach_duration_s) and approach_duration_s > 0):
        raise ValueError("approach_duration_s must be positive")
    side = sum((p - c) * e for p, c, e in zip(p_start, gap.centre_m, gap.e1.tolist(), strict=True))
    sign = -1.0 if side > 0 else 1.0
    vel, acc = _vec3("start_vel_m_s", start_vel_m_s), _vec3("start_acc_m_s2", start_acc_m_s2)
    clear = body.clearance_m
    # the traverse ends the clearance past the wall; the recovery keeps the body's reach from it (the
    # margin between the two lets the plane test decide at once)
    exit_past = max(exit_m, clear)
    (lo_x, lo_y, lo_z), hi = lab.min_m, lab.max_m
    room = LabVolume((lo_x, lo_y, max(lo_z, 0.0)), hi)  # the floor is z = 0 whatever the lab says
    box_planes = list(_lab_planes(room, clear - 1e-9))
    u = _vec3("u", gap.e1 * sign)
    back = (-u[0], -u[1], -u[2])
    hover = hover_point(gap, np.array(u), hover_distance_m, hover_height_m)
    wall = (gap.centre_m, u)
    lo_s, hi_s = crossing_speed_range_m_s
    speeds = _nearest_first(float(crossing_speed_m_s),
                            np.arange(lo_s, hi_s + 1e-9, CROSSING_SPEED_STEP_M_S))
    level = abs(float(GRAVITY_VEC_M_S2 @ gap.e0)) < NEAR_LEVEL_G0_M_S2
    lengths = (None,) if level else (None, *TRAVERSE_LENGTHS_M)
    durations = _nearest_first(float(approach_duration_s), APPROACH_DURATIONS_S)
    why: list[str] = []  # why the first candidate failed
    tried = 0
    for speed in speeds:
        for l_m in lengths:
            try:
                trav = plan_traverse(gap, speed, limits, sign, d_min_m, exit_past, l_m=l_m)
            except PlanningError as exc:
                why.append(str(exc))
                continue
            if not trav.float_trajectory().planes_ok(box_planes):
                why.append(f"the traverse comes within {clear:.2f} m of the floor or the lab's faces")
                continue
            pe, ve, ae = trav.state_tuples(trav.duration_s)
            recovery = None
            for tier_limits, jerk in recovery_tiers:
                try:
                    recovery = search_recovery(pe, ve, ae, hover, room, tier_limits, wall=wall,
                                               margin_m=clear, wall_margin_m=body.reach_m, jerk_m_s3=jerk)
                    break
                except PlanningError as exc:
                    error = str(exc)
            if recovery is None:
                why.append(error)
                continue
            p0, v0, a0 = trav.state_tuples(0.0)
            approach_planes = [*box_planes, Plane(gap.centre_m, back, trav.d_m - 1e-6)]
            for T in durations:
                tried += 1
                (cand,) = solve_floats(p_start, vel, acc, p0, v0, a0, [T])
                if not cand.planes_ok(approach_planes):  # (the cheaper test first)
                    if not why:  # (only the first reason is told)
                        why.append(_approach_failure(cand, T, box_planes, clear))
                    continue
                feas = cand.input_feasible(limits.f_min_m_s2, limits.f_max_m_s2, limits.max_body_rate_rad_s,
                                           limits.min_dt_s)
                if feas is Feasibility.INFEASIBLE:
                    why.append(f"the approach in {T:g} s exceeds the thrust or body-rate limits")
                else:
                    yaw = math.atan2(u[1], u[0])
                    return MissionPlan(gap, cand.trajectory(), trav, recovery, _vec3("hover", hover), yaw,
                                       feas, tried, time.perf_counter() - started)
    raise PlanningError(
        f"no plan keeps the body's {clear:.2f} m clearance: tried {len(speeds)} crossing speeds "
        f"{lo_s:g}-{hi_s:g} m/s, traverse lengths l in (0, 0.5] m and approach durations "
        f"{durations[0]:g} s then {min(durations):g}-{max(durations):g} s ({tried} approaches); at "
        f"{crossing_speed_m_s:g} m/s in {approach_duration_s:g} s: {why[0] if why else 'no candidate'}")


def _approach_failure(approach: FloatTrajectory, T: float, box_planes: list[Plane], clear: float) -> str:
    """Which plane test an approach of ``T`` s failed, in words."""
    if not approach.planes_ok([box_planes[2]]):  # the floor: `_lab_planes`' lower z face
        return f"the approach in {T:g} s comes within {clear:.2f} m of the floor"
    if not approach.planes_ok(box_planes):
        return f"the approach in {T:g} s comes within {clear:.2f} m of the lab's faces"
    return f"the approach in {T:g} s gets nearer the wall than the traverse start"


@dataclass(frozen=True)
class MissionRequest:
    """What the onboard program plans its mission from (SI units, world ENU): the measured start state,
    the gap, the lab and its settings. Its `to_dict` is what the program's ``plan`` event records, so
    that the harness derives the very plan the program flew (`plan`) to check the flight against it."""

    start_pos_m: Vec3
    start_vel_m_s: Vec3
    gap: GapPose
    lab: LabVolume
    approach_duration_s: float
    crossing_speed_m_s: float
    d_min_m: float
    body: BodyClearance = field(default_factory=BodyClearance)
    #: the body rate the vehicle's FC turns it at, at most (rad/s; `VehicleLimits`' by default)
    max_body_rate_rad_s: float = VehicleLimits.max_body_rate_rad_s

    def plan(self) -> MissionPlan:
        """The mission `plan_mission` makes from this request (PlanningError, ValueError as it).

        For a vehicle whose body rate w is below `VehicleLimits`' (the planner's limits for any vehicle),
        the first of: the plan within w; the plan within w whose recovery may be jerk-continuous (after
        a steep traverse, where every minimum-jerk one starts turning faster than w); the plan within 2 w
        (the FC trailing briefly) whose recovery is within w where one is (minimum-jerk, then
        jerk-continuous), else a minimum-jerk one within 2 w. Then (and for any other vehicle only) the
        plan within `VehicleLimits`'.
        """
        return self.ranked_plan()[1]

    def ranked_plan(self) -> tuple[int, MissionPlan]:
        """`plan` with the index of the stage (in `plan`'s order, 0 first) that found it."""
        last = len(self._stages()) - 1
        for i in range(last):
            with contextlib.suppress(PlanningError):
                return i, self.stage_plan(i)
        return last, self.stage_plan(last)

    def passage(self, speed_m_s: float | None = None) -> Passage:
        """What the body needs of the opening at ``speed_m_s`` (m/s; the crossing speed asked for by
        default), `passage`."""
        speed = self.crossing_speed_m_s if speed_m_s is None else speed_m_s
        return passage(self.gap.width_m, self.gap.height_m, self.gap.tilt_rad, speed, self.body,
                       VehicleLimits.max_tilt_rad)

    def checked_plan(self) -> MissionPlan:
        """`plan`, refused (PassageError) where it crosses at a speed the body cannot pass the opening at:
        the planner searches on to other speeds where none is found at the one asked for, and a steep
        gap's plans are often faster (70 deg at 2 m/s from the paper's start: 3 m/s), where the attitude
        error is larger."""
        return self.checked(self.plan())

    def checked(self, plan: MissionPlan) -> MissionPlan:
        """``plan`` (this request's `plan`), refused as `checked_plan` refuses it."""
        speed = plan.traverse.crossing_speed_m_s
        why = self.passage(speed).refusal if speed != self.crossing_speed_m_s else None
        if why is not None:
            raise PassageError(f"the plan crosses at {speed:g} m/s (asked for: "
                               f"{self.crossing_speed_m_s:g} m/s), where {why}")
        return plan

    def stage_plan(self, stage: int, **options: Any) -> MissionPlan:
        """The plan of `plan`'s stage ``stage`` (0 first) alone, with ``options`` of `plan_mission` added
        (PlanningError, ValueError as it); none through an opening the body cannot pass (`passage`)."""
        refusal = self.passage().refusal
        if refusal is not None:
            raise PlanningError(refusal)
        return plan_mission(self.start_pos_m, self.gap, self.lab, start_vel_m_s=self.start_vel_m_s,
                            approach_duration_s=self.approach_duration_s,
                            crossing_speed_m_s=self.crossing_speed_m_s, d_min_m=self.d_min_m, body=self.body,
                            **self._stages()[stage], **options)

    @property
    def own_rate_stages(self) -> int:
        """How many of `plan`'s stages keep the whole plan within the vehicle's own body rate (2 for a
        vehicle slower than `VehicleLimits`', else none: its only stage is the planner's own limit)."""
        return 2 if self.max_body_rate_rad_s < VehicleLimits.max_body_rate_rad_s else 0

    def _stages(self) -> list[dict[str, Any]]:
        """`plan_mission`'s limits and options of each of `plan`'s stages, in order."""
        w = self.max_body_rate_rad_s
        stages: list[dict[str, Any]] = []
        if w < VehicleLimits.max_body_rate_rad_s:
            own = VehicleLimits(max_body_rate_rad_s=w)
            stages = [{"limits": own}, {"limits": own, "smooth_recovery": True}]
            if 2 * w < VehicleLimits.max_body_rate_rad_s:
                stages.append({"limits": VehicleLimits(max_body_rate_rad_s=2 * w), "recovery_limits": own,
                               "smooth_recovery": True})
        return [*stages, {}]

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready numbers (full precision: the same plan comes back from `from_dict`)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> MissionRequest:
        """The request of a `to_dict` (e.g. read back from JSON); ValueError or KeyError if malformed."""
        return cls(_vec3("start_pos_m", data["start_pos_m"]), _vec3("start_vel_m_s", data["start_vel_m_s"]),
                   GapPose(**data["gap"]), LabVolume(**data["lab"]), float(data["approach_duration_s"]),
                   float(data["crossing_speed_m_s"]), float(data["d_min_m"]),
                   BodyClearance(**data["body"]) if "body" in data else BodyClearance(),
                   float(data.get("max_body_rate_rad_s", VehicleLimits.max_body_rate_rad_s)))


#: the step (m) between the start heights `start_height` tries above the take-off height
START_HEIGHT_STEP_M = 0.1


def start_height(request: MissionRequest) -> float:
    """The height (m, world z) to start ``request``'s mission from, at or above its start (the take-off
    height): a slow vehicle chooses it for its approach.

    A vehicle as fast as the planner's limits, or one whose plan from the start stays within its own
    body rate (the first `MissionRequest.own_rate_stages` of `MissionRequest.plan`'s stages), starts where
    it is. Otherwise, where the approach that keeps the body's clearance from the floor from a low start
    is a short one turning the body fast, the start is the lowest height (`START_HEIGHT_STEP_M` apart, up
    to the lab's ceiling less the body's clearance) from which the stage that planned it flies the
    search's first approach (the crossing speed and the approach duration asked for), half a step
    above it; where none does, where it is. Raises PlanningError (as `MissionRequest.plan`) when there is
    no plan from the start.
    """
    return _start_height(request)[0]


def start_plan(request: MissionRequest) -> tuple[float, MissionPlan]:
    """`start_height` and `MissionRequest.plan` from there (``request`` started at that height): where
    that is the request's own start, the plan `start_height` made on its way, not planned twice."""
    z, plan = _start_height(request)
    if plan is None:
        x, y, _ = request.start_pos_m
        plan = dataclasses.replace(request, start_pos_m=(x, y, z)).plan()
    return z, plan


def _start_height(request: MissionRequest) -> tuple[float, MissionPlan | None]:
    """`start_height`, with `MissionRequest.plan` where that is the request's own start (else None)."""
    stage, plan = request.ranked_plan()
    z0 = request.start_pos_m[2]
    if request.own_rate_stages == 0 or stage < request.own_rate_stages or (
            plan.candidates_tried == 1 and plan.traverse.crossing_speed_m_s == request.crossing_speed_m_s):
        return z0, plan
    speed = request.crossing_speed_m_s
    top = request.lab.max_m[2] - request.body.clearance_m
    x, y, _ = request.start_pos_m
    for k in range(1, int((top - z0) / START_HEIGHT_STEP_M + 1e-9) + 1):
        z = z0 + k * START_HEIGHT_STEP_M
        try:
            higher = dataclasses.replace(request, start_pos_m=(x, y, z)).stage_plan(
                stage, crossing_speed_range_m_s=(speed, speed))
        except PlanningError:
            continue
        if higher.candidates_tried == 1:  # (half a step above it: room for the take-off's settling)
            return min(z + START_HEIGHT_STEP_M / 2, top), None
    return z0, plan
