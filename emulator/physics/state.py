"""The vehicle's rigid-body state as one frozen value (world ENU, body FLU, SI units)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Layout of the flat state vector every backend keeps (one row per vehicle in a batch).
POS = slice(0, 3)  # position in world ENU (m)
VEL = slice(3, 6)  # velocity in world ENU (m/s)
QUAT = slice(6, 10)  # attitude body->world, (w, x, y, z)
OMEGA = slice(10, 13)  # body angular rate FLU (rad/s)
ROTOR = slice(13, 17)  # rotor speeds (rad/s)
STATE_SIZE = 17


def _vec(x: object, n: int) -> np.ndarray:
    a = np.array(x, dtype=np.float64).reshape(n)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class VehicleState:
    """One vehicle's state at ``time_s``. Arrays are read-only copies."""

    time_s: float = 0.0
    pos_m: np.ndarray = field(default_factory=lambda: _vec([0, 0, 0], 3))
    vel_m_s: np.ndarray = field(default_factory=lambda: _vec([0, 0, 0], 3))
    quat_wxyz: np.ndarray = field(default_factory=lambda: _vec([1, 0, 0, 0], 4))
    omega_rad_s: np.ndarray = field(default_factory=lambda: _vec([0, 0, 0], 3))
    rotor_speed_rad_s: np.ndarray = field(default_factory=lambda: _vec([0, 0, 0, 0], 4))
    accel_m_s2: np.ndarray = field(default_factory=lambda: _vec([0, 0, 0], 3))  # world, last step

    def __post_init__(self) -> None:
        for name, n in (
            ("pos_m", 3),
            ("vel_m_s", 3),
            ("quat_wxyz", 4),
            ("omega_rad_s", 3),
            ("rotor_speed_rad_s", 4),
            ("accel_m_s2", 3),
        ):
            object.__setattr__(self, name, _vec(getattr(self, name), n))

    def to_vector(self) -> np.ndarray:
        """The flat layout above (length STATE_SIZE)."""
        v = np.empty(STATE_SIZE)
        v[POS], v[VEL], v[QUAT] = self.pos_m, self.vel_m_s, self.quat_wxyz
        v[OMEGA], v[ROTOR] = self.omega_rad_s, self.rotor_speed_rad_s
        return v

    @classmethod
    def from_vector(
        cls, v: np.ndarray, time_s: float = 0.0, accel_m_s2: np.ndarray | None = None
    ) -> VehicleState:
        """Inverse of ``to_vector``."""
        return cls(
            time_s=time_s,
            pos_m=v[POS],
            vel_m_s=v[VEL],
            quat_wxyz=v[QUAT],
            omega_rad_s=v[OMEGA],
            rotor_speed_rad_s=v[ROTOR],
            accel_m_s2=np.zeros(3) if accel_m_s2 is None else accel_m_s2,
        )

    def rotation_matrix(self) -> np.ndarray:
        """Body->world rotation matrix (3x3)."""
        w, x, y, z = self.quat_wxyz
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
