"""Numba kernels of the native quadrotor physics: one vehicle step, and a parallel batch of them.

Each vehicle is a row of STATE_SIZE floats (layout in `emulator.physics.state`) plus an auxiliary row
of AUX_SIZE floats: the external world force (N), the last step's world acceleration (m/s^2) and the
external body torque (N m).
The profile is packed once into a flat parameter vector (`pack_params`) so that the loops touch no
Python objects. `step_vehicle` is the one kernel; `step_batch` runs it over rows in parallel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from emulator.profile import GRAVITY_M_S2, ROTOR_ANGLES_RAD, ROTOR_SPIN, VehicleProfile

# Auxiliary row layout.
AUX_FORCE = slice(0, 3)  # external force, world ENU (N)
AUX_ACCEL = slice(3, 6)  # last step's world acceleration (m/s^2)
AUX_TORQUE = slice(6, 9)  # external torque, body FLU (N m)
AUX_SIZE = 9

# Ground-contact constants (not profile fields): Coulomb friction and rotational damping on contact.
GROUND_FRICTION = 0.5
GROUND_ANGULAR_DAMPING_S = 0.05  # time constant of body-rate decay while touching the ground (s)

# Parameter vector layout.
P_MASS, P_IXX, P_IYY, P_IZZ = 0, 1, 2, 3
P_KF, P_KM, P_WMAX, P_MOTOR_ALPHA = 4, 5, 6, 7
P_DRAG = 8  # 3 entries: body linear drag (N s/m)
P_ANG_DRAG = 11  # 3 entries: body angular drag (N m s/rad)
P_GRAVITY, P_HALF_HEIGHT, P_FRICTION, P_GROUND_DAMP, P_DT = 14, 15, 16, 17, 18
P_ROTOR_X = 19  # 4 entries: rotor positions, body FLU (m)
P_ROTOR_Y = 23
P_SPIN = 27  # 4 entries: +1 counter-clockwise seen from above
N_PARAMS = 31


def pack_params(profile: VehicleProfile, dt_s: float) -> np.ndarray:
    """The profile and step size as the flat float64 vector the kernels read."""
    if not (isinstance(dt_s, int | float) and math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be a positive finite number of seconds, got {dt_s!r}")
    p = np.zeros(N_PARAMS)
    p[P_MASS] = profile.mass_kg
    p[P_IXX], p[P_IYY], p[P_IZZ] = profile.inertia_kgm2
    p[P_KF] = profile.thrust_coeff_n_s2
    p[P_KM] = profile.drag_torque_coeff_nm_s2
    p[P_WMAX] = profile.max_rotor_speed_rad_s
    p[P_MOTOR_ALPHA] = 1.0 - math.exp(-dt_s / profile.motor_time_constant_s)  # exact first-order step
    p[P_DRAG : P_DRAG + 3] = profile.linear_drag_n_s_m
    p[P_ANG_DRAG : P_ANG_DRAG + 3] = profile.angular_drag_nm_s_rad
    p[P_GRAVITY] = GRAVITY_M_S2
    p[P_HALF_HEIGHT] = 0.5 * profile.body_box_m[2]
    p[P_FRICTION] = GROUND_FRICTION
    p[P_GROUND_DAMP] = math.exp(-dt_s / GROUND_ANGULAR_DAMPING_S)
    p[P_DT] = dt_s
    for i, angle in enumerate(ROTOR_ANGLES_RAD):
        p[P_ROTOR_X + i] = profile.arm_length_m * math.cos(angle)
        p[P_ROTOR_Y + i] = profile.arm_length_m * math.sin(angle)
        p[P_SPIN + i] = ROTOR_SPIN[i]
    return p


@njit(cache=True, nogil=True, inline="always")
def _rotor_speed_target(u: float, w_max: float) -> float:
    """Rotor speed (rad/s) a throttle ``u`` settles at: clipped to [0, 1], a non-finite one as 0."""
    if not (u > 0.0):  # also catches NaN
        return 0.0
    return math.sqrt(1.0 if u > 1.0 else u) * w_max


@njit(cache=True, nogil=True, inline="always")
def step_vehicle(x: np.ndarray, aux: np.ndarray, p: np.ndarray, cmd: np.ndarray, n_steps: int) -> None:
    """Advance one vehicle row ``x`` (STATE_SIZE,) by ``n_steps`` under throttle ``cmd`` (4,), in place.

    Throttles are clipped to [0, 1]; a non-finite throttle counts as 0 (motor off).
    """
    dt = p[P_DT]
    m = p[P_MASS]
    ixx, iyy, izz = p[P_IXX], p[P_IYY], p[P_IZZ]
    kf, km, alpha = p[P_KF], p[P_KM], p[P_MOTOR_ALPHA]
    g = p[P_GRAVITY]
    half_h = p[P_HALF_HEIGHT]
    # Rotor speed targets are fixed over the call (a tuple: no array made per call).
    w_max = p[P_WMAX]
    w_cmd = (_rotor_speed_target(cmd[0], w_max), _rotor_speed_target(cmd[1], w_max),
             _rotor_speed_target(cmd[2], w_max), _rotor_speed_target(cmd[3], w_max))
    fx_ext, fy_ext, fz_ext = aux[0], aux[1], aux[2]
    tx_ext, ty_ext, tz_ext = aux[6], aux[7], aux[8]
    ax = ay = az = 0.0
    for _ in range(n_steps):
        # --- motors: exact first-order lag, then forces and torques from the new speeds -----------
        thrust = 0.0
        tau_x = tx_ext
        tau_y = ty_ext
        tau_z = tz_ext
        for i in range(4):
            w = x[13 + i] + (w_cmd[i] - x[13 + i]) * alpha
            x[13 + i] = w
            f = kf * w * w
            thrust += f
            tau_x += p[P_ROTOR_Y + i] * f
            tau_y -= p[P_ROTOR_X + i] * f
            tau_z -= p[P_SPIN + i] * km * w * w
        qw, qx, qy, qz = x[6], x[7], x[8], x[9]
        # Body->world rotation matrix.
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r02 = 2.0 * (qx * qz + qw * qy)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        r12 = 2.0 * (qy * qz - qw * qx)
        r20 = 2.0 * (qx * qz - qw * qy)
        r21 = 2.0 * (qy * qz + qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        vx, vy, vz = x[3], x[4], x[5]
        # Linear drag in the body frame: F_b = -c * (R^T v).
        dbx = -p[P_DRAG] * (r00 * vx + r10 * vy + r20 * vz)
        dby = -p[P_DRAG + 1] * (r01 * vx + r11 * vy + r21 * vz)
        dbz = -p[P_DRAG + 2] * (r02 * vx + r12 * vy + r22 * vz)
        fbz = thrust + dbz
        ax = (r00 * dbx + r01 * dby + r02 * fbz + fx_ext) / m
        ay = (r10 * dbx + r11 * dby + r12 * fbz + fy_ext) / m
        az = (r20 * dbx + r21 * dby + r22 * fbz + fz_ext) / m - g
        # --- translation: exact for constant acceleration over the step ---------------------------
        px = x[0] + vx * dt + 0.5 * ax * dt * dt
        py = x[1] + vy * dt + 0.5 * ay * dt * dt
        pz = x[2] + vz * dt + 0.5 * az * dt * dt
        nvx = vx + ax * dt
        nvy = vy + ay * dt
        nvz = vz + az * dt
        contact = pz - half_h < 0.0
        if contact:
            # The box bottom may not pass z = 0: stop there, drop downward speed (no bounce) and
            # apply Coulomb friction from the normal force that the ground supplies.
            pz = half_h
            if nvz < 0.0:
                nvz = 0.0
            dv_max = p[P_FRICTION] * max(0.0, -az) * dt
            vh = math.sqrt(nvx * nvx + nvy * nvy)
            if vh <= dv_max:
                nvx = 0.0
                nvy = 0.0
            else:
                scale = 1.0 - dv_max / vh
                nvx *= scale
                nvy *= scale
            px = x[0] + 0.5 * (vx + nvx) * dt
            py = x[1] + 0.5 * (vy + nvy) * dt
        ax = (nvx - vx) / dt
        ay = (nvy - vy) / dt
        az = (nvz - vz) / dt
        x[0], x[1], x[2] = px, py, pz
        x[3], x[4], x[5] = nvx, nvy, nvz
        # --- rotation: Euler's equations, then the quaternion turned by the mid-step rate ---------
        wx, wy, wz = x[10], x[11], x[12]
        tau_x += -(wy * wz * (izz - iyy)) - p[P_ANG_DRAG] * wx
        tau_y += -(wz * wx * (ixx - izz)) - p[P_ANG_DRAG + 1] * wy
        tau_z += -(wx * wy * (iyy - ixx)) - p[P_ANG_DRAG + 2] * wz
        nwx = wx + tau_x / ixx * dt
        nwy = wy + tau_y / iyy * dt
        nwz = wz + tau_z / izz * dt
        if contact:
            damp = p[P_GROUND_DAMP]
            nwx *= damp
            nwy *= damp
            nwz *= damp
        mx = 0.5 * (wx + nwx)
        my = 0.5 * (wy + nwy)
        mz = 0.5 * (wz + nwz)
        rate = math.sqrt(mx * mx + my * my + mz * mz)
        half = 0.5 * rate * dt
        if rate > 1e-12:
            s = math.sin(half) / rate
            c = math.cos(half)
        else:
            s = 0.5 * dt
            c = 1.0
        ex, ey, ez = s * mx, s * my, s * mz
        # q <- q (x) [c, e]  (body-frame increment)
        nqw = qw * c - qx * ex - qy * ey - qz * ez
        nqx = qw * ex + qx * c + qy * ez - qz * ey
        nqy = qw * ey - qx * ez + qy * c + qz * ex
        nqz = qw * ez + qx * ey - qy * ex + qz * c
        norm = math.sqrt(nqw * nqw + nqx * nqx + nqy * nqy + nqz * nqz)
        x[6], x[7], x[8], x[9] = nqw / norm, nqx / norm, nqy / norm, nqz / norm
        x[10], x[11], x[12] = nwx, nwy, nwz
    if n_steps > 0:
        aux[3], aux[4], aux[5] = ax, ay, az


@njit(cache=True, parallel=True)
def step_batch(xs: np.ndarray, auxs: np.ndarray, p: np.ndarray, cmds: np.ndarray, n_steps: int) -> None:
    """Advance every row of ``xs`` (N, STATE_SIZE) under ``cmds`` (N, 4), rows in parallel."""
    for i in prange(xs.shape[0]):
        step_vehicle(xs[i], auxs[i], p, cmds[i], n_steps)
