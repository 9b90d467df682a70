"""Vehicle profiles: a quadrotor's physical parameters, loaded from YAML and validated.

Conventions (shared by every physics backend and the flight controller):
- Body frame FLU (x forward, y left, z up); world frame ENU (z up).
- X configuration; rotor i sits at angle ``ROTOR_ANGLES_RAD[i]`` from body +x, at ``arm_length_m``.
  Rotor order follows PX4's quad-X: 0 front-right, 1 rear-left, 2 front-left, 3 rear-right.
- ``ROTOR_SPIN[i]`` is +1 for a rotor spinning counter-clockwise seen from above (its angular
  momentum points +z); its drag reaction torque on the body is ``-ROTOR_SPIN[i] * k_m * w^2`` about z.
- A rotor's thrust is ``thrust_coeff * w^2`` along body +z; motor commands are throttle fractions
  u in [0, 1] with the static map ``thrust = u * max_thrust_per_rotor_n`` (w_cmd = sqrt(u) * w_max).
"""

from __future__ import annotations

import functools
import math
from dataclasses import MISSING, dataclass, fields
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

ROTOR_ANGLES_RAD: tuple[float, ...] = (
    -math.pi / 4,  # 0 front-right
    3 * math.pi / 4,  # 1 rear-left
    math.pi / 4,  # 2 front-left
    -3 * math.pi / 4,  # 3 rear-right
)
ROTOR_SPIN: tuple[int, ...] = (1, 1, -1, -1)
GRAVITY_M_S2 = 9.80665


class ProfileError(ValueError):
    """A vehicle profile file is missing, malformed or out of range; names the file and field."""

    def __init__(self, source: str, field: str, message: str) -> None:
        super().__init__(f"{source}: field '{field}': {message}")
        self.source = source
        self.field = field


@dataclass(frozen=True)
class VehicleProfile:
    """A quadrotor's physical parameters in SI units (see the module docstring for frames)."""

    name: str
    mass_kg: float
    inertia_kgm2: tuple[float, float, float]  # principal moments Ixx, Iyy, Izz
    arm_length_m: float  # rotor centre to body centre
    thrust_coeff_n_s2: float  # k_f: rotor thrust = k_f * w^2 (N per (rad/s)^2)
    drag_torque_coeff_nm_s2: float  # k_m: rotor drag torque = k_m * w^2 (N m per (rad/s)^2)
    motor_time_constant_s: float  # first-order lag of rotor speed
    max_thrust_per_rotor_n: float
    linear_drag_n_s_m: tuple[float, float, float]  # body-frame linear drag, F = -c * v_body
    angular_drag_nm_s_rad: tuple[float, float, float]  # body-frame rotational damping
    body_box_m: tuple[float, float, float]  # collision box length (x), width (y), height (z)
    n3_full_thrust_n: float  # total thrust at N3 vertical command 100 %
    max_tilt_deg: float  # flight controller's roll/pitch limit
    max_body_rate_rad_s: float  # the inner loop's body-rate limit
    max_yaw_rate_deg_s: float = 150.0
    # the power train as the ESCs report it (esc.Status: `emulator.esc.kernels.esc_power`)
    battery_voltage_v: float = 15.2  # the pack's open-circuit voltage (a 4S lithium pack part-charged)
    battery_resistance_ohm: float = 0.05  # the pack's internal resistance, its wiring and connectors
    motor_efficiency: float = 0.7  # shaft power / electrical power drawn, motor and ESC together
    #: the inertia the FC's inner loop is tuned for, when it is not the airframe's (a mis-measured or
    #: stale tuning); None: the FC knows the airframe's inertia_kgm2
    fc_inertia_kgm2: tuple[float, float, float] | None = None
    source_notes: str = ""  # where the numbers come from
    # the FC's gains when a profile sets them (None: derived from the fields above, see emulator.fc.tuning)
    fc_attitude_p_per_s: tuple[float, float, float] | None = None  # rate cmd (rad/s) per rad, x y z
    fc_rate_p_per_s: tuple[float, float, float] | None = None  # angular accel (rad/s^2) per rad/s, x y z
    fc_hold_p_per_s: tuple[float, float] | None = None  # velocity hold: horizontal, vertical (1/s)

    # --- derived quantities -------------------------------------------------------------
    @property
    def fc_tuned_inertia_kgm2(self) -> tuple[float, float, float]:
        """The principal moments (kg m^2) the FC's inner loop believes in: ``fc_inertia_kgm2`` when
        given, else the airframe's ``inertia_kgm2`` (the physics always flies ``inertia_kgm2``)."""
        return self.inertia_kgm2 if self.fc_inertia_kgm2 is None else self.fc_inertia_kgm2

    @property
    def max_rotor_speed_rad_s(self) -> float:
        """Rotor speed at full throttle (rad/s)."""
        return math.sqrt(self.max_thrust_per_rotor_n / self.thrust_coeff_n_s2)

    @property
    def max_total_thrust_n(self) -> float:
        """All four rotors at full throttle (N)."""
        return 4.0 * self.max_thrust_per_rotor_n

    @property
    def hover_throttle(self) -> float:
        """Per-rotor throttle fraction that balances gravity (0..1)."""
        return self.mass_kg * GRAVITY_M_S2 / self.max_total_thrust_n

    def thrust_percent_to_force_n(self, percent: float) -> float:
        """N3 vertical thrust command (0..100 %) -> total thrust (N): thrust % = T / full_thrust."""
        return percent / 100.0 * self.n3_full_thrust_n

    def force_to_thrust_percent(self, force_n: float) -> float:
        """Total thrust (N) -> N3 vertical thrust command (%)."""
        return 100.0 * force_n / self.n3_full_thrust_n

    def with_changes(self, **changes: Any) -> VehicleProfile:
        """A copy with some fields replaced (validated again)."""
        data = {f.name: getattr(self, f.name) for f in fields(self)}
        data.update(changes)
        return _build(data, f"<{self.name} with changes>")


