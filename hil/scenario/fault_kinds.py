"""The kinds of fault a scenario can schedule: one small class per kind (its parameters, where it acts,
how it acts), registered by name in `FAULT_KINDS`. The loader, the runner and the format document's
fault table all read this one registry; a new kind is a class here (or anywhere) registered with
`register_fault_kind` (docs/extending.md).

A kind acts in one of three places (``acts_on``), where the runner calls it:
- ``"link"``: on each frame as it crosses the link its parameters name (`FaultKind.link_of`), from the
  emulator's sending end of the mocap link or either end of the command wire (`FaultKind.on_frame`);
- ``"onboard"``: on the onboard program's process, which it kills or stalls (``onboard_effect``);
- ``"emulator"``: on the flight-controller side's models each time a fault starts or ends anywhere in
  the schedule (`FaultKind.switch`, through the emulator side's `FaultTarget` surface).
The runner makes one instance of each kind per run (a kind may keep that run's state on it).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import MISSING, dataclass
from typing import Any, ClassVar, Protocol

import numpy as np

from hil.scenario.spec import Vec3, spec

# `spec` wraps dataclasses.field (adding validation metadata), so calling it in defaults is intended.
# ruff: noqa: RUF009

LINK_NAMES = ("command", "mocap")
#: where a kind acts (see the module docstring)
FAULT_SITES = ("link", "onboard", "emulator")
ONBOARD_EFFECTS = ("kill", "stall")
AIR_DENSITY_KG_M3 = 1.225
#: drag area Cd * A of the airframe seen by a wind (m^2): a 0.45 m quad with props, about 0.05
WIND_DRAG_AREA_M2 = 0.05
#: a frame after a link's faults: the bytes (None: dropped) and how many of them were changed
FrameOut = tuple[bytes | None, int]


class FaultTarget(Protocol):
    """What an ``"emulator"`` fault acts on: the FC side of one run (`hil.runner.emulator_side`)."""

    esc: Any  # the DroneCAN ESC bus's stepper (`emulator.esc.bus.EscBusStepper`), None without one

    def set_wind(self, force_n: np.ndarray, moment_nm: np.ndarray) -> None:
        """An external force (N, world ENU) and moment (N m, body FLU) on the airframe from now on."""

    def freeze_mocap(self, frozen: bool) -> None:
        """Keep the mocap reporting the pose of now (True) or the vehicle's again (False)."""

    def fc_param(self, name: str) -> float | int:
        """The FC parameter ``name``'s value."""

    def set_fc_param(self, name: str, value: float | int, time_s: float, why: str) -> None:
        """Set an FC parameter as a ground station would; one the FC refuses is said on the link."""


class FaultKind:
    """One kind of fault; subclasses set the class attributes and the method of their ``acts_on``."""

    #: the kind's name in scenario files (``kind:``)
    name: ClassVar[str]
    #: its ``params:`` (a frozen dataclass of `spec` fields; `NoParams` for none)
    params: ClassVar[type]
    acts_on: ClassVar[str]
    #: an instant (written with ``at_s`` / ``at``, no end) instead of a window
    instant: ClassVar[bool] = False
    #: needs the motors on a DroneCAN ESC bus (``links.esc_bus``)
    needs_esc_bus: ClassVar[bool] = False
    #: ``"onboard"`` kinds: what happens to the onboard program (one of `ONBOARD_EFFECTS`)
    onboard_effect: ClassVar[str | None] = None
    #: the format document's fault table: the params column and the meaning column
    params_doc: ClassVar[str] = "none"
    doc: ClassVar[str]

    def link_of(self, params: Any) -> str | None:
        """``"link"`` kinds: the link (one of `LINK_NAMES`) whose frames a fault with ``params`` acts on."""
        return None

    def on_frame(self, active: Sequence[Any], data: bytes, rng: np.random.Generator) -> FrameOut:
        """``"link"`` kinds: the frame ``data`` as it leaves the faults ``active`` on its link now (None:
        dropped), and how many of its bytes were changed; ``rng`` is the link's own generator."""
        return data, 0

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        """``"emulator"`` kinds: set ``target`` as this kind's ``faults`` (all of them in the run, each
        active or not: `Fault.active`) say at ``time_s`` (s); called whenever any fault starts or ends."""

    @classmethod
    def table_row(cls) -> str:
        """The kind's row in docs/scenario-format.md's fault table."""
        return f"| `{cls.name}` | {cls.params_doc} | {cls.doc} |"


#: kind name -> class, in the order the runner applies them
FAULT_KINDS: dict[str, type[FaultKind]] = {}


