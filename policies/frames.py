"""Rotation helpers for the onboard side: elementary rotations, ZYX Euler angles, quaternions (wxyz).

Conventions: world ENU (z up), body FLU. A rotation matrix maps body (or gap) coordinates into the
world: ``v_world = R @ v_body``. Euler angles are Z-Y-X (yaw, pitch, roll):
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``; with yaw = 0 this is the paper's equation (1) (which writes the
transpose, world -> body). All functions accept a leading batch dimension.
"""

from __future__ import annotations

import numpy as np

GRAVITY_M_S2 = 9.8  # the paper's release uses 9.8
GRAVITY_VEC_M_S2 = np.array([0.0, 0.0, -GRAVITY_M_S2])  # ENU: gravity points down


def rot_x(angle_rad: np.ndarray | float) -> np.ndarray:
    """Rotation by ``angle_rad`` about x; shape (..., 3, 3)."""
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([one, zero, zero], -1), np.stack([zero, c, -s], -1),
                     np.stack([zero, s, c], -1)], -2)


def rot_y(angle_rad: np.ndarray | float) -> np.ndarray:
    """Rotation by ``angle_rad`` about y; shape (..., 3, 3)."""
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1),
                     np.stack([-s, zero, c], -1)], -2)


def rot_z(angle_rad: np.ndarray | float) -> np.ndarray:
    """Rotation by ``angle_rad`` about z; shape (..., 3, 3)."""
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1),
                     np.stack([zero, zero, one], -1)], -2)


def euler_to_matrix(roll_rad: np.ndarray | float, pitch_rad: np.ndarray | float,
                    yaw_rad: np.ndarray | float) -> np.ndarray:
    """Body -> world rotation ``Rz(yaw) Ry(pitch) Rx(roll)``; shape (..., 3, 3)."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (w, x, y, z), shape (..., 4), to rotation matrices (..., 3, 3).

    The quaternion is normalised first; a zero quaternion raises ValueError.
    """
    q = np.asarray(q_wxyz, dtype=float)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must have 4 components (w, x, y, z), got shape {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError("quaternion must be finite and non-zero")
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
