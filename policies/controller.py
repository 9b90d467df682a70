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
from typing import Any

import numpy as np

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
    holding a vehicle must not send them; ``ExpertController.command`` raises instead)."""
    if not (math.isfinite(mass_kg) and mass_kg > 0):
        raise ValueError("mass_kg must be positive")
    axes = [tuple(np.asarray(x, float)[..., k] for k in range(3))
            for x in (pos_ref_m, vel_ref_m_s, acc_ref_m_s2, pos_m, vel_m_s)]
    with np.errstate(invalid="ignore", divide="ignore"):
        roll, pitch, thrust = _expert_law(*axes, np.asarray(yaw_ref_rad, float), mass_kg, gains, _ARRAYS)
    return roll, pitch, np.array(np.broadcast_to(np.asarray(yaw_ref_rad, float), thrust.shape)), thrust


class ExpertController:
    """The expert law for one vehicle: ``command(reference, state)`` -> AttitudeThrustCommand."""

    def __init__(self, mass_kg: float = 0.9, gains: ExpertGains | None = None) -> None:
        if not (math.isfinite(mass_kg) and mass_kg > 0):
            raise ValueError("mass_kg must be positive")
        self.mass_kg = mass_kg
        self.gains = gains or ExpertGains()

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
        if not math.isfinite(yaw_ref_rad):
            raise ValueError("yaw_ref_rad must be finite")
        yaw = float(yaw_ref_rad)
        return _new_command(*_expert_law(*vals, yaw, self.mass_kg, self.gains, _FLOATS), yaw)


def _floats3(value: object) -> tuple[float, float, float]:
    """Three floats from an array or a sequence; TypeError or ValueError if it is not three numbers."""
    x, y, z = value.tolist() if isinstance(value, np.ndarray) else value  # type: ignore[attr-defined,misc]
    return float(x), float(y), float(z)


class _Floats:
    """The operations of `_expert_law` on plain floats (one sample, the per-step path)."""

    sqrt, sin, cos, asin, atan2, maximum = math.sqrt, math.sin, math.cos, math.asin, math.atan2, max

    @staticmethod
    def clip(x: float, limit: float) -> float:
        return limit if x > limit else (-limit if x < -limit else x)

    @staticmethod
    def scale(norm: float, limit: float) -> float:
        return limit / norm if norm > limit else 1.0


class _Arrays:
    """The operations of `_expert_law` on arrays (a batch)."""

    sqrt, sin, cos, asin, atan2, maximum = np.sqrt, np.sin, np.cos, np.arcsin, np.arctan2, np.maximum

    @staticmethod
    def clip(x: np.ndarray, limit: float) -> np.ndarray:
        return np.clip(x, -limit, limit)

    @staticmethod
    def scale(norm: np.ndarray, limit: np.ndarray) -> np.ndarray:
        return np.where(norm > limit, limit / norm, 1.0)


_FLOATS, _ARRAYS = _Floats(), _Arrays()
_Vec = tuple[Any, Any, Any]  # x, y, z components: floats, or arrays of the batch shape


def _expert_law(p_ref: _Vec, v_ref: _Vec, a_ref: _Vec, p: _Vec, v: _Vec, yaw: Any, mass_kg: float,
                gains: ExpertGains, ops: _Floats | _Arrays) -> tuple[Any, Any, Any]:
    """The expert law (module docstring) on x, y, z components: roll, pitch (rad) and thrust (N)."""
    mp, mv = gains.max_pos_err_m, gains.max_vel_err_m_s
    (kpx, kpy, kpz), (kvx, kvy, kvz), ka = gains.kp, gains.kv, gains.ka
    clip = ops.clip
    ex, ey, ez = clip(p_ref[0] - p[0], mp), clip(p_ref[1] - p[1], mp), clip(p_ref[2] - p[2], mp)
    fx, fy, fz = clip(v_ref[0] - v[0], mv), clip(v_ref[1] - v[1], mv), clip(v_ref[2] - v[2], mv)
    hx = kvx * (fx + kpx * ex) + ka * a_ref[0] + 0.0
    hy = kvy * (fy + kpy * ey) + ka * a_ref[1] + 0.0
    f_z = ops.maximum(kvz * (fz + kpz * ez) + ka * a_ref[2] + GRAVITY_M_S2,
                      gains.min_thrust_frac * GRAVITY_M_S2)
    # F's horizontal part scaled down to the tilt limit, F_z kept
    scale = ops.scale(ops.sqrt(hx * hx + hy * hy), f_z * math.tan(gains.tilt_max_rad))
    fx, fy, fz = mass_kg * (hx * scale), mass_kg * (hy * scale), mass_kg * f_z
    thrust = ops.sqrt(fx * fx + fy * fy + fz * fz)
    zx_w, zy_w, zz = fx / thrust, fy / thrust, fz / thrust
    # R_d = Rz(yaw) Ry(pitch) Rx(roll): rotate z_b back by -yaw, then z' = (cr sp, -sr, cr cp)
    cy, sy = ops.cos(yaw), ops.sin(yaw)
    zx = cy * zx_w + sy * zy_w
    zy = -sy * zx_w + cy * zy_w
    return ops.asin(clip(-zy, 1.0)), ops.atan2(zx, zz), thrust


def _new_command(roll_rad: float, pitch_rad: float, thrust_n: float, yaw_rad: float) -> AttitudeThrustCommand:
    """``AttitudeThrustCommand(roll_rad, pitch_rad, yaw_rad, thrust_n)`` made without the frozen
    dataclass's per-field __setattr__ calls (once per control step): the same object, built faster."""
    cmd = object.__new__(AttitudeThrustCommand)
    cmd.__dict__.update(roll_rad=roll_rad, pitch_rad=pitch_rad, yaw_rad=yaw_rad, thrust_n=thrust_n)
    return cmd


def limit_tilt_step(cmd: AttitudeThrustCommand, last: AttitudeThrustCommand,
                    max_step_rad: float) -> AttitudeThrustCommand:
    """``cmd`` with its roll and pitch each moved at most ``max_step_rad`` (rad) from ``last``'s: a
    command that turns no faster than the FC can (its body rate times the control period); yaw and
    thrust as they are."""
    r, p, lr, lp = cmd.roll_rad, cmd.pitch_rad, last.roll_rad, last.pitch_rad
    r2 = lr + max_step_rad if r > lr + max_step_rad else (lr - max_step_rad if r < lr - max_step_rad else r)
    p2 = lp + max_step_rad if p > lp + max_step_rad else (lp - max_step_rad if p < lp - max_step_rad else p)
    if r2 == r and p2 == p:
        return cmd
    return _new_command(r2, p2, cmd.thrust_n, cmd.yaw_rad)
