"""The gap and the lab as values: `Gap` (a rectangular opening in a finite wall) and `LabVolume`.

Gap frame (as in the paper's code): with R = Rz(yaw) Ry(pitch) Rx(roll) (angles in radians, applied
roll first, about the world axes x, y, z in that order), the gap's axes are
- e0 = R [0, 1, 0]: along the long side (``width_m``),
- e1 = R [1, 0, 0]: the crossing direction, normal to the wall (``wall_thickness_m`` is along it),
- e2 = e0 x e1 = -R [0, 0, 1]: along the short side (``height_m``).
The gap's roll therefore turns the opening about the crossing axis. A point p has gap coordinates
(u, n, v) = ((p - c).e0, (p - c).e1, (p - c).e2) with c the gap centre. The wall is the slab
|n| <= wall_thickness_m / 2, |u| <= wall_width_m / 2, |v| <= wall_height_m / 2, minus the opening
|u| < width_m / 2, |v| < height_m / 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_WALL_WIDTH_M = 4.0  # the wall's extent along e0, centred on the gap
DEFAULT_WALL_HEIGHT_M = 4.0  # the wall's extent along e2, centred on the gap


def rotation_zyx(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll) (3x3)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_quat(rot: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) with w >= 0 from a rotation matrix (3x3)."""
    r = np.asarray(rot, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    out = np.array(q)
    return -out if out[0] < 0 else out


def _finite(name: str, value: float) -> float:
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return x


def _vec3(name: str, value: object) -> tuple[float, float, float]:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be 3 numbers, got {value!r}") from exc
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Gap:
    """A rectangular opening in a finite wall (metres, radians; frame in the module docstring).

    Defaults: a 0.8 m x 0.45 m opening in a 5 cm thick wall of 4 m x 4 m, level, at (0, 0, 1.5)."""

    centre_m: tuple[float, float, float] = (0.0, 0.0, 1.5)
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    width_m: float = 0.8  # long side, along e0
    height_m: float = 0.45  # short side, along e2
    wall_thickness_m: float = 0.05  # along e1
    wall_width_m: float = DEFAULT_WALL_WIDTH_M  # along e0
    wall_height_m: float = DEFAULT_WALL_HEIGHT_M  # along e2

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre_m", _vec3("Gap.centre_m", self.centre_m))
        for name in ("roll_rad", "pitch_rad", "yaw_rad", "width_m", "height_m", "wall_thickness_m",
                     "wall_width_m", "wall_height_m"):
            object.__setattr__(self, name, _finite(f"Gap.{name}", getattr(self, name)))
        for name in ("width_m", "height_m", "wall_thickness_m"):
            if getattr(self, name) <= 0:
                raise ValueError(f"Gap.{name} must be positive, got {getattr(self, name)}")
        if self.height_m > self.width_m:
            raise ValueError(
                f"Gap.width_m is the long side: width_m ({self.width_m}) must be >= "
                f"height_m ({self.height_m})"
            )
        if self.wall_width_m <= self.width_m or self.wall_height_m <= self.height_m:
            raise ValueError(
                f"the wall ({self.wall_width_m} x {self.wall_height_m} m) must be larger than the opening "
                f"({self.width_m} x {self.height_m} m)"
            )

    @classmethod
    def from_deg(
        cls,
        centre_m: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.5),
        roll_deg: float = 0.0,
        pitch_deg: float = 0.0,
        yaw_deg: float = 0.0,
        **sizes: float,
    ) -> Gap:
        """A gap with its angles in degrees; ``sizes`` are the other fields (width_m, height_m, ...)."""
        return cls(
            centre_m=_vec3("Gap.centre_m", centre_m),
            roll_rad=math.radians(_finite("roll_deg", roll_deg)),
            pitch_rad=math.radians(_finite("pitch_deg", pitch_deg)),
            yaw_rad=math.radians(_finite("yaw_deg", yaw_deg)),
            **sizes,
        )

    def rotation(self) -> np.ndarray:
        """R = Rz(yaw) Ry(pitch) Rx(roll) (3x3): columns e1, e0, -e2."""
        return rotation_zyx(self.roll_rad, self.pitch_rad, self.yaw_rad)

    def quat_wxyz(self) -> np.ndarray:
        """R as a quaternion (w, x, y, z)."""
        return matrix_to_quat(self.rotation())

    def axes(self) -> np.ndarray:
        """Rows e0 (long side), e1 (crossing direction), e2 (short side) in world ENU (3x3)."""
        r = self.rotation()
        e0, e1 = r[:, 1], r[:, 0]
        return np.stack([e0, e1, np.cross(e0, e1)])

@dataclass(frozen=True)
class LabVolume:
    """The flyable room: an axis-aligned box in world ENU (m). Default x, y in [-5, 5], z in [0, 4]."""

    min_m: tuple[float, float, float] = (-5.0, -5.0, 0.0)
    max_m: tuple[float, float, float] = (5.0, 5.0, 4.0)

    def __post_init__(self) -> None:
        lo, hi = _vec3("LabVolume.min_m", self.min_m), _vec3("LabVolume.max_m", self.max_m)
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(f"LabVolume.min_m {lo} must be below max_m {hi} on every axis")
        object.__setattr__(self, "min_m", lo)
        object.__setattr__(self, "max_m", hi)

    def contains(self, point_m: np.ndarray) -> bool:
        """Whether a point lies inside the volume (boundary included)."""
        p = np.asarray(point_m, dtype=np.float64)
        return bool(np.all(p >= np.asarray(self.min_m)) and np.all(p <= np.asarray(self.max_m)))
