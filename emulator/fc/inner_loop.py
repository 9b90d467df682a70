"""The FC's inner loop, run every physics step: attitude -> body rates -> torques -> motor mixing.

Attitude error (quaternion, body frame) -> rate command (P, clipped to the profile's body-rate limit)
-> angular acceleration (P on rate error) -> torque (J alpha + w x J w) -> rotor thrusts through the
inverse of the X-quad allocation matrix, saturated so that roll/pitch come first, collective thrust
second and yaw last (the collective is shifted, yaw is scaled down), as PX4's sequential desaturation does:
at full throttle yaw may lower the collective by up to `YAW_THRUST_MARGIN` of the throttle range, so the FC
keeps some yaw authority there; it never takes from roll or pitch. Numba-compiled hot path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from emulator.profile import ROTOR_ANGLES_RAD, ROTOR_SPIN, VehicleProfile

_S = math.sqrt(0.5)
#: the share of the throttle range (idle to full) by which yaw may lower the collective thrust to keep some
#: yaw authority with the motors at full throttle (PX4's MINIMUM_YAW_MARGIN)
YAW_THRUST_MARGIN = 0.15
# an `InnerLoop`'s ``buffer``: its params (12), then its mix_inv (4 x 4, by rows), then its motor_cmd (4)
_PARAMS = 12
_MOTOR_CMD = _PARAMS + 16
LOOP_SIZE = _MOTOR_CMD + 4


@dataclass(frozen=True)
class InnerLoopGains:
    """Gains of the attitude and rate loops (per body axis x, y, z); a profile's own come from
    `emulator.fc.tuning.fc_gains`."""

    attitude_p_per_s: tuple[float, float, float]  # rate cmd (rad/s) per rad of error
    rate_p_per_s: tuple[float, float, float]  # angular accel (rad/s^2) per rad/s error
    idle_throttle: float = 0.05  # minimum throttle of each motor while armed (0..1)


def allocation_matrix(profile: VehicleProfile) -> np.ndarray:
    """(4, 4) map from rotor thrusts (N) to [total thrust (N), torque x, y, z (N m)], body FLU."""
    m = np.zeros((4, 4))
    ratio = profile.drag_torque_coeff_nm_s2 / profile.thrust_coeff_n_s2
    for i, (angle, spin) in enumerate(zip(ROTOR_ANGLES_RAD, ROTOR_SPIN, strict=True)):
        x, y = profile.arm_length_m * math.cos(angle), profile.arm_length_m * math.sin(angle)
        m[:, i] = (1.0, y, -x, -spin * ratio)
    return m


class InnerLoop:
    """Attitude and rate control plus mixing for one profile; `update` returns motor throttles (4,),
    `update_batch` those of a batch of vehicles.

    Contract for compiled callers that fuse the loop with physics (`emulator.loops.batched_steps`):
    ``control(q, w, roll, pitch, yaw, thrust_n, params, mix_inv, out)`` (`control`, numba) with this
    loop's ``params`` and ``mix_inv`` writes the throttles into ``out`` (4,), here ``motor_cmd``;
    ``control_quat`` takes the target as its quaternion (`target_quat_floats`), for a target held over
    many steps. ``buffer`` holds the three (`loop_views` splits it in a compiled caller).
    """

    def __init__(self, profile: VehicleProfile, gains: InnerLoopGains) -> None:
        if not 0.0 <= gains.idle_throttle < 1.0:
            raise ValueError(f"idle_throttle must be in [0, 1), got {gains.idle_throttle}")
        self.profile = profile
        self.gains = gains
        #: ``params``, ``mix_inv`` and ``motor_cmd`` as views of one array (`LOOP_SIZE`): a compiled caller
        #: takes the three as this one argument and splits it (`loop_views`)
        self.buffer = np.zeros(LOOP_SIZE)
        #: gains, tuned inertia (kg m^2), rate limit (rad/s), rotor thrust (N), idle throttle, packed
        self.params = self.buffer[:_PARAMS]
        self.params[:] = (
            *gains.attitude_p_per_s,
            *gains.rate_p_per_s,
            *profile.fc_tuned_inertia_kgm2,  # what the FC believes (the airframe's by default)
            profile.max_body_rate_rad_s,
            profile.max_thrust_per_rotor_n,
            gains.idle_throttle,
        )
        #: inverse allocation (4, 4): [thrust (N), torque x, y, z (N m)] -> rotor thrusts (N)
        self.mix_inv = self.buffer[_PARAMS:_MOTOR_CMD].reshape(4, 4)
        self.mix_inv[:] = np.linalg.inv(allocation_matrix(profile))
        #: the last throttles (4,) in [0, 1], written in place by every `update`
        self.motor_cmd = self.buffer[_MOTOR_CMD:]

    def update(
        self,
        quat_wxyz: np.ndarray,
        omega_rad_s: np.ndarray,
        roll_rad: float,
        pitch_rad: float,
        yaw_rad: float,
        thrust_n: float,
    ) -> np.ndarray:
        """Throttles (4,) in [0, 1] that steer the body (FLU->ENU ``quat_wxyz``, rates ``omega_rad_s``)
        toward NED Euler angles (roll, pitch, yaw heading) with total thrust ``thrust_n``."""
        control(
            quat_wxyz,
            omega_rad_s,
            roll_rad,
            pitch_rad,
            yaw_rad,
            thrust_n,
            self.params,
            self.mix_inv,
            self.motor_cmd,
        )
        return self.motor_cmd

    def update_batch(self, quat_wxyz: np.ndarray, omega_rad_s: np.ndarray, target: np.ndarray) -> np.ndarray:
        """`update` of N vehicles of this profile: attitudes (N, 4), rates (N, 3) and targets (N, 4) as
        (roll, pitch, yaw (NED, rad), thrust (N)) rows; returns the throttles (N, 4)."""
        q = np.ascontiguousarray(quat_wxyz, dtype=np.float64)
        w = np.ascontiguousarray(omega_rad_s, dtype=np.float64)
        tg = np.ascontiguousarray(target, dtype=np.float64)
        n = len(q)
        if q.shape != (n, 4) or w.shape != (n, 3) or tg.shape != (n, 4):
            raise ValueError(f"update_batch: shapes (N, 4), (N, 3), (N, 4) wanted, got {q.shape}, {w.shape}, "
                             f"{tg.shape}")
        out = np.empty((n, 4))
        _control_batch(q, w, tg, self.params, self.mix_inv, out)
        return out


@njit(cache=True, nogil=True, inline="always")
def loop_views(buf):  # pragma: no cover
    """An `InnerLoop`'s ``buffer`` split into its (``params``, ``mix_inv`` (4, 4), ``motor_cmd``) views, for a
    compiled caller (numba unboxes each array argument on every call: one array, not three)."""
    return buf[:_PARAMS], buf[_PARAMS:_MOTOR_CMD].reshape((4, 4)), buf[_MOTOR_CMD:LOOP_SIZE]


@njit(cache=True)
def _qmul(aw, ax, ay, az, bw, bx, by, bz):
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


@njit(cache=True)
def target_quat_floats(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """`target_quat_enu_flu` as four floats (w >= 0): no array for the per-step path."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    # q_enu = qT * q_ned * qD with qT = (0, s, s, 0) (NED<->ENU) and qD = (0, 1, 0, 0) (FRD<->FLU)
    aw, ax, ay, az = _qmul(0.0, _S, _S, 0.0, w, x, y, z)
    bw, bx, by, bz = _qmul(aw, ax, ay, az, 0.0, 1.0, 0.0, 0.0)
    if bw < 0:
        return -bw, -bx, -by, -bz
    return bw, bx, by, bz