def register_fault_kind(cls: type[FaultKind]) -> type[FaultKind]:
    """Add ``cls`` to `FAULT_KINDS` under ``cls.name`` (a class decorator); ValueError for a name taken
    or a class that does not say where it acts."""
    if cls.name in FAULT_KINDS:
        raise ValueError(f"fault kind {cls.name!r} is registered already")
    if cls.acts_on not in FAULT_SITES:
        raise ValueError(f"fault kind {cls.name!r}: acts_on must be one of {', '.join(FAULT_SITES)}, "
                         f"got {cls.acts_on!r}")
    if cls.acts_on == "onboard" and cls.onboard_effect not in ONBOARD_EFFECTS:
        raise ValueError(f"fault kind {cls.name!r}: onboard_effect must be one of "
                         f"{', '.join(ONBOARD_EFFECTS)}")
    FAULT_KINDS[cls.name] = cls
    return cls


@contextmanager
def fault_kind_registered(cls: type[FaultKind]) -> Iterator[type[FaultKind]]:
    """``cls`` registered for the block, unregistered after (a kind added by a test or a plugin)."""
    register_fault_kind(cls)
    try:
        yield cls
    finally:
        FAULT_KINDS.pop(cls.name, None)


def fault_kind(name: str) -> type[FaultKind]:
    """The registered kind ``name``; KeyError naming the known kinds otherwise."""
    try:
        return FAULT_KINDS[name]
    except KeyError:
        raise KeyError(f"unknown fault kind {name!r}; known: {', '.join(FAULT_KINDS)}") from None


@dataclass(frozen=True)
class NoParams:
    """A fault without parameters."""


@dataclass(frozen=True)
class CorruptBytesParams:
    """Flip bytes on one link."""

    link: str = spec(MISSING, choices=LINK_NAMES, doc="which link's bytes are corrupted")
    fraction: float = spec(MISSING, lo=0.0, hi=1.0, lo_open=True, doc="fraction of bytes corrupted")


@dataclass(frozen=True)
class WindGustParams:
    """A force on the vehicle (give exactly one of force_n and speed_m_s), and the moment about its
    vertical axis that a gust on an asymmetric airframe brings with it."""

    direction: Vec3 = spec(MISSING, lo=-1000.0, hi=1000.0, doc="world ENU direction (normalised on load)")
    force_n: float | None = spec(None, lo=0.0, hi=100.0, lo_open=True, doc="gust force")
    speed_m_s: float | None = spec(None, lo=0.0, hi=30.0, lo_open=True, doc="wind speed (drag model)")
    yaw_moment_nm: float = spec(
        0.0, lo=-1.0, hi=1.0, doc="the gust's moment about the body z axis (N m; + turns the nose left)"
    )


@dataclass(frozen=True)
class ParamSetParams:
    """Set one FC parameter (by its MAVLink name, `emulator.params`) while the fault acts; the value
    in force before comes back when it ends."""

    name: str = spec(MISSING, doc="the parameter's name, e.g. COM_OF_LOSS_T")
    value: float = spec(MISSING, lo=-1e9, hi=1e9, doc="its value, within the parameter's own range")


@dataclass(frozen=True)
class EscSilentParams:
    """One ESC stops answering and stops its motor (needs ``links.esc_bus``)."""

    esc: int = spec(MISSING, lo=0, hi=3, doc="the ESC's index (the FC's motor 0-3)")


@dataclass(frozen=True)
class CanFrameLossParams:
    """A fraction of the ESC bus's frames lost (needs ``links.esc_bus``)."""

    fraction: float = spec(MISSING, lo=0.0, hi=1.0, lo_open=True, doc="fraction of frames lost")


def corrupt(data: bytes, fraction: float, rng: np.random.Generator) -> tuple[bytes, int]:
    """``data`` with about ``fraction`` of its bytes each flipped in one random bit; (bytes, flipped)."""
    if fraction <= 0 or not data:
        return data, 0
    hit = rng.random(len(data)) < fraction
    n = int(hit.sum())
    if n == 0:
        return data, 0
    arr = np.frombuffer(data, dtype=np.uint8).copy()
    bits = rng.integers(0, 8, n)
    arr[hit] ^= (1 << bits).astype(np.uint8)
    return arr.tobytes(), n


def gust_force_n(params: WindGustParams) -> np.ndarray:
    """The force (N, world ENU) of a wind_gust's parameters: ``force_n`` along ``direction``, or the
    quadratic drag 0.5 rho CdA v^2 of a wind of ``speed_m_s`` (vehicle speed neglected)."""
    d = np.asarray(params.direction, dtype=float)
    norm = float(np.linalg.norm(d))
    if not math.isfinite(norm) or norm <= 0:
        raise ValueError(f"wind_gust direction must be a non-zero vector, got {params.direction}")
    if params.force_n is not None:
        magnitude = params.force_n
    elif params.speed_m_s is not None:
        magnitude = 0.5 * AIR_DENSITY_KG_M3 * WIND_DRAG_AREA_M2 * params.speed_m_s**2
    else:
        raise ValueError("wind_gust needs force_n or speed_m_s")
    return d / norm * magnitude


