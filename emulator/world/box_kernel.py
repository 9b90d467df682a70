"""The compiled checks of `emulator.world.collision`: one oriented box against the gap's wall, the
ground and the lab (definitions in that module's docstring), for one pose or a batch of them.

The only implementation: `World`'s queries, one pose or many, are views of it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

CODE_NONE, CODE_WALL, CODE_GROUND, CODE_LAB = 0, 1, 2, 3


@njit(cache=True)
def _box_gap(c: np.ndarray, a: np.ndarray, h: np.ndarray, ht: float, hw: float, hh: float) -> tuple:
    """Clearance (m), in_slab, limiting edge (0..3) of a box: centre c and axes a (columns) in gap
    coordinates (u, n, v), half sizes h; slab half thickness ht, opening half sizes hw x hh."""
    ru = abs(a[0, 0]) * h[0] + abs(a[0, 1]) * h[1] + abs(a[0, 2]) * h[2]
    rn = abs(a[1, 0]) * h[0] + abs(a[1, 1]) * h[1] + abs(a[1, 2]) * h[2]
    rv = abs(a[2, 0]) * h[0] + abs(a[2, 1]) * h[1] + abs(a[2, 2]) * h[2]
    umin, umax, vmin, vmax = c[0] - ru, c[0] + ru, c[2] - rv, c[2] + rv
    in_slab = abs(c[1]) <= ht + rn
    if in_slab and abs(c[1]) + rn > ht:  # the box reaches out of the slab: clip it by the two faces
        vu = np.empty(8)
        vn = np.empty(8)
        vv = np.empty(8)
        for k in range(8):
            sx = h[0] if k & 4 else -h[0]
            sy = h[1] if k & 2 else -h[1]
            sz = h[2] if k & 1 else -h[2]
            vu[k] = c[0] + a[0, 0] * sx + a[0, 1] * sy + a[0, 2] * sz
            vn[k] = c[1] + a[1, 0] * sx + a[1, 1] * sy + a[1, 2] * sz
            vv[k] = c[2] + a[2, 0] * sx + a[2, 1] * sy + a[2, 2] * sz
        umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
        lim = ht * (1 + 1e-12) + 1e-15
        for k in range(8):
            if abs(vn[k]) <= lim:
                umin, umax = min(umin, vu[k]), max(umax, vu[k])
                vmin, vmax = min(vmin, vv[k]), max(vmax, vv[k])
        for k in range(8):
            for bit in (4, 2, 1):
                j = k | bit
                if j == k:
                    continue
                dn = vn[j] - vn[k]
                if dn == 0.0:
                    continue
                for level in (-ht, ht):
                    alpha = (level - vn[k]) / dn
                    if 0.0 <= alpha <= 1.0:
                        u = vu[k] + alpha * (vu[j] - vu[k])
                        v = vv[k] + alpha * (vv[j] - vv[k])
                        umin, umax = min(umin, u), max(umax, u)
                        vmin, vmax = min(vmin, v), max(vmax, v)
        if umin > umax:  # only grazing a face within rounding: use the corners
            umin, umax = vu.min(), vu.max()
            vmin, vmax = vv.min(), vv.max()
    margins = (hw - umax, hw + umin, hh - vmax, hh + vmin)
    edge = 0
    for i in range(1, 4):
        if margins[i] < margins[edge]:
            edge = i
    return margins[edge], in_slab, edge


@njit(cache=True)
def _overlaps_block(t: np.ndarray, r: np.ndarray, b: np.ndarray, a: np.ndarray) -> bool:
    """Separating-axis test: box (centre t, axes r columns, half sizes b) vs the AABB of half sizes a."""
    absr = np.abs(r) + 1e-12
    for k in range(3):
        if abs(t[k]) > a[k] + absr[k, 0] * b[0] + absr[k, 1] * b[1] + absr[k, 2] * b[2]:
            return False
    for i in range(3):
        d = abs(t[0] * r[0, i] + t[1] * r[1, i] + t[2] * r[2, i])
        if d > b[i] + a[0] * absr[0, i] + a[1] * absr[1, i] + a[2] * absr[2, i]:
            return False
    for k in range(3):
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        for i in range(3):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            ra = a[k1] * absr[k2, i] + a[k2] * absr[k1, i]
            rb = b[i1] * absr[k, i2] + b[i2] * absr[k, i1]
            if abs(t[k2] * r[k1, i] - t[k1] * r[k2, i]) > ra + rb:
                return False
    return True


@njit(cache=True)
def check_pose(
    p: np.ndarray, rot: np.ndarray, centre: np.ndarray, axes: np.ndarray, h: np.ndarray,
    wall_half: np.ndarray, hw: float, hh: float, lab_min: np.ndarray, lab_max: np.ndarray, tol: float,
) -> tuple:
    """(obstacle code, clearance_m, in_slab, limiting edge) for one pose; codes as CODE_* above,
    priority wall > ground > lab."""
    buf = np.empty(12)  # one allocation: c (3,) and a (3, 3)
    c = buf[0:3]  # no `@` inside numba without scipy's BLAS: write the products out
    a = buf[3:12].reshape((3, 3))
    d0, d1, d2 = p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]
    for k in range(3):
        c[k] = axes[k, 0] * d0 + axes[k, 1] * d1 + axes[k, 2] * d2
        for i in range(3):
            a[k, i] = axes[k, 0] * rot[0, i] + axes[k, 1] * rot[1, i] + axes[k, 2] * rot[2, i]
    clr, in_slab, edge = _box_gap(c, a, h, wall_half[1], hw, hh)
    if in_slab and clr < -tol and _overlaps_block(c, a, h, wall_half):
        return CODE_WALL, clr, in_slab, edge
    code = CODE_NONE
    for k in range(3):
        ext = abs(rot[k, 0]) * h[0] + abs(rot[k, 1]) * h[1] + abs(rot[k, 2]) * h[2]
        if k == 2 and p[2] - ext < -tol:
            return CODE_GROUND, clr, in_slab, edge
        if p[k] - ext < lab_min[k] - tol or p[k] + ext > lab_max[k] + tol:
            code = CODE_LAB
    return code, clr, in_slab, edge


@njit(cache=True)
def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z), normalised here; the caller rejects zero or NaN."""
    r = np.empty((3, 3))
    quat_to_rot_into(q, r)
    return r


