"""What the onboard side of a run reports for its summary and checks, read from its event log: its
abort, the hover point its plan names, whether it kept lockstep, its closing counters, its exit code."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

SUMMARY_EVENT = "summary"  # the onboard program's closing event: its counters


@dataclass(frozen=True)
class OnboardReport:
    """The onboard program's figures of one run (times in sim s)."""

    events: tuple[dict[str, Any], ...]  # its mission events, as logged
    exit_code: int | None
    abort_s: float | None  # its first abort of the crossing
    abort_reason: str | None  # that abort's reason, with the program's detail
    hover_point_m: Any  # the hover point its plan names (as logged), None without a plan
    lockstep_lost_s: float | None  # the first tick it read short of the mocap announced
    short_reads: int  # how many tick reads came up short
    counters: dict[str, Any] | None  # its closing "summary" event's counters; None when it wrote none
    flies: Any  # what computed each segment's commands, from its "start" event

    @classmethod
    def from_events(cls, events: list[dict[str, Any]], exit_code: int | None) -> OnboardReport:
        def first(name: str) -> dict[str, Any] | None:
            return next((ev for ev in events if ev.get("event") == name), None)

        abort, plan, start = first("abort"), first("plan"), first("start")
        lost = [ev for ev in events if ev.get("event") == "lockstep_lost"]
        summaries = [ev for ev in events if ev.get("event") == SUMMARY_EVENT]
        return cls(
            events=tuple(events),
            exit_code=exit_code,
            abort_s=float(abort["t_s"]) if abort else None,
            abort_reason=abort_reason(abort) if abort else None,
            hover_point_m=plan.get("hover_m") if plan else None,
            lockstep_lost_s=float(lost[0]["t_s"]) if lost else None,
            short_reads=max((int(ev.get("short_reads", 1)) for ev in lost), default=0),
            counters=None if not summaries else {k: v for k, v in summaries[-1].items()
                                                 if k not in ("event", "t_s")},
            flies=None if start is None else start.get("flies"),
        )

    def report_events(self) -> list[dict[str, Any]]:
        """Its events as the report's events (its closing counters left out)."""
        return [{"time_s": ev.get("t_s"), "source": "onboard", "text": _event_text(ev)}
                for ev in self.events if ev.get("event") != SUMMARY_EVENT]


def abort_reason(ev: dict[str, Any]) -> str:
    """An onboard "abort" event's reason, with the detail the program gave (the planner's, for a plan
    that failed): ``planning_failed (no feasible ...)``."""
    detail = ev.get("detail")
    return str(ev.get("reason", "no reason given")) + (f" ({detail})" if detail else "")


def _event_text(ev: dict[str, Any]) -> str:
    name = str(ev.get("event", "?"))
    if name == "abort":
        return f"abort: {abort_reason(ev)}"
    extra = {k: v for k, v in ev.items() if k not in ("event", "t_s")}
    for key in ("segment", "reason"):
        if key in extra:
            return f"{name}: {extra[key]}"
    return name
