"""The expert controller: geometric position tracking (Lee et al.; Mellinger and Kumar) to attitude + thrust.

With the paper's release gains (REFERENCE.md), per axis:
    e_p = clip(p_ref - p, +-0.3 m),  e_v = clip(v_ref - v, +-2 m/s)
    F = m (Kv (e_v + Kp e_p) + g_up) + m Ka a_ref          (N, world ENU, g_up = (0, 0, 9.8))
F is tilted at most ``tilt_max`` from vertical (its horizontal part is scaled down, keeping F_z;
F_z is kept at least ``min_thrust_frac`` of the hover thrust). The thrust command is |F| and the
desired body z axis is F / |F|; with the desired yaw psi the desired attitude is
R_d = Rz(psi) Ry(theta) Rx(phi), whose roll phi and pitch theta are returned. These are the ZYX Euler
angles relative to the ground (world) frame, z up: with psi = 0 (the paper's choice) R_d is the
transpose of the paper's equation (1), body z = (cos phi sin theta, -sin phi, cos phi cos theta).
The vehicle's measured acceleration and attitude are not used by this law (it commands an absolute
attitude); they are inputs of the learned controllers that imitate it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from policies.compiling import Kernel
from policies.frames import GRAVITY_M_S2


@dataclass(frozen=True)
class ExpertGains:
    """Gains and limits of the expert law (the paper's release values by default)."""

    kp: tuple[float, float, float] = (6.5, 6.5, 8.5)  # 1/s
    kv: tuple[float, float, float] = (2.25, 2.25, 4.5)  # 1/s
    ka: float = 0.9  # feed-forward fraction of the reference acceleration
    max_pos_err_m: float = 0.3
    max_vel_err_m_s: float = 2.0
    tilt_max_rad: float = math.radians(75.0)
    min_thrust_frac: float = 0.1  # floor on F_z as a fraction of m g


@dataclass(frozen=True)
class AttitudeThrustCommand:
    """One command in the N3 attitude-thrust form: roll, pitch, yaw (rad, ground frame), thrust (N)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_n: float


def expert_command_batch(pos_ref_m: np.ndarray, vel_ref_m_s: np.ndarray, acc_ref_m_s2: np.ndarray,
                         yaw_ref_rad: np.ndarray | float, pos_m: np.ndarray, vel_m_s: np.ndarray,
                         mass_kg: float = 0.9, gains: ExpertGains = ExpertGains(),
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The expert law over a batch: arrays (..., 3) and yaw (...); returns roll, pitch, yaw (rad) and
    thrust (N), each of shape (...). Non-finite inputs give NaN outputs for that sample (callers
    holding a vehicle must not send them; ``ExpertController.command`` raises instead). The same
    numbers as ``ExpertController.command`` sample by sample (`expert_law`, compiled, row by row)."""
    if not (math.isfinite(mass_kg) and mass_kg > 0):
        raise ValueError("mass_kg must be positive")
    vecs = [np.asarray(x, float) for x in (pos_ref_m, vel_ref_m_s, acc_ref_m_s2, pos_m, vel_m_s)]
    yaw = np.asarray(yaw_ref_rad, float)
    shape = np.broadcast_shapes(yaw.shape, *(v.shape[:-1] for v in vecs))
    rows = [np.ascontiguousarray(np.broadcast_to(v, (*shape, 3))).reshape(-1, 3) for v in vecs]
    yaws = np.ascontiguousarray(np.broadcast_to(yaw, shape)).reshape(-1)
    out = np.empty((yaws.size, 3))
    EXPERT_LAW_ROWS.get()(*rows, yaws, mass_kg, gains_array(gains), out)
    return (out[:, 0].reshape(shape), out[:, 1].reshape(shape), yaws.reshape(shape).copy(),
            out[:, 2].reshape(shape))


def gains_array(gains: ExpertGains) -> np.ndarray:
    """``gains`` as `expert_law` reads them: kp (3, 1/s), kv (3, 1/s), ka, the position (m) and velocity
    (m/s) error limits, tan of the tilt limit, the floor (m/s^2) on F_z / m."""
    return np.array([*gains.kp, *gains.kv, gains.ka, gains.max_pos_err_m, gains.max_vel_err_m_s,
                     math.tan(gains.tilt_max_rad), gains.min_thrust_frac * GRAVITY_M_S2])


class ExpertController:
    """The expert law for one vehicle: ``command(reference, state)`` -> AttitudeThrustCommand."""

    def __init__(self, mass_kg: float = 0.9, gains: ExpertGains | None = None) -> None:
        if not (math.isfinite(mass_kg) and mass_kg > 0):
            raise ValueError("mass_kg must be positive")
        self.mass_kg = mass_kg
        self.gains = gains or ExpertGains()
        self.gains_array = gains_array(self.gains)  # (`expert_law`'s form, made once)

        self._law = EXPERT_LAW.get()

    def command(self, pos_ref_m: object, vel_ref_m_s: object, acc_ref_m_s2: object, yaw_ref_rad: float,
                pos_m: object, vel_m_s: object) -> AttitudeThrustCommand:
        """Attitude and thrust for one reference (m, m/s, m/s^2, rad) and measured state (m, m/s).

        Raises ValueError for non-finite or wrongly shaped inputs.
        """
        try:  # the usual case, checked in one go: five vectors of three finite numbers
            vals = (_floats3(pos_ref_m), _floats3(vel_ref_m_s), _floats3(acc_ref_m_s2), _floats3(pos_m),
                    _floats3(vel_m_s))
            (a, b, c), (d, e, f), (g, h, i), (j, k, m), (n, o, q) = vals
            finite = math.isfinite(a + b + c + d + e + f + g + h + i + j + k + m + n + o + q)
        except (TypeError, ValueError):
            finite = False
        if not finite:
            checked = []  # find which input is bad (or, after an overflowing sum, that none is)
            for name, value in (("pos_ref_m", pos_ref_m), ("vel_ref_m_s", vel_ref_m_s),
                                ("acc_ref_m_s2", acc_ref_m_s2), ("pos_m", pos_m), ("vel_m_s", vel_m_s)):
                try:
                    x, y, z = _floats3(value)
                except (TypeError, ValueError):
                    raise ValueError(f"{name} must be 3 finite numbers, got {value!r}") from None
                if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                    raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
                checked.append((x, y, z))
            vals = tuple(checked)
            (a, b, c), (d, e, f), (g, h, i), (j, k, m), (n, o, q) = vals
        if not math.isfinite(yaw_ref_rad):
            raise ValueError("yaw_ref_rad must be finite")
        yaw = float(yaw_ref_rad)
        return _new_command(*self._law(a, b, c, d, e, f, g, h, i, j, k, m, n, o, q, yaw, self.mass_kg,
                                       self.gains_array), yaw)


def _floats3(value: object) -> tuple[float, float, float]:
    """Three floats from an array or a sequence; TypeError or ValueError if it is not three numbers."""
    x, y, z = value.tolist() if isinstance(value, np.ndarray) else value  # type: ignore[attr-defined,misc]
    return float(x), float(y), float(z)


def _clip(x: float, limit: float) -> float:
    """``x`` within [-limit, limit] (NaN passes)."""
    return limit if x > limit else (-limit if x < -limit else x)


def expert_law(prx: float, pry: float, prz: float, vrx: float, vry: float, vrz: float, arx: float,
               ary: float, arz: float, px: float, py: float, pz: float, vx: float, vy: float, vz: float,
               yaw: float, mass_kg: float, g: np.ndarray) -> tuple[float, float, float]:
    """The expert law (module docstring) on x, y, z components of the reference position (m), velocity
    (m/s) and acceleration (m/s^2), the position (m) and velocity (m/s), with the desired yaw (rad), the
    mass (kg) and the gains ``g`` (`gains_array`): roll, pitch (rad) and thrust (N). Compiled by numba
    (`policies.compiling`), which is how it runs; non-finite inputs give NaN."""
    mp, mv = g[7], g[8]
    ex, ey, ez = _clip(prx - px, mp), _clip(pry - py, mp), _clip(prz - pz, mp)
    fx, fy, fz = _clip(vrx - vx, mv), _clip(vry - vy, mv), _clip(vrz - vz, mv)
    ka = g[6]
    hx = g[3] * (fx + g[0] * ex) + ka * arx + 0.0
    hy = g[4] * (fy + g[1] * ey) + ka * ary + 0.0
    f_z = g[5] * (fz + g[2] * ez) + ka * arz + GRAVITY_M_S2
    floor = g[10]
    f_z = floor if floor > f_z else f_z  # (max(f_z, floor), NaN passing as through it)
    # F's horizontal part scaled down to the tilt limit, F_z kept
    norm, limit = math.sqrt(hx * hx + hy * hy), f_z * g[9]
    scale = limit / norm if norm > limit else 1.0
    fx, fy, fz = mass_kg * (hx * scale), mass_kg * (hy * scale), mass_kg * f_z
    thrust = math.sqrt(fx * fx + fy * fy + fz * fz)
    zx_w, zy_w, zz = fx / thrust, fy / thrust, fz / thrust
    # R_d = Rz(yaw) Ry(pitch) Rx(roll): rotate z_b back by -yaw, then z' = (cr sp, -sr, cr cp)
    cy, sy = math.cos(yaw), math.sin(yaw)
    zx = cy * zx_w + sy * zy_w
    zy = -sy * zx_w + cy * zy_w
    return math.asin(_clip(-zy, 1.0)), math.atan2(zx, zz), thrust


def expert_law_rows(pos_ref_m: np.ndarray, vel_ref_m_s: np.ndarray, acc_ref_m_s2: np.ndarray,
                    pos_m: np.ndarray, vel_m_s: np.ndarray, yaw_rad: np.ndarray, mass_kg: float,
                    g: np.ndarray, out: np.ndarray) -> None:
    """`expert_law` of each row of the (N, 3) arrays and ``yaw_rad`` (N,) into ``out`` (N, 3: roll,
    pitch, thrust); compiled by numba (`policies.compiling`)."""
    for i in range(yaw_rad.shape[0]):
        pr, vr, ar, p, v = pos_ref_m[i], vel_ref_m_s[i], acc_ref_m_s2[i], pos_m[i], vel_m_s[i]
        out[i, 0], out[i, 1], out[i, 2] = expert_law(pr[0], pr[1], pr[2], vr[0], vr[1], vr[2], ar[0], ar[1],
                                                     ar[2], p[0], p[1], p[2], v[0], v[1], v[2], yaw_rad[i],
                                                     mass_kg, g)


def _new_command(roll_rad: float, pitch_rad: float, thrust_n: float, yaw_rad: float) -> AttitudeThrustCommand:
    """``AttitudeThrustCommand(roll_rad, pitch_rad, yaw_rad, thrust_n)`` made without the frozen
    dataclass's per-field __setattr__ calls (once per control step): the same object, built faster."""
    cmd = object.__new__(AttitudeThrustCommand)
    cmd.__dict__.update(roll_rad=roll_rad, pitch_rad=pitch_rad, yaw_rad=yaw_rad, thrust_n=thrust_n)
    return cmd


def limit_tilt_step(cmd: AttitudeThrustCommand, last_roll_rad: float, last_pitch_rad: float,
                    max_step_rad: float) -> AttitudeThrustCommand:
    """``cmd`` with its roll and pitch each moved at most ``max_step_rad`` (rad) from the last command's
    (``last_roll_rad``, ``last_pitch_rad``): a command that turns no faster than the FC can (its body rate
    times the control period); yaw and thrust as they are."""
    r, p = cmd.roll_rad, cmd.pitch_rad
    r2, p2 = tilt_step_limited(r, p, last_roll_rad, last_pitch_rad, max_step_rad)
    if r2 == r and p2 == p:
        return cmd
    return _new_command(r2, p2, cmd.thrust_n, cmd.yaw_rad)


def tilt_step_limited(roll_rad: float, pitch_rad: float, last_roll_rad: float, last_pitch_rad: float,
                      max_step_rad: float) -> tuple[float, float]:
    """`limit_tilt_step`'s roll and pitch (rad) on floats: each moved at most ``max_step_rad`` (rad) from the
    last command's (compiled into the traditional pilot's control step, `policies.compiling`)."""
    hi, lo = last_roll_rad + max_step_rad, last_roll_rad - max_step_rad
    r = hi if roll_rad > hi else (lo if roll_rad < lo else roll_rad)
    hi, lo = last_pitch_rad + max_step_rad, last_pitch_rad - max_step_rad
    return r, (hi if pitch_rad > hi else (lo if pitch_rad < lo else pitch_rad))


_CLIP = Kernel(_clip)
#: roll, pitch (rad), thrust (N) of the expert law, compiled: `expert_law`
EXPERT_LAW = Kernel(expert_law, _clip=_CLIP)
#: `expert_law` row by row, compiled: `expert_law_rows`
EXPERT_LAW_ROWS = Kernel(expert_law_rows, expert_law=EXPERT_LAW)
#: `tilt_step_limited` compiled
TILT_STEP_LIMITED = Kernel(tilt_step_limited)
