"""The native physics backend: one vehicle (`NativeBackend`) or many (`BatchPhysics`), numba-compiled.

Model: 6-DoF rigid body with a quaternion attitude, four first-order motors (rotor speed lags toward
sqrt(u) * w_max), thrust k_f w^2 and drag torque k_m w^2 per rotor, X-configuration torques from the
rotor positions, gravity, linear body drag, angular damping, an external world force, and ground
contact at z = 0 with the bottom of the body box (no bounce, Coulomb friction). Both classes step
with the same kernel (`emulator.physics.kernels.step_vehicle`); one vehicle is the N = 1 case.
"""

from __future__ import annotations

import math
from dataclasses import fields

import numpy as np

from emulator.physics import DEFAULT_DT_S
from emulator.physics.kernels import (
    AUX_ACCEL,
    AUX_FORCE,
    AUX_SIZE,
    AUX_TORQUE,
    N_PARAMS,
    pack_params,
    step_batch,
    step_vehicle,
)
from emulator.physics.state import OMEGA, POS, QUAT, ROTOR, STATE_SIZE, VEL, VehicleState
from emulator.profile import VehicleProfile

#: where the parameters begin in `NativeBackend.kernel_buffer` (after the state and auxiliary rows)
KERNEL_PARAMS = STATE_SIZE + AUX_SIZE
#: where the captured pose begins in `NativeBackend.kernel_buffer` (after the parameters): a batched
#: stepper's copy of the pose at a step inside its batch (x, y, z (m), qw, qx, qy, qz: `pose_values`)
KERNEL_POSE = KERNEL_PARAMS + N_PARAMS
POSE_SIZE = 7
#: where the clock is in `NativeBackend.kernel_buffer` (after the captured pose): the steps taken since the
#: last reset (a whole number, as a float) and the time then (s); ``time_s`` is ``t0 + steps * dt_s``. A
#: batched stepper's kernel counts the steps it takes there itself (no `advance_clock` call a batch)
KERNEL_CLOCK = KERNEL_POSE + POSE_SIZE
KERNEL_SIZE = KERNEL_CLOCK + 2


