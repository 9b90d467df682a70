"""Physics backends behind one interface, selectable by name (`native`, `jsbsim`).

A backend integrates one vehicle's rigid body under four motor throttle commands u in [0, 1] (see
`emulator.profile` for the rotor layout and frames). Backends are looked up lazily so that an
optional engine (jsbsim) fails only for those who ask for it.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from emulator.physics.state import VehicleState
from emulator.profile import VehicleProfile
from hil.link.registry import Registry

DEFAULT_DT_S = 0.001  # 1 kHz


class PhysicsBackend(Protocol):
    """One vehicle stepped at a fixed ``dt_s``. Everything outside the backend steps it through this
    protocol; compiled callers that fuse per-step work with the native kernel (the FC's batched steps)
    use the native backends' own ``kernel_arrays`` and ``advance_clock``."""

    name: str
    profile: VehicleProfile
    dt_s: float

    def reset(self, state: VehicleState) -> None:
        """Put the vehicle in ``state`` (its time_s becomes the backend's clock)."""

    def step(self, motor_cmd: np.ndarray, n_steps: int = 1) -> None:
        """Hold throttle ``motor_cmd`` (4,) in [0, 1] for ``n_steps`` steps of ``dt_s``."""

    def set_external_force(self, force_world_n: np.ndarray) -> None:
        """A disturbance force (wind gust) in world ENU (N), held until changed."""

    def set_external_torque(self, torque_body_nm: np.ndarray) -> None:
        """A disturbance torque (a gust's moment) in body FLU (N m), held until changed."""

    @property
    def time_s(self) -> float:
        """The backend's clock (s): the reset state's time plus the steps since."""

    @property
    def state(self) -> VehicleState:
        """The current state."""

    def close(self) -> None:
        """Release the engine; idempotent."""


#: the physics engines by name, each imported only when asked for
BACKENDS = Registry("physics backend", entries={"native": "emulator.physics.native:NativeBackend",
                                                "jsbsim": "emulator.physics.jsbsim_backend:JSBSimBackend"})


def backend_names() -> list[str]:
    """Names accepted by `make_backend`."""
    return BACKENDS.names()


def make_backend(name: str, profile: VehicleProfile, dt_s: float = DEFAULT_DT_S) -> PhysicsBackend:
    """Create a backend by name; a clear error for an unknown name or a missing optional engine."""
    try:
        backend = BACKENDS.load(name)
    except ImportError as exc:
        raise RuntimeError(
            f"physics backend '{name}' needs an optional dependency: {exc}. "
            "Install it with: pip install 'crossgap-hil[jsbsim]'"
        ) from exc
    return backend(profile, dt_s=dt_s)  # type: ignore[operator]