@njit(cache=True)
def quat_to_rot_into(q: np.ndarray, r: np.ndarray) -> None:
    """`quat_to_rot` written into ``r`` (3, 3)."""
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    r[0, 0], r[0, 1], r[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r[1, 0], r[1, 1], r[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r[2, 0], r[2, 1], r[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


#: layout of the packed world constants of `check_packed` (see `pack_world`)
_P_CENTRE, _P_AXES, _P_HALF, _P_WALL, _P_HW, _P_HH, _P_MIN, _P_MAX, _P_TOL = 0, 3, 12, 15, 18, 19, 20, 23, 26


def pack_world(
    centre: np.ndarray, axes: np.ndarray, h: np.ndarray, wall_half: np.ndarray, hw: float, hh: float,
    lab_min: np.ndarray, lab_max: np.ndarray, tol: float,
) -> np.ndarray:
    """`check_pose`'s constant arguments in one float64 array (27,), for `check_packed`."""
    return np.concatenate([
        np.asarray(centre, np.float64).ravel(), np.asarray(axes, np.float64).ravel(),
        np.asarray(h, np.float64).ravel(), np.asarray(wall_half, np.float64).ravel(), [hw, hh],
        np.asarray(lab_min, np.float64).ravel(), np.asarray(lab_max, np.float64).ravel(), [tol],
    ]).astype(np.float64)


@njit(cache=True)
def check_packed(p: np.ndarray, rot: np.ndarray, world: np.ndarray) -> tuple:
    """`check_pose` of position ``p`` and rotation ``rot`` with the world constants of `pack_world`."""
    return check_pose(
        p, rot, world[_P_CENTRE:_P_AXES], world[_P_AXES:_P_HALF].reshape((3, 3)),
        world[_P_HALF:_P_WALL], world[_P_WALL:_P_HW], world[_P_HW], world[_P_HH], world[_P_MIN:_P_MAX],
        world[_P_MAX:_P_TOL], world[_P_TOL],
    )


@njit(cache=True)
def check_states(
    p: np.ndarray, q: np.ndarray, world: np.ndarray, codes: np.ndarray, clr: np.ndarray, in_slab: np.ndarray
) -> None:
    """`check_packed` of each row of positions ``p`` (N, 3) and quaternions ``q`` (N, 4; non-zero) or
    rotations (N, 3, 3), written to ``codes``, ``clr`` and ``in_slab`` (N,)."""
    for i in range(p.shape[0]):
        rot = quat_to_rot(q[i]) if q.ndim == 2 else q[i]
        c, cl, s, _ = check_packed(p[i], rot, world)
        codes[i] = c
        clr[i] = cl
        in_slab[i] = s
