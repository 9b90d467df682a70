"""A finished run folder as the live view's scene and frames (`hil view RUN_DIR`): the same page, with a
time slider, from summary.json, timeseries.npz and onboard_events.jsonl."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from emulator.profile import load_profile
from emulator.world import LabVolume, World
from hil.report.timeseries import read_timeseries
from hil.runner.emulator_side import flown_profile, make_gap
from hil.runner.recorder import FC_STATE_CODES
from hil.runner.run import ONBOARD_LOG_NAME
from hil.scenario import ScenarioError, loads_scenarios
from hil.scenario.schema import Scenario
from hil.view.live import TAKEOFF_PHASE, banner, phase_after, plan_points, scene

#: the replay's frames: one per this much sim time (s)
FRAME_STEP_S = 0.02
_FC_STATES = {code: name for name, code in FC_STATE_CODES.items()}
_FAILSAFE = {"failsafe_hover", "failsafe_land"}
_COMMAND = ("roll_cmd_deg", "pitch_cmd_deg", "yaw_cmd_deg", "thrust_cmd_pct")


class ReplayError(ValueError):
    """The folder is no finished run (the message says what is missing)."""


def _scenario(summary: dict[str, Any]) -> Scenario:
    doc = {k: v for k, v in summary["scenario"].items() if k not in Scenario.META_FIELDS}
    try:
        [s] = loads_scenarios(yaml.safe_dump(doc, sort_keys=False), source=str(summary.get("scenario_id")))
    except (ScenarioError, ValueError) as exc:
        raise ReplayError(f"the run's scenario does not load: {exc}") from exc
    return s


def load_replay(run_dir: str | Path) -> dict[str, Any]:
    """``{"scene": ..., "frames": [...]}`` of a finished run; ReplayError when it is none."""
    d = Path(run_dir)
    try:
        summary = json.loads((d / "summary.json").read_text(encoding="utf-8"))
        cols = None if summary.get("refused") else read_timeseries(d)
    except (OSError, ValueError, KeyError, AttributeError) as exc:
        raise ReplayError(f"{d} holds no finished run (summary.json and timeseries.npz): {exc}") from exc
    s = _scenario(summary)
    failed = failed_checks(summary)
    events = []
    log = d / ONBOARD_LOG_NAME
    if log.is_file():
        for line in log.read_text(encoding="utf-8").splitlines():
            try:
                events.append(json.loads(line))
            except ValueError:
                continue
    profile = flown_profile(load_profile(s.vehicle), s.airframe)
    world = World.for_profile(make_gap(s), LabVolume(s.lab.min_m, s.lab.max_m), profile)
    verdict = "PASSED" if summary.get("passed") else "REFUSED" if summary.get("refused") else "FAILED"
    sc = scene(world, profile.body_box_m, f"{summary.get('scenario_id')} ({verdict}, replay)",
               {"command": {"latency_ms": s.links.command.latency_ms, "loss": s.links.command.loss},
                "mocap": {"latency_ms": s.links.mocap.latency_ms, "loss": s.links.mocap.loss}},
               profile.max_total_thrust_n)
    plan = plan_points(events)
    if plan is not None:
        sc["plan_m"] = plan
    return {"scene": sc, "frames": [] if cols is None else frames(cols, summary, events), "verdict": verdict,
            "failed_checks": failed, "refused": summary.get("refused")}


def failed_checks(summary: dict[str, Any]) -> list[dict[str, Any]]:
    """The run's failed checks, each with its name, sim time (s; None: the whole run), expected and
    observed, in the order of the summary."""
    return [{"name": c.get("name"), "time_s": c.get("time_s"), "expected": str(c.get("expected")),
             "observed": str(c.get("observed"))}
            for c in summary.get("checks", []) if isinstance(c, dict) and not c.get("passed")]


def frames(cols: dict[str, np.ndarray], summary: dict[str, Any], events: list[dict[str, Any]],
           ) -> list[dict[str, Any]]:
    """The run's frames, one every `FRAME_STEP_S` of sim time, in the live view's form."""
    t = cols["t_s"]
    if len(t) == 0:
        return []
    idx = np.unique(np.searchsorted(t, np.arange(0.0, float(t[-1]) + FRAME_STEP_S, FRAME_STEP_S)))
    idx = idx[idx < len(t)]
    aborts = [ev for ev in events if ev.get("event") == "abort"]
    abort_s = float(aborts[0]["t_s"]) if aborts else None
    abort = str(aborts[0].get("reason", "?")) if aborts else None
    hit_s = summary.get("collision_time_s")
    texts = sorted(((float(ev["time_s"]), f"{ev['source']} {ev['text']}") for ev in summary.get("events", [])
                    if isinstance(ev.get("time_s"), int | float)), key=lambda e: e[0])
    faults = [(f["kind"], f["start_s"], f["end_s"]) for f in summary.get("faults", [])
              if f.get("start_s") is not None]
    fc_reason = ""
    out = []
    k = 0
    onboard = sorted((ev for ev in events if isinstance(ev.get("t_s"), int | float)), key=lambda e: e["t_s"])
    phase, j = TAKEOFF_PHASE, 0
    hit = None if hit_s is None else min(int(np.searchsorted(t, hit_s)), len(t) - 1)

    def num(a: np.ndarray, i: int, digits: int = 4) -> float | None:
        v = float(a[i])
        return round(v, digits) if np.isfinite(v) else None

    for i in idx.tolist():
        ti = float(t[i])
        new = []
        while k < len(texts) and texts[k][0] <= ti:
            new.append(texts[k][1])
            if texts[k][1].startswith("fc "):
                fc_reason = texts[k][1].split(": ", 1)[-1]
            k += 1
        while j < len(onboard) and onboard[j]["t_s"] <= ti:
            phase, j = phase_after(onboard[j], phase), j + 1
        state = _FC_STATES.get(int(cols["fc_state"][i]), "?")
        at = i if hit is None or i < hit else hit  # the vehicle stays where it hit
        out.append({
            "t": round(ti, 4),
            "phase": phase,
            "pos": [num(cols[f"pos_m_{a}"], at) for a in "xyz"],
            "rpy": [num(cols[f"{a}_deg"], at) for a in ("roll", "pitch", "yaw")],
            "cmd": [num(cols[c], i) for c in _COMMAND],
            "thrust_n": num(cols["thrust_n"], i),
            "speed": round(float(np.linalg.norm([cols[f"vel_m_s_{a}"][i] for a in "xyz"])), 4),
            "clearance": num(cols["clearance_m"], i),
            "fc": state,
            "links": {"cmd_hz": num(cols["command_rate_hz"], i, 1),
                      "mocap_hz": num(cols["mocap_rate_hz"], i, 1),
                      "cmd_lost": int(cols["command_lost"][i]), "mocap_lost": int(cols["mocap_lost"][i]),
                      "sp_age_ms": None if not np.isfinite(cols["setpoint_age_s"][i])
                      else round(float(cols["setpoint_age_s"][i]) * 1e3, 1)},
            "faults": sorted({kind for kind, a, b in faults if a <= ti and (b is None or ti < b)}),
            "banner": banner(state, state in _FAILSAFE, fc_reason,
                             abort if abort_s is not None and ti >= abort_s else None,
                             summary.get("collision") if hit_s is not None and ti >= hit_s else None),
            "events": new,
        })
    return out