_VECTOR_FIELDS = {
    "inertia_kgm2": 3,
    "fc_inertia_kgm2": 3,
    "linear_drag_n_s_m": 3,
    "angular_drag_nm_s_rad": 3,
    "body_box_m": 3,
    "fc_attitude_p_per_s": 3,
    "fc_rate_p_per_s": 3,
    "fc_hold_p_per_s": 2,
}
_POSITIVE_FIELDS = {
    "mass_kg",
    "arm_length_m",
    "thrust_coeff_n_s2",
    "drag_torque_coeff_nm_s2",
    "motor_time_constant_s",
    "max_thrust_per_rotor_n",
    "n3_full_thrust_n",
    "max_tilt_deg",
    "max_body_rate_rad_s",
    "max_yaw_rate_deg_s",
    "battery_voltage_v",
    "battery_resistance_ohm",
    "motor_efficiency",
}


def _build(data: dict[str, Any], source: str) -> VehicleProfile:
    known = {f.name for f in fields(VehicleProfile)}
    for key in data:
        if key not in known:
            raise ProfileError(source, str(key), f"unknown field (known: {', '.join(sorted(known))})")
    values: dict[str, Any] = {}
    for f in fields(VehicleProfile):
        if f.name not in data:
            if f.default is not MISSING:
                continue
            raise ProfileError(source, f.name, "required field is missing")
        raw = data[f.name]
        if raw is None and f.default is None:  # an optional field left out
            continue
        if f.name in ("name", "source_notes"):
            if not isinstance(raw, str):
                raise ProfileError(source, f.name, f"expected a string, got {raw!r}")
            values[f.name] = raw
        elif f.name in _VECTOR_FIELDS:
            n = _VECTOR_FIELDS[f.name]
            if not isinstance(raw, list | tuple) or len(raw) != n:
                raise ProfileError(source, f.name, f"expected a list of {n} numbers, got {raw!r}")
            vec = tuple(_number(source, f.name, x) for x in raw)
            bound = 0.0 if "drag" in f.name else None
            for x in vec:
                if (bound is None and x <= 0) or (bound is not None and x < bound):
                    raise ProfileError(
                        source, f.name, f"expected {'>= 0' if bound is not None else '> 0'}, got {x}"
                    )
            values[f.name] = vec
        else:
            x = _number(source, f.name, raw)
            if f.name in _POSITIVE_FIELDS and x <= 0:
                raise ProfileError(source, f.name, f"expected a positive number, got {x}")
            values[f.name] = x
    if values["max_tilt_deg"] >= 90:
        raise ProfileError(source, "max_tilt_deg", f"expected < 90, got {values['max_tilt_deg']}")
    if values.get("motor_efficiency", 0.0) > 1.0:
        raise ProfileError(source, "motor_efficiency",
                           f"expected at most 1, got {values['motor_efficiency']}")
    profile = VehicleProfile(**values)
    if profile.hover_throttle >= 1.0:
        raise ProfileError(
            source, "max_thrust_per_rotor_n", f"the four rotors cannot lift {profile.mass_kg} kg"
        )
    return profile


def _number(source: str, field: str, raw: Any) -> float:
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        raise ProfileError(source, field, f"expected a number, got {raw!r}")
    x = float(raw)
    if not math.isfinite(x):
        raise ProfileError(source, field, f"expected a finite number, got {raw!r}")
    return x


def load_profile(path_or_name: str | Path) -> VehicleProfile:
    """Load a profile from a YAML file path, or by the name of a built-in profile (e.g. 'n3_tx2')."""
    path = Path(path_or_name)
    if not path.suffix:
        builtin = resources.files("emulator") / "profiles" / f"{path_or_name}.yaml"
        if not builtin.is_file():
            raise ProfileError(
                str(path_or_name), "name", f"no built-in profile (have: {', '.join(builtin_profiles())})"
            )
        text = builtin.read_text()
        source = f"{path_or_name}.yaml"
    else:
        try:
            text = path.read_text()
        except OSError as exc:
            raise ProfileError(str(path), "<file>", f"cannot read: {exc.strerror}") from exc
        source = str(path)
    return _profile_from_text(text, source)


@functools.lru_cache(maxsize=64)
def _profile_from_text(text: str, source: str) -> VehicleProfile:
    """The profile a file's text describes, parsed once per process for the same text (a suite loads
    the same few profiles run after run; an edited file is new text, parsed again)."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ProfileError(source, "<yaml>", f"not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ProfileError(source, "<root>", "expected a mapping of field: value")
    return _build(data, source)


def builtin_profiles() -> list[str]:
    """Names of the profiles shipped with the package."""
    folder = resources.files("emulator") / "profiles"
    return sorted(p.name[: -len(".yaml")] for p in folder.iterdir() if p.name.endswith(".yaml"))
