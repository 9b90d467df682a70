"""`World`: what the vehicle's collision box hits (wall, ground, lab boundary) and its clearance in the gap.

The vehicle is an oriented box (``body_box_m`` = length x, width y, height z in body FLU, centred on the
body origin). A pose is a position (m, world ENU) and an attitude, body->world, given either as a 3x3
rotation matrix or as a quaternion (w, x, y, z).

Clearance (m), defined on the gap coordinates (u, n, v) of `emulator.world.geometry`:
  take the part of the box inside the wall slab |n| <= wall_thickness_m / 2 (exact: the box clipped by
  the two faces of the slab), project it on the gap plane, and measure for each of the opening's four
  edges the signed distance from the edge line to the farthest point of that projection, positive on the
  opening's side: width_m/2 - max u, width_m/2 + min u, height_m/2 - max v, height_m/2 + min v. The
  clearance is the smallest of the four (``limiting_edge`` says which: "+e0", "-e0", "+e2", "-e2").
  Positive: the box passes the opening with that margin (the exact in-plane distance to the nearest
  edge); negative: its depth past that edge line, measured normal to the edge. When the box does not
  reach the slab, the whole box is projected instead and ``in_slab`` is False.

Collision: the wall is the slab minus the opening, bounded by the wall's extent. The box hits it exactly
when the box overlaps the whole wall block (separating-axis test, 15 axes) and its clearance is negative.
Ground is z = 0; the lab boundary is the `LabVolume`'s faces. Penetrations up to ``contact_tolerance_m``
count as touching, not as a collision (a vehicle resting on the floor has not crashed).

`check`, `collision` and `clearance` (one pose) run a compiled kernel (`box_kernel`); the `*_batch`
helpers are vectorised numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, StrEnum

import numpy as np

from emulator.world.box_kernel import check_pose, check_state_pose, check_states, pack_world, quat_to_rot
from emulator.world.geometry import Gap, LabVolume, quat_to_matrix

EDGE_NAMES: tuple[str, ...] = ("+e0", "-e0", "+e2", "-e2")


class Obstacle(StrEnum):
    """What a collision hit; compares equal to its string value."""

    WALL = "wall"
    GROUND = "ground"
    LAB_BOUNDARY = "lab_boundary"


class ObstacleCode(IntEnum):
    """Integer codes used by the batch helpers (0 = no collision)."""

    NONE = 0
    WALL = 1
    GROUND = 2
    LAB_BOUNDARY = 3


_CODE_TO_OBSTACLE = {1: Obstacle.WALL, 2: Obstacle.GROUND, 3: Obstacle.LAB_BOUNDARY}


@dataclass(frozen=True)
class Clearance:
    """Signed clearance of the box in the gap (m); see the module docstring for the definition."""

    clearance_m: float
    in_slab: bool  # True: measured on the part of the box inside the wall slab; False: whole box projected
    limiting_edge: str  # the edge giving the minimum: "+e0", "-e0" (ends of the long side), "+e2", "-e2"


# Box vertices as sign patterns and the 12 edges as pairs of vertex indices differing in one sign.
_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                   if np.sum(_SIGNS[a] != _SIGNS[b]) == 1])
_EA, _EB = _EDGES[:, 0], _EDGES[:, 1]
# Index grids for the nine cross-product axes of the separating-axis test.
_KK, _II = (g.ravel() for g in np.meshgrid(np.arange(3), np.arange(3), indexing="ij"))
_K1, _K2, _I1, _I2 = (_KK + 1) % 3, (_KK + 2) % 3, (_II + 1) % 3, (_II + 2) % 3
_SAT_EPS = 1e-12


def _as_positions(pos_m: np.ndarray, batch: bool) -> np.ndarray:
    p = np.asarray(pos_m, dtype=np.float64)
    want = "(N, 3)" if batch else "(3,)"
    if (batch and (p.ndim != 2 or p.shape[1] != 3)) or (not batch and p.shape != (3,)):
        raise ValueError(f"position must have shape {want}, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("position has non-finite values")
    return p


def _as_rotations(attitude: np.ndarray, batch: bool) -> np.ndarray:
    a = np.asarray(attitude, dtype=np.float64)
    lead = a.shape[:1] if batch else ()
    if a.shape == (*lead, 4):
        if batch:
            return quat_to_matrix(a)
        if not (np.isfinite(a).all() and a @ a > 1e-18):
            raise ValueError(f"quaternion must be finite and non-zero, got {attitude!r}")
        return quat_to_rot(a)
    if a.shape == (*lead, 3, 3):
        if not np.all(np.isfinite(a)):
            raise ValueError("rotation matrix has non-finite values")
        return a
    want = "(N, 4) quaternions or (N, 3, 3) matrices" if batch else "a (4,) quaternion or a (3, 3) matrix"
    raise ValueError(f"attitude must be {want}, got shape {a.shape}")


class World:
    """The gap's wall, the ground (z = 0) and the lab volume, checked against the vehicle's body box."""

    def __init__(
        self,
        gap: Gap | None = None,
        lab: LabVolume | None = None,
        body_box_m: tuple[float, float, float] = (0.45, 0.45, 0.12),
        contact_tolerance_m: float = 1e-6,
    ) -> None:
        self.gap = gap if gap is not None else Gap()
        self.lab = lab if lab is not None else LabVolume()
        box = np.asarray(body_box_m, dtype=np.float64)
        if box.shape != (3,) or not np.all(np.isfinite(box)) or np.any(box <= 0):
            raise ValueError(f"body_box_m must be 3 positive lengths (m), got {body_box_m!r}")
        if not np.isfinite(contact_tolerance_m) or contact_tolerance_m < 0:
            raise ValueError(f"contact_tolerance_m must be >= 0, got {contact_tolerance_m!r}")
        self.body_box_m = (float(box[0]), float(box[1]), float(box[2]))
        self.contact_tolerance_m = float(contact_tolerance_m)
        self._half = box / 2
        self._centre = np.asarray(self.gap.centre_m)
        self._axes = self.gap.axes()  # rows e0, e1, e2
        self._hw, self._hh = self.gap.width_m / 2, self.gap.height_m / 2
        self._ht = self.gap.wall_thickness_m / 2
        self._wall_half = np.array([self.gap.wall_width_m / 2, self._ht, self.gap.wall_height_m / 2])
        self._lab_min, self._lab_max = np.asarray(self.lab.min_m), np.asarray(self.lab.max_m)
        self._signs_half = _SIGNS * self._half
        self._packed = pack_world(self._centre, self._axes, self._half, self._wall_half, self._hw, self._hh,
                                  self._lab_min, self._lab_max, self.contact_tolerance_m)

    @classmethod
    def for_profile(cls, gap: Gap, lab: LabVolume, profile: object, **kwargs: float) -> World:
        """A world checking the collision box of a `VehicleProfile` (its ``body_box_m``)."""
        return cls(gap, lab, body_box_m=profile.body_box_m, **kwargs)  # type: ignore[attr-defined]

    # --- scalar queries (one pose) ------------------------------------------------------------------
    def check(self, pos_m: np.ndarray, attitude: np.ndarray) -> tuple[Obstacle | None, Clearance]:
        """Both `collision` and `clearance` for one pose, computed together."""
        p = _as_positions(pos_m, batch=False)
        rot = _as_rotations(attitude, batch=False)
        code, clr, in_slab, edge = check_pose(
            p, rot, self._centre, self._axes, self._half, self._wall_half, self._hw, self._hh,
            self._lab_min, self._lab_max, self.contact_tolerance_m,
        )
        return _CODE_TO_OBSTACLE.get(code), Clearance(float(clr), bool(in_slab), EDGE_NAMES[edge])

    def check_state(self, pos_m: np.ndarray, quat_wxyz: np.ndarray) -> tuple[Obstacle | None, Clearance]:
        """`check` for a simulated state's own arrays, straight into the compiled kernels: float64
        position (3,) and non-zero quaternion (4,), finite (the caller vouches; nothing is validated)."""
        code, clr, in_slab, edge = check_state_pose(pos_m, quat_wxyz, self._packed)
        return _CODE_TO_OBSTACLE.get(code), Clearance(float(clr), bool(in_slab), EDGE_NAMES[edge])

    def check_state_values(self, pos_m: np.ndarray, quat_wxyz: np.ndarray) -> tuple[int, float, bool, int]:
        """`check_state` as plain values: (`ObstacleCode`, clearance_m, in_slab, limiting edge index into
        `EDGE_NAMES`), for per-sample loops."""
        return check_state_pose(pos_m, quat_wxyz, self._packed)

    def check_states_values(
        self, pos_m: np.ndarray, quat_wxyz: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`check_state_values` of N simulated states at once: positions (N, 3) and non-zero quaternions
        (N, 4), float64 and finite (not validated); returns (`ObstacleCode` (N,), clearance_m (N,),
        in_slab (N,))."""
        p = np.ascontiguousarray(pos_m, dtype=np.float64)
        q = np.ascontiguousarray(quat_wxyz, dtype=np.float64)
        n = len(p)
        codes, clr, in_slab = np.empty(n, np.int64), np.empty(n), np.empty(n, np.bool_)
        check_states(p, q, self._packed, codes, clr, in_slab)
        return codes, clr, in_slab

    def collision(self, pos_m: np.ndarray, attitude: np.ndarray) -> Obstacle | None:
        """What the box hits at this pose, or None. Order when several: wall, ground, lab boundary."""
        return self.check(pos_m, attitude)[0]

    def clearance(self, pos_m: np.ndarray, attitude: np.ndarray) -> Clearance:
        """Signed clearance of the box in the opening (m); see the module docstring."""
        return self.check(pos_m, attitude)[1]

    def gap_coords(self, pos_m: np.ndarray) -> np.ndarray:
        """A point's gap coordinates (u along e0, n along e1, v along e2) in metres (3,)."""
        return self._axes @ (_as_positions(pos_m, batch=False) - self._centre)

    def gap_coords_unchecked(self, pos_m: np.ndarray) -> np.ndarray:
        """`gap_coords` of a float64 (3,) position the caller has validated."""
        return self._axes @ (pos_m - self._centre)

    # --- batch queries (N poses) ---------------------------------------------------------------------
    def collision_batch(self, pos_m: np.ndarray, attitude: np.ndarray) -> np.ndarray:
        """`ObstacleCode` per pose (N,) int8 for positions (N, 3) and attitudes (N, 3, 3) or (N, 4)."""
        p = _as_positions(pos_m, batch=True)
        rot = _as_rotations(attitude, batch=True)
        if len(rot) != len(p):
            raise ValueError(f"{len(p)} positions but {len(rot)} attitudes")
        codes = np.zeros(len(p), dtype=np.int8)
        extent = np.abs(rot) @ self._half
        tol = self.contact_tolerance_m
        out_lab = np.any(p - extent < self._lab_min - tol, axis=1)
        out_lab |= np.any(p + extent > self._lab_max + tol, axis=1)
        codes[out_lab] = ObstacleCode.LAB_BOUNDARY
        codes[p[:, 2] - extent[:, 2] < -tol] = ObstacleCode.GROUND
        local, axes = self._to_local(p, rot)
        near = np.abs(local[:, 1]) <= self._ht + np.abs(axes[:, 1, :]) @ self._half
        if np.any(near):
            idx = np.flatnonzero(near)
            codes[idx[self._wall_hit(local[idx], axes[idx])]] = ObstacleCode.WALL
        return codes

    def clearance_batch(self, pos_m: np.ndarray, attitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(clearance_m (N,), in_slab (N,) bool) for positions (N, 3) and attitudes (N, 3, 3) or (N, 4)."""
        p = _as_positions(pos_m, batch=True)
        rot = _as_rotations(attitude, batch=True)
        if len(rot) != len(p):
            raise ValueError(f"{len(p)} positions but {len(rot)} attitudes")
        clr, in_slab, _ = self._clearance_local(*self._to_local(p, rot))
        return clr, in_slab

    @staticmethod
    def obstacle(code: int) -> Obstacle | None:
        """The `Obstacle` for a batch code (None for 0)."""
        return _CODE_TO_OBSTACLE.get(int(code))

    # --- geometry in gap coordinates -------------------------------------------------------------------
    def _to_local(self, p: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Box centres (N, 3) and axes (N, 3, 3), column i = body axis i, in gap coordinates (u, n, v)."""
        return (p - self._centre) @ self._axes.T, self._axes @ rot

    def _extents(self, local: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, ...]:
        """(umin, umax, vmin, vmax, in_slab) of the box's part inside the slab (whole box if outside)."""
        absax = np.abs(axes)
        ru, rn, rv = absax[:, 0, :] @ self._half, absax[:, 1, :] @ self._half, absax[:, 2, :] @ self._half
        cu, cn, cv = local[:, 0], local[:, 1], local[:, 2]
        umin, umax, vmin, vmax = cu - ru, cu + ru, cv - rv, cv + rv
        in_slab = np.abs(cn) <= self._ht + rn
        clipped = in_slab & (np.abs(cn) + rn > self._ht)  # reaches out of the slab: clip it
        if np.any(clipped):
            idx = np.flatnonzero(clipped)
            lo = self._clipped_extents(local[idx], axes[idx])
            umin[idx], umax[idx], vmin[idx], vmax[idx] = lo
        return umin, umax, vmin, vmax, in_slab

    def _clipped_extents(self, local: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, ...]:
        """u/v extents of box ∩ slab from its vertices: box corners inside, box edges ∩ the two faces."""
        verts = local[:, None, :] + np.einsum("vi,nki->nvk", self._signs_half, axes)  # (N, 8, 3)
        u, n, v = verts[..., 0], verts[..., 1], verts[..., 2]
        ht = self._ht
        cand_u, cand_v, cand_ok = [u], [v], [np.abs(n) <= ht * (1 + 1e-12) + 1e-15]
        na, nb = n[:, _EA], n[:, _EB]
        dn = nb - na
        safe = np.where(dn == 0, 1.0, dn)
        for level in (-ht, ht):
            alpha = (level - na) / safe
            cand_ok.append((dn != 0) & (alpha >= 0) & (alpha <= 1))
            cand_u.append(u[:, _EA] + alpha * (u[:, _EB] - u[:, _EA]))
            cand_v.append(v[:, _EA] + alpha * (v[:, _EB] - v[:, _EA]))
        cu, cv, ok = np.concatenate(cand_u, 1), np.concatenate(cand_v, 1), np.concatenate(cand_ok, 1)
        empty = ~np.any(ok, axis=1)
        if np.any(empty):  # only grazing a face within rounding: fall back to the corners
            ok[empty] = True
        return (np.where(ok, cu, np.inf).min(1), np.where(ok, cu, -np.inf).max(1),
                np.where(ok, cv, np.inf).min(1), np.where(ok, cv, -np.inf).max(1))

    def _clearance_local(self, local: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, ...]:
        """(clearance_m, in_slab, limiting edge index) per box."""
        umin, umax, vmin, vmax, in_slab = self._extents(local, axes)
        margins = np.stack([self._hw - umax, self._hw + umin, self._hh - vmax, self._hh + vmin], axis=1)
        edge = np.argmin(margins, axis=1)
        return margins[np.arange(len(edge)), edge], in_slab, edge

    def _wall_hit(self, local: np.ndarray, axes: np.ndarray) -> np.ndarray:
        """(N,) bool: the box overlaps the wall's solid part (negative clearance and inside the block)."""
        clr, in_slab, _ = self._clearance_local(local, axes)
        hit = in_slab & (clr < -self.contact_tolerance_m)
        if np.any(hit):
            idx = np.flatnonzero(hit)
            hit[idx] = self._overlaps_wall_block(local[idx], axes[idx])
        return hit

    def _overlaps_wall_block(self, t: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Separating-axis test of the boxes against the whole wall block (an AABB in gap coordinates)."""
        a, b = self._wall_half, self._half
        absr = np.abs(r) + _SAT_EPS
        sep = np.any(np.abs(t) > a + absr @ b, axis=1)
        dist = np.abs(np.einsum("nk,nki->ni", t, r))
        sep |= np.any(dist > np.einsum("nki,k->ni", absr, a) + b, axis=1)
        ra = a[_K1] * absr[:, _K2, _II] + a[_K2] * absr[:, _K1, _II]
        rb = b[_I1] * absr[:, _KK, _I2] + b[_I2] * absr[:, _KK, _I1]
        dist = np.abs(t[:, _K2] * r[:, _K1, _II] - t[:, _K1] * r[:, _K2, _II])
        sep |= np.any(dist > ra + rb, axis=1)
        return ~sep
