"""`CrossingTracker`: follows a trajectory sample by sample and reports gap crossings, minimum clearance
and the first collision.

A crossing is the vehicle's centre passing the gap plane (through the gap centre, normal to e1). Its
time and point are interpolated linearly between the two samples on either side of the plane; it is
"through the opening" when that point lies inside the opening's rectangle (|u| <= width/2 and
|v| <= height/2). The minimum clearance is taken over the samples whose box overlaps the wall slab.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from emulator.world.box_kernel import NO_PREVIOUS, SCAN_NONFINITE, SCAN_NOT_INCREASING, scan_samples
from emulator.world.collision import Obstacle, ObstacleCode, World


@dataclass(frozen=True)
class Crossing:
    """One passage of the centre through the gap plane."""

    time_s: float
    direction: int  # +1 along e1 (the crossing direction), -1 against it
    point_m: tuple[float, float, float]  # world ENU, where the centre met the plane
    offset_m: tuple[float, float]  # (u, v): the point's offsets from the gap centre along e0 and e2
    through_opening: bool


@dataclass(frozen=True)
class CollisionEvent:
    """The first sample at which the box hit something."""

    time_s: float
    obstacle: Obstacle


class CrossingTracker:
    """Feed it samples with `update`; read `crossings`, `min_clearance_m` and `first_collision`."""

    def __init__(self, world: World) -> None:
        self.world = world
        world.compile_kernels()  # (now, not at the first sample of a real-time loop)
        self._crossings: list[Crossing] = []
        self._prev: tuple[float, np.ndarray, float] | None = None  # (time_s, pos_m, n)
        self.min_clearance_m: float | None = None  # None until the box first overlaps the slab
        self.min_clearance_time_s: float | None = None
        self.first_collision: CollisionEvent | None = None
        self.samples = 0
        self._changes = np.empty(64, np.int64)  # `scan_samples`' sign changes of a batch

    def update(self, time_s: float, pos_m: np.ndarray, attitude: np.ndarray) -> Crossing | None:
        """Add one sample (time in s, position m, attitude as 3x3 or quaternion wxyz), checked with
        ``world.check``; returns the crossing completed by this sample, if any. Times must increase."""
        world = self.world
        hit, clr = world.check(pos_m, attitude)  # validates the pose
        p = np.array(pos_m, dtype=np.float64)
        code = ObstacleCode.NONE if hit is None else ObstacleCode[hit.name]
        done = self.add_checked_batch([time_s], p[None], np.array([code], np.int64),
                                      np.array([clr.clearance_m]), np.array([clr.in_slab]),
                                      world.gap_coords(p)[1:2])
        return done[0][1] if done else None

    def add_checked_batch(
        self,
        time_s: np.ndarray,
        pos_m: np.ndarray,
        codes: np.ndarray,
        clearance_m: np.ndarray,
        in_slab: np.ndarray,
        n_m: np.ndarray,
    ) -> list[tuple[int, Crossing]]:
        """Add N samples whose poses the caller has checked already: times (N,) (s) increasing, positions
        (N, 3) (m), what each hit (`ObstacleCode` (N,)), clearances (N,) (m) and in_slab (N,) as
        ``world.check_states_values`` gives them, and offsets along e1 (N,) (m). Returns the crossings
        completed, each with the index of the sample that completed it."""
        t = np.asarray(time_s, dtype=np.float64)
        m = len(t)
        if m == 0:
            return []
        if m > len(self._changes):
            self._changes = np.empty(2 * m, np.int64)
        n = np.asarray(n_m, dtype=np.float64)
        prev = self._prev
        last = (prev[0], prev[2], True) if prev else NO_PREVIOUS
        verdict, j, hit, count = scan_samples(t, codes, clearance_m, in_slab, n, *last, self._changes)
        if verdict == SCAN_NONFINITE:
            raise ValueError(f"time_s must be finite, got {time_s!r}")
        if verdict == SCAN_NOT_INCREASING:
            raise ValueError("time_s must increase")
        if j >= 0 and (self.min_clearance_m is None or clearance_m[j] < self.min_clearance_m):
            self.min_clearance_m, self.min_clearance_time_s = float(clearance_m[j]), float(t[j])
        if hit >= 0 and self.first_collision is None:
            obstacle = World.obstacle(codes[hit])
            self.first_collision = CollisionEvent(float(t[hit]), obstacle)  # type: ignore[arg-type]
        p = np.asarray(pos_m, dtype=np.float64)
        out = []
        if count:
            for i in self._changes[:count].tolist():
                if i == 0:  # across from the last batch
                    out.append((0, self._crossing(prev[0], prev[1], prev[2], float(t[0]), p[0], float(n[0]))))
                else:
                    out.append((i, self._crossing(float(t[i - 1]), p[i - 1], float(n[i - 1]), float(t[i]),
                                                  p[i], float(n[i]))))
            self._crossings.extend(c for _, c in out)
        self._prev = (float(t[-1]), p[-1].copy(), float(n[-1]))
        self.samples += m
        return out

    def _crossing(self, t0: float, p0: np.ndarray, n0: float, t: float, p: np.ndarray, n: float) -> Crossing:
        """The crossing between samples (t0, p0, n0) and (t, p, n) on either side of the plane."""
        world = self.world
        alpha = -n0 / (n - n0)
        point = p0 + alpha * (p - p0)
        u, _, v = world.gap_coords(point)
        gap = world.gap
        return Crossing(
            time_s=t0 + alpha * (t - t0),
            direction=1 if n > n0 else -1,
            point_m=(float(point[0]), float(point[1]), float(point[2])),
            offset_m=(float(u), float(v)),
            through_opening=bool(abs(u) <= gap.width_m / 2 and abs(v) <= gap.height_m / 2),
        )

    @property
    def crossing_count(self) -> int:
        """How many crossings so far (``len(crossings)`` without building the tuple)."""
        return len(self._crossings)

    @property
    def crossings(self) -> tuple[Crossing, ...]:
        """All crossings so far, in time order."""
        return tuple(self._crossings)

    @property
    def crossed_through_opening(self) -> bool:
        """Whether the first crossing went forward (+e1) through the opening."""
        first = self._crossings[0] if self._crossings else None
        return first is not None and first.direction > 0 and first.through_opening

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready summary (for run reports)."""
        first = self._crossings[0] if self._crossings else None
        return {
            "samples": self.samples,
            "crossings": len(self._crossings),
            "crossed_through_opening": self.crossed_through_opening,
            "crossing_time_s": None if first is None else first.time_s,
            "crossing_direction": None if first is None else first.direction,
            "crossing_offset_m": None if first is None else list(first.offset_m),
            "min_clearance_m": self.min_clearance_m,
            "min_clearance_time_s": self.min_clearance_time_s,
            "collision": None if self.first_collision is None else str(self.first_collision.obstacle),
            "collision_time_s": None if self.first_collision is None else self.first_collision.time_s,
        }
