"""The onboard program's vehicle configuration: what the onboard software is told about its airframe
(mass, the N3's thrust scale, the tilt limit, the FC's attitude lag), read from its own YAML file.

Built-in files are ``policies/vehicles/NAME.yaml``; any other is given by path. A new airframe needs
one beside its emulator profile (the harness looks for ``PROFILE.onboard.yaml`` next to a profile
file): the onboard side never reads the emulator's profile, as the real onboard computer cannot.
"""

from __future__ import annotations

import functools
import math
from dataclasses import MISSING, dataclass, fields
from importlib import resources
from pathlib import Path

import yaml

from policies.frames import GRAVITY_M_S2
from policies.gap_planning import VehicleLimits

DEFAULT_VEHICLE = "n3_tx2"
#: the traverse's least start distance before the gap plane (m) unless a vehicle's file says otherwise:
#: the n3_tx2's (its FC finishes most of the roll into the gap's tilt before its 0.52 m body reaches the wall)
TRAVERSE_LEAD_M = 0.25


@dataclass(frozen=True)
class OnboardVehicle:
    """The airframe as the onboard program knows it (SI units)."""

    name: str
    mass_kg: float
    full_thrust_n: float  # total thrust at N3 vertical command 100 %
    max_tilt_deg: float  # the expert's tilt limit (the FC's own limit or less)
    control_lead_s: float  # commands are computed this far ahead: the FC's attitude lag
    body_box_m: tuple[float, float, float]  # the collision box the plans keep clear (length, width, height)
    #: the traverse starts at least this far before the gap plane (m): far enough for the FC to finish
    #: the roll into the gap's tilt before the body reaches the wall (optional, `TRAVERSE_LEAD_M`)
    traverse_lead_m: float = TRAVERSE_LEAD_M
    #: the body rate its FC turns it at, at most (rad/s): the planner prefers plans within it (optional,
    #: the planner's own limit for any vehicle, `VehicleLimits`)
    max_body_rate_rad_s: float = VehicleLimits.max_body_rate_rad_s

    def __post_init__(self) -> None:
        for name in ("mass_kg", "full_thrust_n", "max_tilt_deg"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and v > 0):
                raise ValueError(f"vehicle {self.name}: {name} must be a positive number, got {v!r}")
        if not 0 < self.max_tilt_deg < 90:
            raise ValueError(f"vehicle {self.name}: max_tilt_deg must be in (0, 90), got {self.max_tilt_deg}")
        w = self.max_body_rate_rad_s
        if isinstance(w, bool) or not isinstance(w, int | float) or not (math.isfinite(w) and w > 0):
            raise ValueError(f"vehicle {self.name}: max_body_rate_rad_s must be a positive number, got {w!r}")
        tl = self.traverse_lead_m
        if isinstance(tl, bool) or not isinstance(tl, int | float) or not (0 < tl <= 1.0):
            raise ValueError(f"vehicle {self.name}: traverse_lead_m must be in (0, 1] m, got {tl!r}")
        lead = self.control_lead_s
        if isinstance(lead, bool) or not isinstance(lead, int | float) or not (0 <= lead <= 0.2):
            raise ValueError(f"vehicle {self.name}: control_lead_s must be in [0, 0.2] s, got {lead!r}")
        box = self.body_box_m
        if not (isinstance(box, tuple) and len(box) == 3
                and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                        for v in box)):
            raise ValueError(f"vehicle {self.name}: body_box_m must be 3 positive lengths (m), got {box!r}")
        if self.mass_kg * GRAVITY_M_S2 >= self.full_thrust_n:
            raise ValueError(
                f"vehicle {self.name}: full_thrust_n {self.full_thrust_n} N cannot hold {self.mass_kg} kg"
            )


def vehicle_names() -> list[str]:
    """Names of the built-in onboard vehicle configurations."""
    folder = resources.files("policies") / "vehicles"
    return sorted(p.name[: -len(".yaml")] for p in folder.iterdir() if p.name.endswith(".yaml"))


def load_vehicle(name_or_path: str | Path) -> OnboardVehicle:
    """A built-in configuration by name, or a YAML file by path; ValueError naming the file and field."""
    path = Path(name_or_path)
    if not path.suffix:
        f = resources.files("policies") / "vehicles" / f"{name_or_path}.yaml"
        if not f.is_file():
            have = ", ".join(vehicle_names())
            raise ValueError(f"no onboard vehicle configuration {str(name_or_path)!r} (built-in: {have})")
        text, source = f.read_text(), f"{name_or_path}.yaml"
    else:
        try:
            text, source = path.read_text(), str(path)
        except OSError as exc:
            raise ValueError(f"onboard vehicle configuration {path}: cannot read: {exc.strerror}") from None
    return _vehicle_from_text(text, source)


@functools.lru_cache(maxsize=64)
def _vehicle_from_text(text: str, source: str) -> OnboardVehicle:
    """The configuration a file's text describes, parsed once per process for the same text (an edited
    file is new text, parsed again)."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{source}: not valid YAML: {exc}") from None
    known = [f.name for f in fields(OnboardVehicle)]
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a mapping of field: value ({', '.join(known)})")
    unknown = sorted(set(data) - set(known))
    missing = [f.name for f in fields(OnboardVehicle) if f.name not in data and f.default is MISSING]
    if unknown or missing:
        raise ValueError(
            f"{source}: unknown fields {unknown}, missing fields {missing} (fields: {', '.join(known)})"
        )
    if isinstance(data.get("body_box_m"), list):
        data["body_box_m"] = tuple(data["body_box_m"])
    try:
        return OnboardVehicle(**data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: {exc}") from None
