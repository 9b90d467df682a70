"""The harness's pre-flight check: a gap whose opening the flown vehicle's body box cannot pass (at the
attitude it reaches there, `policies.gap_planning.passage`: the one computation the onboard planner
refuses by too) is refused before take-off, with the reason, and never flown into the wall. It is judged
at the crossing speed asked for, then at the speed the onboard planner would fly from the start (the
plan it makes before taking off): a steep gap is often flown faster than asked, where the attitude error
is larger."""

from __future__ import annotations

import dataclasses
import math
from html import escape
from pathlib import Path
from typing import Any

from emulator.profile import VehicleProfile
from hil.report import write_summary
from hil.runner.checks import Check, Observations, register_check
from hil.runner.onboard_side import DEFAULT_APPROACH_SPEED_M_S
from hil.scenario.schema import Expectations, Scenario
from policies.gap_planning import BodyClearance, GapPose, PassageError, passage
from policies.onboard import ProgramConfig
from policies.onboard.program import pre_takeoff_check

REFUSED_END = "refused before take-off"


def refusal(s: Scenario, profile: VehicleProfile, config: ProgramConfig | None = None) -> str | None:
    """Why ``profile`` (the flown vehicle: its box, its tilt limit) cannot pass ``s``'s true opening at
    the scenario's crossing speed, or, given the onboard program's ``config``, at the speed of the plan
    it would make from the scenario's start (with the flown body box); None when it can."""
    speed = s.approach.speed_m_s or DEFAULT_APPROACH_SPEED_M_S
    why = passage(s.gap.width_m, s.gap.height_m, math.radians(s.gap.tilt_deg), speed,
                  BodyClearance(profile.body_box_m), math.radians(profile.max_tilt_deg)).refusal
    if why is not None or config is None:
        return why
    g = s.gap
    gap = GapPose.from_deg(g.centre_m, g.roll_deg, g.pitch_deg, g.yaw_deg, width_m=g.width_m,
                           height_m=g.height_m)
    flown = dataclasses.replace(config, body_box_m=tuple(profile.body_box_m))
    try:
        pre_takeoff_check(flown, s.initial.pos_m, gap)
    except PassageError as exc:
        return str(exc)
    except ValueError:  # (a PlanningError of another kind: the onboard program's to report, on the ground)
        return None
    return None


def preflight_check(refusal_expected: bool, reason: str | None) -> Check:
    """The pre-flight check's verdict: whether the run was refused before take-off (``reason``, None: it
    was accepted and flown) as the scenario expects (``expect.refused``)."""
    observed = "accepted, flown" if reason is None else f"refused: {reason}"
    if refusal_expected:
        return Check("preflight", reason is not None, REFUSED_END, observed, 0.0)
    return Check("preflight", reason is None, "a gap the vehicle can pass", observed, 0.0)


@register_check("preflight", expect="refused",
                doc="the run was refused before take-off, or flown, as `refused` expects (a gap too small "
                    "for the vehicle's body box at the attitude it reaches there is refused and flies "
                    "nothing; listed in refused runs and in flown runs that expected a refusal)")
def _preflight(e: Expectations, obs: Observations) -> list[Check]:
    """A flown run was accepted before take-off: a failure where the scenario expected a refusal (a run
    that passed needs no line for it; a refused run is judged by `preflight_check` alone)."""
    return [preflight_check(True, None)] if e.refused else []


def refused_summary(s: Scenario, check: Check, reason: str | None) -> dict[str, Any]:
    """A run that never took off: its verdict, the pre-flight check, why, and the scenario."""
    return {
        "passed": check.passed, "scenario_id": s.id, "refused": reason, "end_reason": REFUSED_END,
        "checks": [check.to_dict()], "crossed_gap": False, "collision": None, "min_clearance_m": None,
        "attitude_error_deg": None, "sim_time_s": 0.0, "wall_time_s": 0.0, "real_time_factor": None,
        "events": [{"time_s": 0.0, "source": "harness", "text": f"preflight: {check.observed}"}],
        "scenario": s.to_dict(),
    }


def write_refused(out: Path, summary: dict[str, Any]) -> None:
    """summary.json and a one-screen report.html of a run that never took off."""
    write_summary(out, summary)
    check = summary["checks"][0]
    word = "PASSED" if summary["passed"] else "REFUSED"
    (out / "report.html").write_text(
        f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{word}: '
        f"{escape(summary['scenario_id'])}</title></head><body><h1>{word}: {escape(summary['scenario_id'])}"
        f"</h1><p>{REFUSED_END}: nothing was flown.</p><p>preflight: expected "
        f"{escape(str(check['expected']))}, observed {escape(str(check['observed']))}</p></body></html>\n",
        encoding="utf-8")
