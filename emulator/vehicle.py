"""One emulated vehicle: a physics backend and its flight controller stepped together in simulated time."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from emulator.fc.flight_controller import FcConfig, FlightController
from emulator.fc.hold import hold_command
from emulator.fc.inner_loop import control
from emulator.fc.landed import body_landed
from emulator.fc.n3 import attitude_thrust_values, limit_tilt, yaw_fields
from emulator.physics import DEFAULT_DT_S, PhysicsBackend, make_backend
from emulator.physics.native import NativeBackend
from emulator.physics.state import VehicleState
from emulator.profile import VehicleProfile


def resting_state(
    profile: VehicleProfile,
    x_m: float = 0.0,
    y_m: float = 0.0,
    ground_z_m: float = 0.0,
    yaw_rad: float = math.pi / 2,
) -> VehicleState:
    """Level, at rest on the ground (body box bottom at ``ground_z_m``), rotors stopped, body x at
    ``yaw_rad`` from world +x (ENU: pi/2, the default, is north)."""
    quat = np.array([math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)])
    return VehicleState(pos_m=np.array([x_m, y_m, ground_z_m + 0.5 * profile.body_box_m[2]]), quat_wxyz=quat)


class MotorPath(Protocol):
    """Something that steps a vehicle's physics and FC its own way (`EmulatedVehicle.motor_path`)."""

    def step(self, n_steps: int) -> None: ...


class EmulatedVehicle:
    """Physics at ``dt_s`` (1 kHz by default) with the FC's inner loop run before every step."""

    def __init__(
        self,
        profile: VehicleProfile,
        *,
        backend: str | PhysicsBackend = "native",
        config: FcConfig | None = None,
        initial_state: VehicleState | None = None,
        dt_s: float = DEFAULT_DT_S,
    ) -> None:
        self.profile = profile
        self.backend = make_backend(backend, profile, dt_s) if isinstance(backend, str) else backend
        self.fc = FlightController(profile, config)
        self.backend.reset(initial_state or resting_state(profile, ground_z_m=self.fc.config.ground_z_m))
        self._state: VehicleState | None = self.backend.state
        self.steps = 0
        #: the step count ``_state`` was built at: a state of another count is stale (a batched stepper
        #: that steps the backend itself counts its steps here and needs no `invalidate_state` a batch)
        self._state_steps = 0
        #: steps the vehicle instead of `step`'s own loop when set (the motors behind an ESC bus,
        #: `emulator.esc.bus.EscBusStepper`); it counts ``steps`` itself
        self.motor_path: MotorPath | None = None
        # the backend's own flat readers, where it has them (read per stop of a run's loop): the same
        # values as the state built from the backend's, without building one, called straight
        fast_pose = getattr(self.backend, "pose_values", None)
        if fast_pose is not None:
            self.pose_values = fast_pose  # type: ignore[method-assign]
        fast_vector = getattr(self.backend, "state_vector", None)
        if fast_vector is not None:
            self.state_vector = fast_vector  # type: ignore[method-assign]

    @property
    def state(self) -> VehicleState:
        """The state after the last step (built from the backend when first asked for)."""
        st = self._state
        if st is None or self._state_steps != self.steps:
            st = self._state = self.backend.state
            self._state_steps = self.steps
        return st

    def pose_values(self) -> tuple[float, ...]:
        """(x, y, z (m), qw, qx, qy, qz) now as plain floats: what a tracker needs (the backend's own
        reader where it has one, see ``__init__``)."""
        st = self.state
        return (*st.pos_m.tolist(), *st.quat_wxyz.tolist())

    def state_vector(self) -> np.ndarray:
        """The state now as one flat float64 copy (`VehicleState.to_vector` layout; the backend's own
        reader where it has one, see ``__init__``)."""
        return self.state.to_vector()

    @property
    def time_s(self) -> float:
        st = self._state
        return self.backend.time_s if st is None or self._state_steps != self.steps else st.time_s

    def invalidate_state(self) -> None:
        """The backend was stepped or changed behind this object's back: rebuild on demand (a stepper
        that adds the steps it took to ``steps`` needs no call)."""
        self._state = None

    @property
    def dt_s(self) -> float:
        return self.backend.dt_s

    def compile_kernels(self) -> None:
        """Compile the numba kernels of this vehicle's own steps (the FC's inner loop and its hold
        controller, the native physics step), or load them from numba's cache, now rather than at their
        first use, with the argument types that use will have: on a fresh install a real-time loop would
        otherwise stall for seconds in flight the first time the FC arms. Changes no state."""
        st, fc = self.state, self.fc
        inner = fc.inner
        control(st.quat_wxyz, st.omega_rad_s, 0.0, 0.0, 0.0, 0.0, inner.params, inner.mix_inv, np.zeros(4))
        hold_command(0.0, 0.0, 0.0, 0.0, 0.0, fc.hold_params, 0.0, 0.0)
        body_landed(0.0, 0.0, 0.0, 0.0)
        limit_tilt(0.0, 0.0, 1.0)
        attitude_thrust_values(0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0)  # (a setpoint's intake)
        yaw_fields(0, 0.0, 1.0)
        if isinstance(self.backend, NativeBackend):
            self.backend.step(np.zeros(4), 0)  # (no step: the state stays as it is)

    def step(self, n_steps: int = 1) -> None:
        """Run ``n_steps`` physics steps, the FC deciding the throttles before each."""
        if self.motor_path is not None:
            self.motor_path.step(n_steps)
            return
        backend, fc = self.backend, self.fc
        for _ in range(n_steps):
            backend.step(fc.update(self.state), 1)
            self._state = backend.state
        self.steps = self._state_steps = self.steps + n_steps

    def step_to(self, time_s: float) -> int:
        """Step until simulated time reaches ``time_s`` (to the step below); returns the steps taken."""
        n = math.floor((time_s - self.time_s) / self.backend.dt_s + 1e-6)
        if n > 0:
            self.step(n)
        return max(n, 0)

    def close(self) -> None:
        self.backend.close()