class _Drop(FaultKind):
    """A link fault that drops every frame on its link while it acts."""

    params = NoParams
    acts_on = "link"
    link: ClassVar[str]

    def link_of(self, params: Any) -> str | None:
        return self.link

    def on_frame(self, active: Sequence[Any], data: bytes, rng: np.random.Generator) -> FrameOut:
        return None, 0


@register_fault_kind
class CommandLinkDown(_Drop):
    name = "command_link_down"
    link = "command"
    doc = "the command link carries nothing, both ways"


@register_fault_kind
class MocapFrozen(FaultKind):
    name = "mocap_frozen"
    params = NoParams
    acts_on = "emulator"
    doc = "the mocap keeps sending its last frame (stale data, fresh timestamps)"

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        target.freeze_mocap(any(f.active(time_s) for f in faults))


@register_fault_kind
class MocapDropped(_Drop):
    name = "mocap_dropped"
    link = "mocap"
    doc = "the mocap sends nothing"


@register_fault_kind
class CorruptBytes(FaultKind):
    name = "corrupt_bytes"
    params = CorruptBytesParams
    acts_on = "link"
    params_doc = "`link`, `fraction`"
    doc = "bytes on one link are flipped at random"

    def link_of(self, params: Any) -> str | None:
        return params.link if isinstance(params, CorruptBytesParams) else None

    def on_frame(self, active: Sequence[Any], data: bytes, rng: np.random.Generator) -> FrameOut:
        return corrupt(data, max(f.params.fraction for f in active), rng)


@register_fault_kind
class OnboardKilled(FaultKind):
    name = "onboard_killed"
    params = NoParams
    acts_on = "onboard"
    onboard_effect = "kill"
    instant = True
    params_doc = "none; written with `at_s` instead of `start_s`/`end_s`"
    doc = "the onboard program is killed at `at_s` (an instant)"


@register_fault_kind
class OnboardStalled(FaultKind):
    name = "onboard_stalled"
    params = NoParams
    acts_on = "onboard"
    onboard_effect = "stall"
    doc = "the onboard program is frozen (stops reading and writing), then resumes"


@register_fault_kind
class WindGust(FaultKind):
    name = "wind_gust"
    params = WindGustParams
    acts_on = "emulator"
    params_doc = "`force_n` or `speed_m_s`, and `direction`"
    doc = "a wind gust on the vehicle"

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        force, moment = np.zeros(3), np.zeros(3)
        for f in faults:
            if f.active(time_s):
                force += gust_force_n(f.params)
                moment[2] += f.params.yaw_moment_nm
        target.set_wind(force, moment)


@register_fault_kind
class ParamSet(FaultKind):
    name = "param_set"
    params = ParamSetParams
    acts_on = "emulator"
    params_doc = "`name`, `value`"
    doc = ("an FC parameter set while the fault acts (the failsafe timeout changed in flight, say); the "
           "value in force before comes back at `end_s` (none: it stays)")

    def __init__(self) -> None:
        self._before: dict[int, float | int] = {}  # fault index -> the value it replaced

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        for i, f in enumerate(faults):
            p, on = f.params, f.active(time_s)
            if on and i not in self._before:
                self._before[i] = target.fc_param(p.name)
                target.set_fc_param(p.name, p.value, time_s, self.name)
            elif not on and i in self._before:
                target.set_fc_param(p.name, self._before.pop(i), time_s, self.name)


@register_fault_kind
class EscSilent(FaultKind):
    name = "esc_silent"
    params = EscSilentParams
    acts_on = "emulator"
    needs_esc_bus = True
    params_doc = "`esc`"
    doc = "ESC `esc` stops answering and stops its motor (needs `links.esc_bus`)"

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        if target.esc is None:
            return
        esc = target.esc.esc
        silent = {f.params.esc for f in faults if f.active(time_s)}
        for i in range(len(esc.config.esc_node_ids)):
            esc.set_silent(i, i in silent)


@register_fault_kind
class CanFrameLoss(FaultKind):
    name = "can_frame_loss"
    params = CanFrameLossParams
    acts_on = "emulator"
    needs_esc_bus = True
    params_doc = "`fraction`"
    doc = "that fraction of the ESC bus's frames is lost (the larger of it and `links.esc_bus.loss`)"

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        if target.esc is not None:
            target.esc.esc.bus.extra_loss = max((f.params.fraction for f in faults if f.active(time_s)),
                                                default=0.0)


@register_fault_kind
class CanBusOff(FaultKind):
    name = "can_bus_off"
    params = NoParams
    acts_on = "emulator"
    needs_esc_bus = True
    doc = ("the ESC bus carries nothing (the FC's controller bus-off); ESCs stop their motors 0.1 s after "
           "their last command")

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        if target.esc is not None:
            ends = [f.end_s or math.inf for f in faults if f.active(time_s)]
            target.esc.esc.bus.bus_off_until_s = max(ends, default=-math.inf)
