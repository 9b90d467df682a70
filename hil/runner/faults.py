"""Fault injection for a run: the scenario's fault schedule queried by sim time, byte corruption, and
the wind gust's force and moment.

Faults act where they act on the bench: in the links (bytes dropped or flipped, mocap frozen or
dropped), in the onboard process (killed, stalled) and on the airframe (a gust as an external force,
with a yaw moment if given).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from hil.scenario.schema import CorruptBytesParams, EventTime, Fault, WindGustParams

AIR_DENSITY_KG_M3 = 1.225
#: drag area Cd * A of the airframe seen by a wind (m^2): a 0.45 m quad with props, about 0.05
WIND_DRAG_AREA_M2 = 0.05


class FaultSchedule:
    """The faults of one run, queried by sim time (s)."""

    def __init__(self, faults: Iterable[Fault]) -> None:
        #: as given; a fault timed after a mission event is replaced by its timed form when the event
        #: comes (`at_event`), and stays as given (never active) if it never does
        self.faults = tuple(faults)
        #: mission event -> indices of the faults still waiting for it
        self.waiting: dict[str, list[int]] = {}
        for i, f in enumerate(self.faults):
            if f.after is not None:
                self.waiting.setdefault(f.after.after, []).append(i)
        self.kill_s = self.killed_at_s()
        #: whether any fault acts on the mocap link / the command link (the per-frame paths skip the
        #: schedule when none does)
        self.has_mocap_faults = any(self._on_link(f, "mocap", "mocap_dropped") for f in self.faults)
        self.has_command_faults = any(self._on_link(f, "command", "command_link_down") for f in self.faults)
        self.has_param_faults = any(f.kind == "param_set" for f in self.faults)

    @staticmethod
    def _on_link(f: Fault, link: str, drop_kind: str) -> bool:
        if f.kind == drop_kind:
            return True
        p = f.params
        return f.kind == "corrupt_bytes" and isinstance(p, CorruptBytesParams) and p.link == link

    def count_from(self, name: str) -> None:
        """Make every fault given in sim seconds count from the event ``name`` instead (real time: from
        the onboard program's first contact, as its start-up takes wall time that lockstep does not)."""
        faults = list(self.faults)
        for i, f in enumerate(faults):
            if f.after is None:
                duration = None if f.end_s is None else f.end_s - f.start_s
                faults[i] = replace(f, start_s=math.inf, end_s=None, after=EventTime(name, f.start_s),
                                    duration_s=duration)
                self.waiting.setdefault(name, []).append(i)
        self.faults = tuple(faults)
        self.kill_s = self.killed_at_s()

    def at_event(self, name: str, event_s: float, now_s: float) -> bool:
        """The mission event ``name`` happened at ``event_s`` (sim s), seen at ``now_s``: time the faults
        waiting for it (the first time only); True if any was."""
        waiting = self.waiting.pop(name, None)
        if not waiting:
            return False
        faults = list(self.faults)
        for i in waiting:
            faults[i] = faults[i].at_event(event_s, now_s)
        self.faults = tuple(faults)
        self.kill_s = self.killed_at_s()
        return True

    def active(self, kind: str, time_s: float) -> list[Fault]:
        """Faults of ``kind`` acting at ``time_s``."""
        return [f for f in self.faults if f.kind == kind and f.active(time_s)]

    def any_active(self, kind: str, time_s: float) -> bool:
        return any(f.kind == kind and f.active(time_s) for f in self.faults)

    def boundaries_s(self) -> list[float]:
        """Every start and end time, sorted (where the loop must stop to switch a fault)."""
        times = {f.start_s for f in self.faults} | {f.end_s for f in self.faults if f.end_s is not None}
        return sorted(t for t in times if math.isfinite(t))

    def next_boundary_s(self, after_s: float) -> float:
        """The first start or end strictly after ``after_s`` (inf when none)."""
        for t in self.boundaries_s():
            if t > after_s + 1e-12:
                return t
        return math.inf

    def corrupt_fraction(self, link: str, time_s: float) -> float:
        """Fraction of bytes flipped on ``link`` ("command" or "mocap") at ``time_s`` (0 when none)."""
        frac = 0.0
        for f in self.active("corrupt_bytes", time_s):
            p = f.params
            if isinstance(p, CorruptBytesParams) and p.link == link:
                frac = max(frac, p.fraction)
        return frac

    def killed_at_s(self) -> float | None:
        """When the onboard program is killed (the earliest ``onboard_killed``), or None."""
        times = [f.start_s for f in self.faults if f.kind == "onboard_killed" and math.isfinite(f.start_s)]
        return min(times) if times else None

    def wind_force_n(self, time_s: float) -> np.ndarray:
        """The total gust force on the airframe at ``time_s`` (N, world ENU)."""
        total = np.zeros(3)
        for f in self.active("wind_gust", time_s):
            total += gust_force_n(f.params)
        return total

    def wind_torque_nm(self, time_s: float) -> np.ndarray:
        """The total gust moment on the airframe at ``time_s`` (N m, body FLU: about its z axis)."""
        total = np.zeros(3)
        for f in self.active("wind_gust", time_s):
            if isinstance(f.params, WindGustParams):
                total[2] += f.params.yaw_moment_nm
        return total

    def events(self) -> list[dict[str, object]]:
        """The schedule as report events (start and end of each fault)."""
        out: list[dict[str, object]] = []
        for f in self.faults:
            if not math.isfinite(f.start_s):
                assert f.after is not None
                text = f"{f.kind} never started: no {f.after.after!r} event came"  # (or no contact)
                out.append({"time_s": None, "source": "fault", "text": text})
                continue
            out.append({"time_s": f.start_s, "source": "fault", "text": f"{f.kind} starts"})
            if f.end_s is not None and f.kind != "onboard_killed":
                out.append({"time_s": f.end_s, "source": "fault", "text": f"{f.kind} ends"})
        return out


def gust_force_n(params: object) -> np.ndarray:
    """The force (N, world ENU) of a wind_gust's parameters: ``force_n`` along ``direction``, or the
    quadratic drag 0.5 rho CdA v^2 of a wind of ``speed_m_s`` (vehicle speed neglected)."""
    if not isinstance(params, WindGustParams):
        raise ValueError(f"wind_gust needs WindGustParams, got {type(params).__name__}")
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
