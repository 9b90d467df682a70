"""The fault schedule of a run: the scenario's faults queried by sim time, timed from mission events
as they come, and applied where each kind acts (`hil.scenario.fault_kinds`): to a link's frames, to the
onboard program's process, or to the emulator side's models when a fault switches.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from hil.scenario.fault_kinds import FAULT_KINDS, LINK_NAMES, FaultKind, FaultTarget, FrameOut
from hil.scenario.schema import EventTime, Fault


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
        #: one instance of every registered kind for this run (a kind may keep the run's state)
        self.kinds: dict[str, FaultKind] = {name: cls() for name, cls in FAULT_KINDS.items()}
        self._emulator_kinds = [k for k in self.kinds.values() if k.acts_on == "emulator"]
        #: link -> the kinds with a fault on it, in the registry's order (a dropped frame goes no further)
        self._link_kinds = {link: [k for k in self.kinds.values() if k.acts_on == "link" and any(
            f.kind == k.name and k.link_of(f.params) == link for f in self.faults)] for link in LINK_NAMES}
        #: whether any fault acts on the mocap link / the command link (the per-frame paths skip the
        #: schedule when none does)
        self.has_mocap_faults = bool(self._link_kinds["mocap"])
        self.has_command_faults = bool(self._link_kinds["command"])
        self._timed()

    def _timed(self) -> None:
        """Note what the faults as timed now do to the onboard program (after each retiming)."""
        #: when the onboard program is killed (`killed_at_s`), or None
        self.kill_s = self.killed_at_s()
        self._stalls = tuple(f for f in self.faults if self.kinds[f.kind].onboard_effect == "stall")
        #: whether any fault kills or stalls the onboard program (a loop skips `stalled` and `kill_s`
        #: when none does)
        self.acts_on_process = self.kill_s is not None or bool(self._stalls)

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
        self._timed()

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
        self._timed()
        return True

    def of_kind(self, kind: FaultKind) -> list[Fault]:
        """The faults of ``kind``, in the schedule's order."""
        return [f for f in self.faults if f.kind == kind.name]

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

    def on_frame(self, link: str, data: bytes, time_s: float, rng: np.random.Generator) -> FrameOut:
        """A frame crossing ``link`` (one of `LINK_NAMES`) at ``time_s`` with the faults acting on it
        then: (the frame, None when dropped; how many of its bytes the faults changed)."""
        changed = 0
        for kind in self._link_kinds[link]:
            active = [f for f in self.faults
                      if f.kind == kind.name and f.active(time_s) and kind.link_of(f.params) == link]
            if active:
                out, n = kind.on_frame(active, data, rng)
                changed += n
                if out is None:
                    return None, changed
                data = out
        return data, changed

    def switch(self, time_s: float, target: FaultTarget) -> None:
        """Set the emulator side as its faults say at ``time_s`` (a fault started or ended)."""
        for kind in self._emulator_kinds:
            kind.switch(self.of_kind(kind), time_s, target)

    def killed_at_s(self) -> float | None:
        """When the onboard program is killed (the earliest fault that kills it), or None."""
        times = [f.start_s for f in self.faults
                 if self.kinds[f.kind].onboard_effect == "kill" and math.isfinite(f.start_s)]
        return min(times) if times else None

    def stalled(self, time_s: float) -> bool:
        """Whether a fault holds the onboard program stalled at ``time_s``."""
        return any(f.active(time_s) for f in self._stalls)

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
            if f.end_s is not None and not f.instant:
                out.append({"time_s": f.end_s, "source": "fault", "text": f"{f.kind} ends"})
        return out