@njit(cache=True)
def target_quat_enu_flu(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body(FLU)->world(ENU) quaternion of NED/FRD Euler angles (rad)."""
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = target_quat_floats(roll, pitch, yaw)
    return out


@njit(cache=True, nogil=True)
def control(q, w, roll, pitch, yaw, thrust_n, p, mix_inv, out):  # pragma: no cover
    """The inner loop's step (see the module doc): throttles into ``out`` (4,) for attitude ``q``
    (FLU->ENU, wxyz) and rates ``w`` (rad/s) toward NED (``roll``, ``pitch``, ``yaw``) (rad) and
    ``thrust_n`` (N); ``p`` and ``mix_inv`` are an `InnerLoop`'s ``params`` and ``mix_inv``.
    Scalars only (no array is allocated: it runs every physics step of every vehicle)."""
    d0, d1, d2, d3 = target_quat_floats(roll, pitch, yaw)
    control_quat(q, w, d0, d1, d2, d3, thrust_n, p, mix_inv, out)


@njit(cache=True, nogil=True, inline="always")
def control_quat(q, w, d0, d1, d2, d3, thrust_n, p, mix_inv, out):  # pragma: no cover
    """`control` toward the target attitude given as its FLU->ENU quaternion (``d0``..``d3`` = w, x, y,
    z; `target_quat_floats` of the NED Euler angles): a caller holding one target over many steps
    computes it once."""
    # error quaternion qe = conj(q) * qd (rotation from the body to the target, body frame)
    qw, qx, qy, qz = q[0], -q[1], -q[2], -q[3]
    ew = qw * d0 - qx * d1 - qy * d2 - qz * d3
    ex = qw * d1 + qx * d0 + qy * d3 - qz * d2
    ey = qw * d2 - qx * d3 + qy * d0 + qz * d1
    ez = qw * d3 + qx * d2 - qy * d1 + qz * d0
    if ew < 0:
        ex, ey, ez = -ex, -ey, -ez
    max_rate = p[9]
    rc0 = min(max_rate, max(-max_rate, 2.0 * p[0] * ex))
    rc1 = min(max_rate, max(-max_rate, 2.0 * p[1] * ey))
    rc2 = min(max_rate, max(-max_rate, 2.0 * p[2] * ez))
    ixx, iyy, izz = p[6], p[7], p[8]
    w0, w1, w2 = w[0], w[1], w[2]
    ax = p[3] * (rc0 - w0)
    ay = p[4] * (rc1 - w1)
    az = p[5] * (rc2 - w2)
    tx = ixx * ax + (izz - iyy) * w1 * w2
    ty = iyy * ay + (ixx - izz) * w2 * w0
    tz = izz * az + (iyy - ixx) * w0 * w1
    f_max = p[10]
    f_lo = p[11] * f_max
    avail = f_max - f_lo
    f0 = mix_inv[0, 1] * tx + mix_inv[0, 2] * ty
    f1 = mix_inv[1, 1] * tx + mix_inv[1, 2] * ty
    f2 = mix_inv[2, 1] * tx + mix_inv[2, 2] * ty
    f3 = mix_inv[3, 1] * tx + mix_inv[3, 2] * ty
    dmin = min(min(1e300, f0), min(f1, min(f2, f3)))
    dmax = max(max(-1e300, f0), max(f1, max(f2, f3)))
    spread = dmax - dmin
    if spread > avail:  # roll/pitch alone saturate: scale them down to fit
        k = avail / spread
        dmin *= k
        dmax *= k
        f0 *= k
        f1 *= k
        f2 *= k
        f3 *= k
    collective = 0.25 * thrust_n
    collective = min(max(collective, f_lo - dmin), f_max - dmax)  # shift the collective to fit
    f0 += collective
    f1 += collective
    f2 += collective
    f3 += collective
    y0, y1, y2, y3 = mix_inv[0, 3] * tz, mix_inv[1, 3] * tz, mix_inv[2, 3] * tz, mix_inv[3, 3] * tz
    # yaw last: the largest share of the yaw torque that fits, where yaw may lower the collective by up to
    # YAW_THRUST_MARGIN of the throttle range: a rotor may reach f_hi before the collective comes down, and
    # the four may not spread wider than the range (so that lowering it takes nothing from roll or pitch)
    f_hi = f_max + YAW_THRUST_MARGIN * avail
    k = min(min(_yaw_room(f0, y0, f_lo, f_hi), _yaw_room(f1, y1, f_lo, f_hi)),
            min(_yaw_room(f2, y2, f_lo, f_hi), _yaw_room(f3, y3, f_lo, f_hi)))
    k = min(k, _spread_room(f0, y0, f1, y1, avail), _spread_room(f0, y0, f2, y2, avail),
            _spread_room(f0, y0, f3, y3, avail), _spread_room(f1, y1, f2, y2, avail),
            _spread_room(f1, y1, f3, y3, avail), _spread_room(f2, y2, f3, y3, avail))
    k = max(min(k, 1.0), 0.0)
    f0 += k * y0
    f1 += k * y1
    f2 += k * y2
    f3 += k * y3
    drop = max(0.0, max(max(f0, f1), max(f2, f3)) - f_max)  # the collective given up to yaw
    out[0] = min(1.0, max(0.0, (f0 - drop) / f_max))
    out[1] = min(1.0, max(0.0, (f1 - drop) / f_max))
    out[2] = min(1.0, max(0.0, (f2 - drop) / f_max))
    out[3] = min(1.0, max(0.0, (f3 - drop) / f_max))


@njit(cache=True, nogil=True)
def _yaw_room(f: float, y: float, f_lo: float, f_hi: float) -> float:
    """The share of a rotor's yaw thrust ``y`` (N) that keeps its thrust ``f`` + share * y in
    [f_lo, f_hi] (1 or more: all of it)."""
    if y > 1e-12:
        return (f_hi - f) / y
    if y < -1e-12:
        return (f_lo - f) / y
    return 1.0


@njit(cache=True, nogil=True)
def _spread_room(fa: float, ya: float, fb: float, yb: float, avail: float) -> float:
    """The share of the yaw thrusts ``ya``, ``yb`` (N) that keeps two rotors' thrusts ``fa``, ``fb`` (N)
    within ``avail`` (N) of each other (1 or more: all of it)."""
    dy = ya - yb
    if dy > 1e-12:
        return (avail - (fa - fb)) / dy
    if dy < -1e-12:
        return (-avail - (fa - fb)) / dy
    return 1.0


@njit(cache=True, nogil=True)
def _control_batch(q, w, tg, p, mix_inv, out):  # pragma: no cover
    for i in range(q.shape[0]):
        control(q[i], w[i], tg[i, 0], tg[i, 1], tg[i, 2], tg[i, 3], p, mix_inv, out[i])
