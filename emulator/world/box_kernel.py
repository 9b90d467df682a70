"""The compiled checks of `emulator.world.collision`: one oriented box against the gap's wall, the
ground and the lab (definitions in that module's docstring), for one pose or a batch of them; and the
crossing tracker's pass over a batch of checked samples (`scan_samples`).

The only implementation: `World`'s queries, one pose or many, and `CrossingTracker`'s batches are views
of it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

CODE_NONE, CODE_WALL, CODE_GROUND, CODE_LAB = 0, 1, 2, 3


@njit(cache=True)
def _slab_extent(c0: float, c1: float, c2: float, a: tuple, h0: float, h1: float, h2: float,
                 ht: float) -> tuple:
    """(umin, umax, vmin, vmax) (m) of the part of a box (centre c, axes ``a`` = its 3x3 matrix's
    entries row by row, half sizes h) within the slab |n| <= ``ht``: the box clipped by the two faces."""
    vu = np.empty(8)
    vn = np.empty(8)
    vv = np.empty(8)
    for k in range(8):
        sx = h0 if k & 4 else -h0
        sy = h1 if k & 2 else -h1
        sz = h2 if k & 1 else -h2
        vu[k] = c0 + a[0] * sx + a[1] * sy + a[2] * sz
        vn[k] = c1 + a[3] * sx + a[4] * sy + a[5] * sz
        vv[k] = c2 + a[6] * sx + a[7] * sy + a[8] * sz
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
    return umin, umax, vmin, vmax


@njit(cache=True, inline="always")
def _box_gap(c0: float, c1: float, c2: float, a: tuple, h0: float, h1: float, h2: float, ht: float,
             hw: float, hh: float) -> tuple:
    """Clearance (m), in_slab, limiting edge (0..3) of a box: centre c and axes ``a`` (its 3x3 matrix's
    entries row by row; columns: the box's axes) in gap coordinates (u, n, v), half sizes h; slab half
    thickness ht, opening half sizes hw x hh."""
    ru = abs(a[0]) * h0 + abs(a[1]) * h1 + abs(a[2]) * h2
    rn = abs(a[3]) * h0 + abs(a[4]) * h1 + abs(a[5]) * h2
    rv = abs(a[6]) * h0 + abs(a[7]) * h1 + abs(a[8]) * h2
    umin, umax, vmin, vmax = c0 - ru, c0 + ru, c2 - rv, c2 + rv
    in_slab = abs(c1) <= ht + rn
    if in_slab and abs(c1) + rn > ht:  # the box reaches out of the slab: clip it by the two faces
        umin, umax, vmin, vmax = _slab_extent(c0, c1, c2, a, h0, h1, h2, ht)
    m0, m1, m2, m3 = hw - umax, hw + umin, hh - vmax, hh + vmin
    edge, least = 0, m0
    if m1 < least:
        edge, least = 1, m1
    if m2 < least:
        edge, least = 2, m2
    if m3 < least:
        edge, least = 3, m3
    return least, in_slab, edge


@njit(cache=True)
def _overlaps_block(t0: float, t1: float, t2: float, a: tuple, b0: float, b1: float, b2: float,
                    w: np.ndarray) -> bool:
    """Separating-axis test: box (centre t, axes ``a`` = its 3x3 matrix's entries row by row, columns its
    axes, half sizes b) vs the AABB of half sizes ``w`` (3,)."""
    t = np.array((t0, t1, t2))
    b = np.array((b0, b1, b2))
    r = np.empty((3, 3))
    for k in range(9):
        r[k // 3, k % 3] = a[k]
    absr = np.abs(r) + 1e-12
    for k in range(3):
        if abs(t[k]) > w[k] + absr[k, 0] * b[0] + absr[k, 1] * b[1] + absr[k, 2] * b[2]:
            return False
    for i in range(3):
        d = abs(t[0] * r[0, i] + t[1] * r[1, i] + t[2] * r[2, i])
        if d > b[i] + w[0] * absr[0, i] + w[1] * absr[1, i] + w[2] * absr[2, i]:
            return False
    for k in range(3):
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        for i in range(3):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            ra = w[k1] * absr[k2, i] + w[k2] * absr[k1, i]
            rb = b[i1] * absr[k, i2] + b[i2] * absr[k, i1]
            if abs(t[k2] * r[k1, i] - t[k1] * r[k2, i]) > ra + rb:
                return False
    return True


@njit(cache=True)
def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z), normalised here; the caller rejects zero or NaN."""
    r = np.empty((3, 3))
    quat_to_rot_into(q, r)
    return r


@njit(cache=True, inline="always")
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
    """The world's constants in one float64 array (27,), for `check_packed`: the gap's centre (m), its
    axes (rows e0, e1, e2), the box's half sizes (m), the wall's half sizes (m), the opening's half width
    and height (m), the lab's corners (m) and the contact tolerance (m)."""
    return np.concatenate([
        np.asarray(centre, np.float64).ravel(), np.asarray(axes, np.float64).ravel(),
        np.asarray(h, np.float64).ravel(), np.asarray(wall_half, np.float64).ravel(), [hw, hh],
        np.asarray(lab_min, np.float64).ravel(), np.asarray(lab_max, np.float64).ravel(), [tol],
    ]).astype(np.float64)


@njit(cache=True, inline="always")
def check_packed(p: np.ndarray, rot: np.ndarray, world: np.ndarray) -> tuple:
    """(obstacle code, clearance_m, in_slab, limiting edge) of position ``p`` (3,) and rotation ``rot``
    (3, 3) in the world of `pack_world`; codes as CODE_* above, priority wall > ground > lab. (Scalars
    throughout: the array views numba makes per call cost it more than the arithmetic does.)"""
    w = world
    d0, d1, d2 = p[0] - w[_P_CENTRE], p[1] - w[_P_CENTRE + 1], p[2] - w[_P_CENTRE + 2]
    x0, x1, x2 = w[_P_AXES], w[_P_AXES + 1], w[_P_AXES + 2]  # the gap's axes (rows)
    y0, y1, y2 = w[_P_AXES + 3], w[_P_AXES + 4], w[_P_AXES + 5]
    z0, z1, z2 = w[_P_AXES + 6], w[_P_AXES + 7], w[_P_AXES + 8]
    # the box's centre and axes in gap coordinates: c = axes (p - centre), a = axes rot
    c0 = x0 * d0 + x1 * d1 + x2 * d2
    c1 = y0 * d0 + y1 * d1 + y2 * d2
    c2 = z0 * d0 + z1 * d1 + z2 * d2
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    a = (x0 * r00 + x1 * r10 + x2 * r20, x0 * r01 + x1 * r11 + x2 * r21, x0 * r02 + x1 * r12 + x2 * r22,
         y0 * r00 + y1 * r10 + y2 * r20, y0 * r01 + y1 * r11 + y2 * r21, y0 * r02 + y1 * r12 + y2 * r22,
         z0 * r00 + z1 * r10 + z2 * r20, z0 * r01 + z1 * r11 + z2 * r21, z0 * r02 + z1 * r12 + z2 * r22)
    h0, h1, h2 = w[_P_HALF], w[_P_HALF + 1], w[_P_HALF + 2]
    tol = w[_P_TOL]
    clr, in_slab, edge = _box_gap(c0, c1, c2, a, h0, h1, h2, w[_P_WALL + 1], w[_P_HW], w[_P_HH])
    if in_slab and clr < -tol and _overlaps_block(c0, c1, c2, a, h0, h1, h2, w[_P_WALL:_P_HW]):
        return CODE_WALL, clr, in_slab, edge
    code = CODE_NONE
    for k in range(3):
        ext = abs(rot[k, 0]) * h0 + abs(rot[k, 1]) * h1 + abs(rot[k, 2]) * h2
        if k == 2 and p[2] - ext < -tol:
            return CODE_GROUND, clr, in_slab, edge
        if p[k] - ext < w[_P_MIN + k] - tol or p[k] + ext > w[_P_MAX + k] + tol:
            code = CODE_LAB
    return code, clr, in_slab, edge


@njit(cache=True)
def check_states(
    p: np.ndarray, q: np.ndarray, world: np.ndarray, codes: np.ndarray, clr: np.ndarray, in_slab: np.ndarray
) -> None:
    """`check_packed` of each row of positions ``p`` (N, 3) and quaternions ``q`` (N, 4; non-zero) or
    rotations (N, 3, 3), written to ``codes``, ``clr`` and ``in_slab`` (N,)."""
    r = np.empty((3, 3))
    for i in range(p.shape[0]):
        if q.ndim == 2:
            quat_to_rot_into(q[i], r)
            rot = r
        else:
            rot = q[i]
        c, cl, s, _ = check_packed(p[i], rot, world)
        codes[i] = c
        clr[i] = cl
        in_slab[i] = s


#: `scan_samples`'s verdicts on a batch's times
SCAN_OK, SCAN_NONFINITE, SCAN_NOT_INCREASING = 0, 1, 2
#: `scan_samples`' (prev_t, prev_n, has_prev) for a batch with no sample before it
NO_PREVIOUS = (-np.inf, np.nan, False)


@njit(cache=True)
def scan_samples(t: np.ndarray, codes: np.ndarray, clr: np.ndarray, in_slab: np.ndarray, n: np.ndarray,
                 prev_t: float, prev_n: float, has_prev: bool, changes: np.ndarray) -> tuple:
    """The crossing tracker's pass over a batch of checked samples: times ``t`` (N,) (s), obstacle codes,
    clearances (m) and in_slab (N,), offsets along the gap normal ``n`` (N,) (m), after the last sample
    (``prev_t`` s, ``prev_n`` m) when ``has_prev``. Returns (verdict SCAN_*, the first sample of least
    clearance in the slab (NaN counts least, as np.argmin; -1: none), the first that hit something (-1:
    none), how many sign changes of ``n`` (< 0 or not) there are): their indices, written to ``changes``
    in order, are the samples that complete a crossing (0: across from the last sample)."""
    m = t.shape[0]
    for i in range(m):
        if not np.isfinite(t[i]):
            return SCAN_NONFINITE, -1, -1, 0
    if has_prev and t[0] <= prev_t:
        return SCAN_NOT_INCREASING, -1, -1, 0
    for i in range(1, m):
        if t[i] - t[i - 1] <= 0:
            return SCAN_NOT_INCREASING, -1, -1, 0
    least = -1
    for i in range(m):
        if in_slab[i]:
            c = clr[i]
            if least < 0 or (clr[least] == clr[least] and (c != c or c < clr[least])):
                least = i
    hit = -1
    for i in range(m):
        if codes[i] != 0:
            hit = i
            break
    count = 0
    if has_prev and (prev_n < 0) != (n[0] < 0):
        changes[0] = 0
        count = 1
    for i in range(1, m):
        if (n[i] < 0) != (n[i - 1] < 0):
            changes[count] = i
            count += 1
    return SCAN_OK, least, hit, count
