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

Every query, one pose or a batch, is a view of the compiled kernel in `emulator.world.box_kernel`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, StrEnum

import numpy as np

from emulator.world.box_kernel import (
    NO_PREVIOUS,
    check_packed,
    check_states,
    pack_world,
    quat_to_rot,
    scan_samples,
)
from emulator.world.geometry import Gap, LabVolume

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


def _as_positions(pos_m: np.ndarray, batch: bool) -> np.ndarray:
    p = np.array(pos_m, dtype=np.float64)  # (a writable copy: one compiled type for the checks, even of
    # a `VehicleState`'s read-only arrays)
    want = "(N, 3)" if batch else "(3,)"
    if (batch and (p.ndim != 2 or p.shape[1] != 3)) or (not batch and p.shape != (3,)):
        raise ValueError(f"position must have shape {want}, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("position has non-finite values")
    return p


def _as_attitudes(attitude: np.ndarray, batch: bool) -> np.ndarray:
    """Validated quaternions (N, 4) or rotations (N, 3, 3) of a batch; one pose's rotation (3, 3)."""
    a = np.array(attitude, dtype=np.float64)  # (a writable copy, as `_as_positions`)
    lead = a.shape[:1] if batch else ()
    if a.shape == (*lead, 4):
        if not (np.isfinite(a).all() and np.all(np.einsum("...i,...i", a, a) > 1e-18)):
            raise ValueError(f"quaternion must be finite and non-zero, got {attitude!r}")
        return a if batch else quat_to_rot(a)
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
        self._centre = np.asarray(self.gap.centre_m)
        self._axes = self.gap.axes()  # rows e0, e1, e2
        g = self.gap
        wall_half = np.array([g.wall_width_m / 2, g.wall_thickness_m / 2, g.wall_height_m / 2])
        self._packed = pack_world(self._centre, self._axes, box / 2, wall_half, g.width_m / 2, g.height_m / 2,
                                  self.lab.min_m, self.lab.max_m, self.contact_tolerance_m)

    @classmethod
    def for_profile(cls, gap: Gap, lab: LabVolume, profile: object, **kwargs: float) -> World:
        """A world checking the collision box of a `VehicleProfile` (its ``body_box_m``)."""
        return cls(gap, lab, body_box_m=profile.body_box_m, **kwargs)  # type: ignore[attr-defined]

    @property
    def packed(self) -> np.ndarray:
        """This world's constants as `box_kernel.pack_world` packs them (27,): a row of the worlds that
        `emulator.loops.batched_steps.fly_targets` checks a batch against, each row its own world."""
        return self._packed

    def compile_kernels(self) -> None:
        """Compile the compiled checks, one pose and N, and the crossing tracker's pass over a batch, or
        load them from numba's cache, now rather than at the first check: a real-time loop would otherwise
        stall in flight on a fresh install."""
        level = np.array([1.0, 0.0, 0.0, 0.0])
        self.check(self._centre, level)
        codes, clr, in_slab = self.check_states_values(self._centre[None, :], level[None, :])
        scan_samples(clr, codes, clr, in_slab, clr, *NO_PREVIOUS, np.empty(1, np.int64))  # (the tracker's)

    # --- one pose ---------------------------------------------------------------------------------------
    def check(self, pos_m: np.ndarray, attitude: np.ndarray) -> tuple[Obstacle | None, Clearance]:
        """Both `collision` and `clearance` for one pose, computed together."""
        p = _as_positions(pos_m, batch=False)
        code, clr, in_slab, edge = check_packed(p, _as_attitudes(attitude, batch=False), self._packed)
        return _CODE_TO_OBSTACLE.get(code), Clearance(float(clr), bool(in_slab), EDGE_NAMES[edge])

    def collision(self, pos_m: np.ndarray, attitude: np.ndarray) -> Obstacle | None:
        """What the box hits at this pose, or None. Order when several: wall, ground, lab boundary."""
        return self.check(pos_m, attitude)[0]

    def clearance(self, pos_m: np.ndarray, attitude: np.ndarray) -> Clearance:
        """Signed clearance of the box in the opening (m); see the module docstring."""
        return self.check(pos_m, attitude)[1]

    def gap_coords(self, pos_m: np.ndarray) -> np.ndarray:
        """A point's gap coordinates (u along e0, n along e1, v along e2) in metres (3,)."""
        return self._axes @ (_as_positions(pos_m, batch=False) - self._centre)


    # --- N poses ---------------------------------------------------------------------------------------
    def check_states_values(
        self, pos_m: np.ndarray, attitude: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`check` of N poses as arrays, for simulated states (not validated): positions (N, 3) and
        non-zero quaternions (N, 4) or rotations (N, 3, 3), finite; returns (`ObstacleCode` (N,),
        clearance_m (N,), in_slab (N,))."""
        p = np.ascontiguousarray(pos_m, dtype=np.float64)
        a = np.ascontiguousarray(attitude, dtype=np.float64)
        n = len(p)
        codes, clr, in_slab = np.empty(n, np.int64), np.empty(n), np.empty(n, np.bool_)
        check_states(p, a, self._packed, codes, clr, in_slab)
        return codes, clr, in_slab

    def check_batch(self, pos_m: np.ndarray, attitude: np.ndarray) -> tuple[np.ndarray, ...]:
        """`check_states_values` of positions (N, 3) and attitudes (N, 3, 3) or (N, 4), validated."""
        p = _as_positions(pos_m, batch=True)
        att = _as_attitudes(attitude, batch=True)
        if len(att) != len(p):
            raise ValueError(f"{len(p)} positions but {len(att)} attitudes")
        return self.check_states_values(p, att)

    @staticmethod
    def obstacle(code: int) -> Obstacle | None:
        """The `Obstacle` for a batch code (None for 0)."""
        return _CODE_TO_OBSTACLE.get(int(code))
