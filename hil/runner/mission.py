"""The onboard program's mission events as the harness reads them (its JSON event log): the name of each
event a fault can be timed after, and the flight phases they delimit.

A segment event ({"event": "segment", "segment": "approach", ...}) is named by its segment; the others
by their event name ("takeoff", "plan", ...). The phases: takeoff from the "takeoff" event to the first
segment, then each segment to the next; the last ends with the mission ("mission_done"), an abort or the
end of the run.
"""

from __future__ import annotations

import math
from typing import Any

from hil.scenario.schema import FLIGHT_PHASES, MISSION_EVENTS

#: the harness's own event: the onboard program's first frame on the command link (what real-time runs
#: count the faults given in sim seconds from; see `hil.runner.realtime`)
CONTACT_EVENT = "contact"
#: events that end whatever phase is under way
_ENDS = ("mission_done", "abort", "done", "error", "fc_lost")


def event_name(ev: dict[str, Any]) -> str | None:
    """The mission event an onboard event is (one of `MISSION_EVENTS`, or `CONTACT_EVENT`), None for
    any other."""
    name = ev.get("event")
    if name == "segment":
        name = ev.get("segment")
    return name if name in MISSION_EVENTS or name == CONTACT_EVENT else None


def phase_intervals(events: list[dict[str, Any]], end_s: float) -> dict[str, list[tuple[float, float]]]:
    """Phase -> the sim intervals [start, end) (s) it was flown in, from the events in their order."""
    out: dict[str, list[tuple[float, float]]] = {p: [] for p in FLIGHT_PHASES}
    current: tuple[str, float] | None = None
    for ev in events:
        t = ev.get("t_s")
        if not isinstance(t, int | float) or not math.isfinite(t):
            continue
        name = event_name(ev)
        starts = name in FLIGHT_PHASES
        if (starts or ev.get("event") in _ENDS) and current is not None:
            out[current[0]].append((current[1], float(t)))
            current = None
        if starts:
            assert name is not None
            current = (name, float(t))
    if current is not None:
        out[current[0]].append((current[1], end_s))
    return out


def window_hits(start_s: float, end_s: float | None, intervals: list[tuple[float, float]],
                instant: bool = False) -> bool:
    """Whether a fault acting on [start_s, end_s) (s; end None: to the end of the run), or at the instant
    ``start_s``, overlaps any of ``intervals``."""
    if not math.isfinite(start_s):
        return False
    if instant:
        return any(a <= start_s < b for a, b in intervals)
    return any(start_s < b and (end_s is None or end_s > a) for a, b in intervals)
