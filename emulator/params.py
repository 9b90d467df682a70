"""The FC's parameters: one table (name, type, range, unit, where it applies, meaning) and the values in
force, read from and written to the parts that use them.

A parameter has PX4's name where PX4 has the setting, and the prefix ``N3_`` where it is this N3-style
FC's own. Its default is not written here: it is the default of the setting it stands for (an `FcConfig`
field, the vehicle profile's limit, the telemetry's `DEFAULT_INTERVALS_S`, an `EscBusConfig` field), so
`ParamDef.default` reads it from there. Values in force are read from the live objects at each request
(`Parameters.get`), so a change made any other way (SET_MESSAGE_INTERVAL, say) shows too.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from emulator.esc.config import EscBusConfig
from emulator.fc.flight_controller import FcConfig, FlightController
from emulator.servers.telemetry import DEFAULT_INTERVALS_S, MIN_INTERVAL_S
from hil.link.mavlink import mav

FLOAT, INT = "float", "int"
NAME_MAX_CHARS = 16  # MAVLink's param_id


class ParamError(ValueError):
    """A parameter refused: ``reason`` says why (short enough for a STATUSTEXT), ``kind`` is one of
    'unknown', 'type', 'range', 'invalid'."""

    def __init__(self, reason: str, kind: str) -> None:
        super().__init__(reason)
        self.reason, self.kind = reason, kind


@dataclass(frozen=True)
class ParamDef:
    """One parameter: ``applies`` says where it acts and ``key`` which setting there:
    ``fc`` (an `FcConfig` field, in flight from the next step), ``limit`` (a setpoint limit of the FC's
    vehicle profile, from the next setpoint), ``stream`` (the rate of the telemetry message with id
    ``key``, 0 Hz: off), ``esc`` (an `EscBusConfig` field of the ESC bus; kept for when one is on),
    ``link`` (the MAVLink link's data-rate budget, `emulator.servers.link_budget`)."""

    name: str
    kind: str  # FLOAT or INT (MAV_PARAM_TYPE_REAL32 / INT32 on the wire)
    lo: float
    hi: float
    unit: str
    applies: str
    key: str | int
    doc: str
    #: INT parameters that stand for a named setting: wire value -> the setting's value
    choices: tuple[tuple[int, Any], ...] = ()

    def check(self, value: Any) -> float | int:
        """``value`` as this parameter's type, or ParamError with the reason. A float parameter takes a
        value within its range as float32 carries it (0.8 travels as 0.800000012), clamped to the range."""
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ParamError(f"{self.name}: expected a number, got {value!r}", "type")
        if self.kind == INT:
            if not (math.isfinite(value) and value == int(value)):
                raise ParamError(f"{self.name}: expected an integer, got {value!r}", "type")
            value = int(value)
            if self.choices and value not in dict(self.choices):
                allowed = ", ".join(f"{k} {v}" for k, v in self.choices)
                raise ParamError(f"{self.name}: {value} not one of {allowed}", "range")
        elif not math.isfinite(value):
            raise ParamError(f"{self.name}: expected a finite number, got {value!r}", "range")
        else:
            value = float(value)
            if _float32(self.lo) <= value <= _float32(self.hi):
                value = min(max(value, self.lo), self.hi)
        if not self.lo <= value <= self.hi:
            raise ParamError(f"{self.name}: {value:g} outside {self.lo:g}..{self.hi:g} {self.unit}".rstrip(),
                             "range")
        return value

    def default(self, fc: FlightController | None) -> float | int:
        """The default of the setting this parameter stands for, on ``fc``'s vehicle (None: only for
        the parameters whose default does not depend on the vehicle)."""
        if self.applies == "fc":
            d = _FC_DEFAULTS[str(self.key)]
            if d is None:
                if fc is None:
                    raise ValueError(f"{self.name}: the default depends on the vehicle")
                d = fc.profile.hover_throttle
            return self._to_wire(d)
        if self.applies == "limit":
            if fc is None:
                raise ValueError(f"{self.name}: the default depends on the vehicle")
            return float(getattr(fc.base_profile, str(self.key)))
        if self.applies == "stream":
            interval = DEFAULT_INTERVALS_S.get(int(self.key))
            return 0.0 if interval is None else 1.0 / interval
        if self.applies == "link":
            return 0.0
        return self._to_wire(_ESC_DEFAULTS[str(self.key)])

    def _to_wire(self, value: Any) -> float | int:
        for wire, meant in self.choices:
            if meant == value:
                return wire
        return int(value) if self.kind == INT else float(value)

    def _from_wire(self, value: float | int) -> Any:
        return dict(self.choices)[int(value)] if self.choices else value


_F32 = struct.Struct("<f")


def _float32(x: float) -> float:
    """``x`` rounded to the nearest float32 (MAVLink's REAL32), as a float."""
    return _F32.unpack(_F32.pack(x))[0]


_FC_DEFAULTS = {f.name: f.default for f in fields(FcConfig)}
_ESC_DEFAULTS = {f.name: f.default for f in fields(EscBusConfig)}



def _rate(name: str, what: str) -> ParamDef:
    msg_id = getattr(mav, f"MAVLINK_MSG_ID_{what}")
    return ParamDef(name, FLOAT, 0.0, 1.0 / MIN_INTERVAL_S, "Hz", "stream", msg_id,
                    f"{what} telemetry rate (0: off)")


#: every parameter, in index order (PARAM_VALUE's param_index)
PARAMS: tuple[ParamDef, ...] = (
    ParamDef("COM_OF_LOSS_T", FLOAT, 0.1, 60.0, "s", "fc", "failsafe_timeout_s",
             "offboard setpoint silence before the failsafe"),
    ParamDef("COM_OBL_RC_ACT", INT, 4, 5, "", "fc", "failsafe_action",
             "failsafe action on setpoint loss: 4 land, 5 hold (hover N3_FS_HOVER_T, then land)",
             choices=((4, "land"), (5, "hover"))),
    ParamDef("COM_DISARM_LAND", FLOAT, 0.1, 20.0, "s", "fc", "auto_disarm_s",
             "on the ground this long after a landing: disarm"),
    ParamDef("MPC_TILTMAX_AIR", FLOAT, 5.0, 89.0, "deg", "fc", "hover_max_tilt_deg",
             "tilt limit of the FC's own hover and landing controller"),
    ParamDef("MPC_THR_HOVER", FLOAT, 0.1, 0.8, "norm", "fc", "hover_throttle",
             "hover throttle the FC's own hover controller assumes (default: the vehicle's)"),
    ParamDef("MPC_LAND_SPEED", FLOAT, 0.1, 3.0, "m/s", "fc", "land_speed_m_s", "descent rate when landing"),
    ParamDef("MC_YAWRATE_MAX", FLOAT, 1.0, 1800.0, "deg/s", "limit", "max_yaw_rate_deg_s",
             "largest yaw rate a setpoint may command (faster ones are clamped)"),
    ParamDef("N3_SP_TILT_MAX", FLOAT, 1.0, 89.0, "deg", "limit", "max_tilt_deg",
             "largest tilt an offboard setpoint may command (steeper ones are scaled back)"),
    ParamDef("N3_FS_HOVER_T", FLOAT, 0.1, 600.0, "s", "fc", "failsafe_hover_s",
             "failsafe hover this long before landing"),
    ParamDef("N3_OF_MIN_RATE", FLOAT, 0.5, 100.0, "Hz", "fc", "min_offboard_rate_hz",
             "setpoint stream rate needed before OFFBOARD is granted"),
    _rate("N3_RATE_HB", "HEARTBEAT"),
    _rate("N3_RATE_ATT", "ATTITUDE"),
    _rate("N3_RATE_ATT_Q", "ATTITUDE_QUATERNION"),
    _rate("N3_RATE_LPOS", "LOCAL_POSITION_NED"),
    _rate("N3_RATE_GPOS", "GLOBAL_POSITION_INT"),
    _rate("N3_RATE_IMU", "HIGHRES_IMU"),
    _rate("N3_RATE_SYS", "SYS_STATUS"),
    _rate("N3_RATE_BAT", "BATTERY_STATUS"),
    _rate("N3_RATE_EXT", "EXTENDED_SYS_STATE"),
    ParamDef("N3_ESC_TOUT", FLOAT, 0.01, 10.0, "s", "esc", "status_timeout_s",
             "ESC bus: an ESC without esc.Status this long is reported failed"),
    ParamDef("N3_ESC_FS_ACT", INT, 0, 2, "", "esc", "failsafe_action",
             "ESC bus, an ESC failed: 0 report only, 1 land, 2 disarm",
             choices=((0, "report"), (1, "land"), (2, "disarm"))),
    ParamDef("MAV_0_RATE", FLOAT, 0.0, 1e6, "B/s", "link", "rate_bytes_s",
             "telemetry streams' data-rate budget, scaled down to fit (0: half a serial line, none else)"),
)
BY_NAME: dict[str, int] = {p.name: i for i, p in enumerate(PARAMS)}
assert all(len(p.name) <= NAME_MAX_CHARS for p in PARAMS)


def param_def(name: str) -> ParamDef:
    """The parameter called ``name``; ParamError (kind 'unknown', with the nearest names) if none."""
    i = BY_NAME.get(name)
    if i is None:
        import difflib

        near = difflib.get_close_matches(name, BY_NAME, n=1)
        hint = f" (did you mean {near[0]}?)" if near else ""
        raise ParamError(f"unknown parameter {name!r}{hint}", "unknown")
    return PARAMS[i]


def describe(fc: FlightController | None = None) -> list[str]:
    """The table as Markdown rows (name, type, range, unit, default, applies to, meaning); defaults that
    depend on the vehicle read "vehicle" without ``fc``."""
    rows = ["| name | type | range | unit | default | applies to | meaning |", "|---" * 7 + "|"]
    where = {"fc": "FC, next step", "limit": "FC, next setpoint", "stream": "telemetry, at once",
             "esc": "ESC bus, at once", "link": "telemetry, at once"}
    for p in PARAMS:
        if fc is None and (p.applies == "limit" or (p.applies == "fc" and _FC_DEFAULTS[str(p.key)] is None)):
            default = "vehicle"
        else:
            default = f"{p.default(fc):g}"
        span = ", ".join(str(k) for k, _ in p.choices) if p.choices else f"{p.lo:g}..{p.hi:g}"
        rows.append(f"| `{p.name}` | {'int32' if p.kind == INT else 'float'} | {span} | {p.unit} | {default} "
                    f"| {where[p.applies]} | {p.doc} |")
    return rows


def check_values(values: Mapping[str, Any]) -> dict[str, float | int]:
    """``values`` (name -> value) checked against the table; ParamError naming the first bad one."""
    return {name: param_def(str(name)).check(v) for name, v in values.items()}


class Parameters:
    """The parameters of one FC, its MAVLink server's streams and its ESC bus."""

    def __init__(self, fc: FlightController, streams: Any) -> None:
        """``streams``: has ``stream_rate_hz(msg_id)``, ``set_stream_rate(msg_id, hz)``,
        ``link_rate_bytes_s()`` and ``set_link_rate(bytes_s)``, or None on a
        link without MAVLink telemetry (the rates then refuse to be set); ``esc`` (set
        when an ESC bus is on): has ``config`` and ``reconfigure(**changes)``."""
        self.fc, self.streams = fc, streams
        self.esc: Any = None
        self._esc_values: dict[str, Any] = {}  # ESC settings set while no bus is on
        #: called with (name, value in force) after every accepted change
        self.on_change: Callable[[str, float | int], None] | None = None

    def __len__(self) -> int:
        return len(PARAMS)

    def get(self, name: str) -> float | int:
        """The value in force of ``name`` (ParamError if unknown)."""
        return self._get(param_def(name))

    def _get(self, p: ParamDef) -> float | int:
        key = str(p.key)
        if p.applies == "fc":
            v = getattr(self.fc.config, key)
            return p._to_wire(self.fc.profile.hover_throttle if v is None else v)
        if p.applies == "limit":
            return float(getattr(self.fc.profile, key))
        if p.applies == "stream":
            if self.streams is None:  # a link without MAVLink telemetry: the rate nobody sends at
                return p._to_wire(p.default(self.fc))
            return float(self.streams.stream_rate_hz(int(p.key)))
        if p.applies == "link":
            return 0.0 if self.streams is None else float(self.streams.link_rate_bytes_s())
        if self.esc is not None:
            return p._to_wire(getattr(self.esc.config, key))
        return self._esc_values.get(key, p.default(self.fc))

    def items(self) -> Iterable[tuple[int, ParamDef, float | int]]:
        """(index, definition, value in force) of every parameter."""
        for i, p in enumerate(PARAMS):
            yield i, p, self._get(p)

    def set(self, name: str, value: Any) -> float | int:
        """Set ``name`` to ``value`` (checked: ParamError with the reason, nothing changed); returns the
        value in force."""
        p = param_def(name)
        v = p.check(value)
        meant, key = p._from_wire(v), str(p.key)
        try:
            if p.applies in ("stream", "link") and self.streams is None:
                raise ParamError(f"{name}: a MAVLink telemetry setting, and this link has no MAVLink "
                                 "telemetry", "invalid")
            if p.applies == "fc":
                self.fc.reconfigure(**{key: meant})
            elif p.applies == "limit":
                self.fc.set_limits(**{key: meant})
            elif p.applies == "stream":
                self.streams.set_stream_rate(int(p.key), meant)
            elif p.applies == "link":
                self.streams.set_link_rate(meant)
            elif self.esc is not None:
                self.esc.reconfigure(**{key: meant})
            else:
                self._esc_values[key] = v
        except ValueError as exc:  # the setting's own validation (a combination it refuses)
            raise ParamError(f"{name}: {exc}", "invalid") from None
        now = self._get(p)
        if self.on_change is not None:
            self.on_change(name, now)
        return now

    def esc_settings(self) -> dict[str, Any]:
        """The ESC bus settings these parameters hold (`EscBusConfig` fields), for a bus built now."""
        return {str(p.key): p._from_wire(self._get(p)) for p in PARAMS if p.applies == "esc"}

    def set_many(self, values: Mapping[str, Any]) -> None:
        """Set several (all checked first: ParamError naming the first bad one, nothing changed)."""
        checked = check_values(values)
        for name, v in checked.items():
            self.set(name, v)

    def reset(self) -> None:
        """Every parameter back to its default."""
        for _, p, _ in list(self.items()):
            self.set(p.name, p.default(self.fc))

    # --- files -------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write every value in force to ``path`` (MAVProxy's ``param save`` format: NAME VALUE)."""
        lines = ["# crossgap-hil N3-style FC parameters (NAME VALUE)"]
        for _, p, v in self.items():
            lines.append(f"{p.name:<16} {v:d}" if p.kind == INT else f"{p.name:<16} {v:.9g}")
        Path(path).write_text("\n".join(lines) + "\n")


def read_param_file(path: str | Path) -> dict[str, float | int]:
    """Parameters from a file: MAVProxy's ``NAME VALUE`` lines or QGroundControl's tab-separated
    ``SYS COMP NAME VALUE TYPE`` lines, ``#`` comments; checked against the table. ValueError naming
    the file and line of the first mistake (OSError when it cannot be read)."""
    text = Path(path).read_text()
    out: dict[str, float | int] = {}
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) == 5:  # QGroundControl: vehicle id, component id, name, value, type
            parts = parts[2:4]
        if len(parts) != 2:
            raise ValueError(f"{path}:{n}: expected 'NAME VALUE', got {raw.strip()!r}")
        name, text_value = parts
        try:
            value: float | int = int(text_value) if text_value.lstrip("+-").isdigit() else float(text_value)
        except ValueError:
            raise ValueError(f"{path}:{n}: {name}: expected a number, got {text_value!r}") from None
        try:
            out[name] = param_def(name).check(value)
        except ParamError as exc:
            raise ValueError(f"{path}:{n}: {exc.reason}") from None
    return out