def hover_state(profile: VehicleProfile, pos_m: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> VehicleState:
    """A level vehicle at rest at ``pos_m`` (m, ENU) with rotors spinning at the hover speed."""
    w = math.sqrt(profile.hover_throttle) * profile.max_rotor_speed_rad_s
    return VehicleState(pos_m=np.array(pos_m, dtype=float), rotor_speed_rad_s=np.full(4, w))


def _check_state_vector(v: np.ndarray, what: str) -> np.ndarray:
    """A validated copy of state rows (..., STATE_SIZE) with unit quaternions."""
    v = np.array(v, dtype=np.float64)
    if v.shape[-1:] != (STATE_SIZE,):
        raise ValueError(f"{what}: expected rows of {STATE_SIZE} numbers, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{what}: state contains non-finite values")
    norms = np.linalg.norm(v[..., QUAT], axis=-1, keepdims=True)
    if np.any(norms < 1e-9):
        raise ValueError(f"{what}: attitude quaternion has zero length")
    v[..., QUAT] /= norms
    if np.any(v[..., ROTOR] < 0):
        raise ValueError(f"{what}: rotor speeds must be >= 0 rad/s")
    return v


def _check_force(force: np.ndarray, shape: tuple[int, ...], what: str = "external force",
                 unit: str = "N, world ENU") -> np.ndarray:
    f = np.asarray(force, dtype=np.float64)
    try:
        f = np.broadcast_to(f, shape)
    except ValueError:
        raise ValueError(f"{what}: expected shape {shape} ({unit}), got {f.shape}") from None
    if not np.all(np.isfinite(f)):
        raise ValueError(f"{what}: non-finite values")
    return f


def _check_steps(n_steps: int) -> int:
    if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 0:
        raise ValueError(f"n_steps must be a non-negative integer, got {n_steps!r}")
    return int(n_steps)


_STATE_FIELDS = ("time_s", "pos_m", "vel_m_s", "quat_wxyz", "omega_rad_s", "rotor_speed_rad_s", "accel_m_s2")
assert tuple(f.name for f in fields(VehicleState)) == _STATE_FIELDS, "VehicleState changed: update here"


def _state_from_vector(x: np.ndarray, time_s: float, accel: np.ndarray) -> VehicleState:
    """`VehicleState.from_vector` for the backend's own finite float64 vector, without the per-field
    conversions: one read-only copy of the vector, the fields are views of it."""
    v = np.concatenate((x, accel))
    v.flags.writeable = False
    st = object.__new__(VehicleState)
    put = object.__setattr__
    put(st, "time_s", time_s)
    put(st, "pos_m", v[POS])
    put(st, "vel_m_s", v[VEL])
    put(st, "quat_wxyz", v[QUAT])
    put(st, "omega_rad_s", v[OMEGA])
    put(st, "rotor_speed_rad_s", v[ROTOR])
    put(st, "accel_m_s2", v[STATE_SIZE : STATE_SIZE + 3])
    return st


class NativeBackend:
    """One vehicle stepped by the numba kernel at a fixed ``dt_s`` (s); implements PhysicsBackend.

    Throttles outside [0, 1] are clipped; a non-finite throttle counts as 0 (motor off).
    """

    name = "native"

    def __init__(self, profile: VehicleProfile, dt_s: float = DEFAULT_DT_S) -> None:
        self.profile = profile
        params = pack_params(profile, dt_s)
        self.dt_s = float(dt_s)
        # the state row, the auxiliary row and the parameters one after another in one array, a pose
        # captured mid-batch and the clock (`kernel_buffer`), each a view of it
        self._buffer = np.zeros(KERNEL_SIZE)
        self._x = self._buffer[:STATE_SIZE]
        self._aux = self._buffer[STATE_SIZE:KERNEL_PARAMS]
        self._params = self._buffer[KERNEL_PARAMS:KERNEL_POSE]
        self._pose = self._buffer[KERNEL_POSE:KERNEL_CLOCK]
        self._clock = self._buffer[KERNEL_CLOCK:]  # (steps, t0 (s)): the only count of the steps taken
        self._params[:] = params
        self.reset(VehicleState())

    def reset(self, state: VehicleState) -> None:
        """Put the vehicle in ``state``; its ``time_s`` becomes the clock. The external force is kept."""
        self._x[:] = _check_state_vector(state.to_vector(), "reset")
        self._aux[AUX_ACCEL] = state.accel_m_s2
        self._clock[:] = (0.0, float(state.time_s))

    def step(self, motor_cmd: np.ndarray, n_steps: int = 1) -> None:
        """Hold throttle ``motor_cmd`` (4,) in [0, 1] for ``n_steps`` steps of ``dt_s``."""
        cmd = np.asarray(motor_cmd, dtype=np.float64)
        if cmd.shape != (4,):
            raise ValueError(f"motor_cmd: expected 4 throttles, got shape {cmd.shape}")
        if n_steps.__class__ is not int or n_steps < 0:
            n_steps = _check_steps(n_steps)
        step_vehicle(self._x, self._aux, self._params, cmd, n_steps)
        self._clock[0] += n_steps

    @property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(state row (STATE_SIZE,), auxiliary row (AUX_SIZE,), parameters) as `step_vehicle` advances
        them in place: for a compiled caller that fuses its own per-step work with the physics step
        (`emulator.loops.batched_steps`); it reports the steps it took with `advance_clock`."""
        return self._x, self._aux, self._params

    @property
    def kernel_buffer(self) -> np.ndarray:
        """`kernel_arrays` as one array, of which they are views: the state row ``[:STATE_SIZE]``, the
        auxiliary row ``[STATE_SIZE:KERNEL_PARAMS]``, the parameters ``[KERNEL_PARAMS:KERNEL_POSE]``, a
        captured pose ``[KERNEL_POSE:KERNEL_CLOCK]`` (`captured_pose`), the clock ``[KERNEL_CLOCK:]``
        (`KERNEL_CLOCK`: a compiled caller that counts its steps there needs no `advance_clock`); a
        compiled caller called often takes this one argument instead of three (numba unboxes each array
        argument of each call)."""
        return self._buffer

    @property
    def clock(self) -> tuple[float, int]:
        """(t0 (s), steps): ``time_s`` is ``t0 + steps * dt_s``, for a compiled caller that keeps the time
        of the steps it takes through `kernel_arrays`."""
        steps, t0 = self._clock.tolist()
        return t0, int(steps)

    def advance_clock(self, n_steps: int) -> float:
        """Count ``n_steps`` steps taken through `kernel_arrays` by another caller; returns ``time_s``
        (its sum, without the property's call)."""
        c = self._clock
        steps, t0 = c.tolist()
        steps += n_steps
        c[0] = steps
        return t0 + steps * self.dt_s

    def time_after_s(self, n_steps: int) -> float:
        """``time_s`` after ``n_steps`` more steps (s), as `advance_clock` will count them, without
        counting them."""
        steps, t0 = self._clock.tolist()
        return t0 + (steps + n_steps) * self.dt_s

    def captured_pose(self) -> tuple[float, ...]:
        """The pose a batched stepper last captured in `kernel_buffer` (``[KERNEL_POSE:]``), as
        `pose_values` gives a pose: (x, y, z (m), qw, qx, qy, qz)."""
        return tuple(self._pose.tolist())

    def set_external_force(self, force_world_n: np.ndarray) -> None:
        """A disturbance force (N, world ENU) held until changed."""
        self._aux[AUX_FORCE] = _check_force(force_world_n, (3,))

    def set_external_torque(self, torque_body_nm: np.ndarray) -> None:
        """A disturbance torque (N m, body FLU) held until changed."""
        self._aux[AUX_TORQUE] = _check_force(torque_body_nm, (3,), "external torque", "N m, body FLU")

    @property
    def time_s(self) -> float:
        """Simulated time (s)."""
        steps, t0 = self._clock.tolist()
        return t0 + steps * self.dt_s

    @property
    def state(self) -> VehicleState:
        """The current state (built on demand)."""
        return _state_from_vector(self._x, self.time_s, self._aux[AUX_ACCEL])

    def state_vector(self) -> np.ndarray:
        """A copy of the flat state (STATE_SIZE,), cheaper than ``state``."""
        return self._x.copy()

    def pose_values(self) -> tuple[float, ...]:
        """(x, y, z (m), qw, qx, qy, qz) now as plain floats, cheaper than ``state``."""
        v = self._x.tolist()
        return (v[0], v[1], v[2], v[6], v[7], v[8], v[9])

    def close(self) -> None:
        """Nothing to release; idempotent."""


class BatchPhysics:
    """``n`` independent vehicles of one profile, rows of an (n, STATE_SIZE) array, stepped in parallel."""

    def __init__(self, profile: VehicleProfile, n: int, dt_s: float = DEFAULT_DT_S) -> None:
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise ValueError(f"n must be a positive integer, got {n!r}")
        self.profile = profile
        self.n = int(n)
        self._params = pack_params(profile, dt_s)
        self.dt_s = float(dt_s)
        self._x = np.tile(VehicleState().to_vector(), (self.n, 1))
        self._aux = np.zeros((self.n, AUX_SIZE))
        self._steps = 0

    def reset(self, states: np.ndarray | VehicleState, rows: np.ndarray | None = None) -> None:
        """Set all rows (or ``rows``) to ``states``: (k, STATE_SIZE), one row, or a VehicleState."""
        vec = states.to_vector() if isinstance(states, VehicleState) else states
        idx = np.arange(self.n) if rows is None else np.asarray(rows, dtype=np.intp).reshape(-1)
        if idx.size and (idx.min() < -self.n or idx.max() >= self.n):
            raise ValueError(f"reset: row index out of range for {self.n} vehicles")
        v = _check_state_vector(vec, "reset")
        try:
            self._x[idx] = np.broadcast_to(v, (idx.size, STATE_SIZE))
        except ValueError:
            raise ValueError(f"reset: {v.shape} states do not fit {idx.size} rows") from None
        self._aux[idx, 3:6] = 0.0
        if rows is None:
            self._steps = 0

    def step(self, motor_cmd: np.ndarray, n_steps: int = 1) -> None:
        """Hold throttles ``motor_cmd`` (n, 4) (or (4,) for all) for ``n_steps`` steps of ``dt_s``."""
        cmd = np.asarray(motor_cmd, dtype=np.float64)
        if cmd.shape != (self.n, 4):
            if cmd.shape != (4,):
                raise ValueError(f"motor_cmd: expected shape ({self.n}, 4) or (4,), got {cmd.shape}")
            cmd = np.broadcast_to(cmd, (self.n, 4))
        step_batch(self._x, self._aux, self._params, np.ascontiguousarray(cmd), _check_steps(n_steps))
        self._steps += n_steps

    @property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`NativeBackend.kernel_arrays` of the batch: state rows (n, STATE_SIZE), auxiliary rows
        (n, AUX_SIZE), parameters; a caller reports the steps it took with `advance_clock`."""
        return self._x, self._aux, self._params

    @property
    def clock(self) -> tuple[float, int]:
        """(t0 (s), steps): ``time_s`` is ``t0 + steps * dt_s`` (a batch's time starts at 0 s at its
        construction or full reset), for a compiled caller that keeps the time of the steps it takes
        through `kernel_arrays`."""
        return 0.0, self._steps

    def advance_clock(self, n_steps: int) -> None:
        """Count ``n_steps`` steps taken through `kernel_arrays` by another caller."""
        self._steps += n_steps

    def set_external_force(self, force_world_n: np.ndarray) -> None:
        """Disturbance forces (N, world ENU): (n, 3) per vehicle or (3,) for all, held until changed."""
        self._aux[:, AUX_FORCE] = _check_force(force_world_n, (self.n, 3))

    @property
    def time_s(self) -> float:
        """Simulated time since construction or the last full reset (s)."""
        return self._steps * self.dt_s

    @property
    def states(self) -> np.ndarray:
        """The state array (n, STATE_SIZE), read-only view (layout of `emulator.physics.state`)."""
        return self._view(slice(None))

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) positions, world ENU (m)."""
        return self._view(POS)

    @property
    def velocities(self) -> np.ndarray:
        """(n, 3) velocities, world ENU (m/s)."""
        return self._view(VEL)

    @property
    def quaternions(self) -> np.ndarray:
        """(n, 4) attitudes body->world (w, x, y, z)."""
        return self._view(QUAT)

    @property
    def accelerations(self) -> np.ndarray:
        """(n, 3) last step's accelerations, world ENU (m/s^2)."""
        a = self._aux[:, AUX_ACCEL]
        a.flags.writeable = False
        return a

    def vehicle_state(self, i: int) -> VehicleState:
        """Row ``i`` as a VehicleState."""
        return VehicleState.from_vector(self._x[i], time_s=self.time_s, accel_m_s2=self._aux[i, AUX_ACCEL])

    def _view(self, cols: slice) -> np.ndarray:
        v = self._x[:, cols]
        v.flags.writeable = False
        return v
