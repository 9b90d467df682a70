"""Faults timed at the flight phase they name: a fault given after a mission event the onboard program
reports starts there, on both paths and deterministically; a fault whose window missed the phase it
names, or whose event never came, fails the run's fault_phases check instead of passing quietly."""

from __future__ import annotations

import json

import pytest

from hil.runner import RunOptions, run_scenario
from hil.scenario import ScenarioError, loads_scenarios

RELATIVE = """
description: a gust across the crossing, 0.3 s into the approach, for 0.4 s
gap: {roll_deg: 0}
faults:
  - {kind: wind_gust, start: {after: approach, s: 0.3}, duration_s: 0.4,
     params: {force_n: 1.0, direction: [0, 1, 0]}}
duration_s: 11
"""


def _events(out) -> list[dict]:
    return [json.loads(line) for line in (out / "onboard_events.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("in_process", [True, False], ids=["in_process", "ptys"])
def test_a_fault_after_a_mission_event_starts_there(tmp_path, in_process):
    s = loads_scenarios(RELATIVE)[0]
    r = run_scenario(s, tmp_path, RunOptions(in_process=in_process))
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]
    approach = next(e["t_s"] for e in _events(tmp_path) if e.get("segment") == "approach")
    starts = [e["time_s"] for e in r.summary["events"] if e["text"] == "wind_gust starts"]
    ends = [e["time_s"] for e in r.summary["events"] if e["text"] == "wind_gust ends"]
    assert starts == [pytest.approx(approach + 0.3, abs=1e-9)]
    assert ends == [pytest.approx(approach + 0.7, abs=1e-9)]
    check = next(c for c in r.checks if c.name == "fault_phases")
    assert check.passed and check.observed == "each fault acted in its phase"
    assert r.summary["faults"] == [{"kind": "wind_gust", "start_s": starts[0], "end_s": ends[0],
                                    "phase": "approach", "hit_phase": True}]


def test_a_fault_after_an_event_is_deterministic(tmp_path):
    s = loads_scenarios(RELATIVE)[0]
    a, b = (run_scenario(s, tmp_path / n, RunOptions(in_process=False)) for n in "ab")
    assert a.tlog_path.read_bytes() == b.tlog_path.read_bytes()


MISSED = """
description: a gust meant for the approach, timed in absolute seconds that fall in the takeoff
gap: {roll_deg: 0}
faults:
  - {kind: wind_gust, start_s: 1.0, end_s: 1.5, phase: approach, params: {force_n: 1.0, direction: [0, 1, 0]}}
  - {kind: mocap_frozen, start: {after: traverse, s: 0.1}, duration_s: 0.05}
duration_s: 5
expect: {crosses_gap: false, recovery: false}
"""


def test_a_fault_that_missed_its_phase_or_never_started_fails_the_run(tmp_path):
    s = loads_scenarios(MISSED)[0]
    r = run_scenario(s, tmp_path, RunOptions(in_process=True))
    check = next(c for c in r.checks if c.name == "fault_phases")
    assert not check.passed and not r.passed
    assert "faults[0] wind_gust at 1.00-1.50 s; approach:" in check.observed
    assert "faults[1] mocap_frozen never started (no 'traverse' event)" in check.observed
    assert check.time_s == 1.0
    texts = [e["text"] for e in r.summary["events"]]
    assert "mocap_frozen never started: no 'traverse' event came" in texts


@pytest.mark.parametrize(
    ("fault", "field", "message"),
    [
        ("{kind: mocap_dropped, start_s: 1, start: {after: approach}}", "faults[0].start_s",
         "give exactly one of start_s"),
        ("{kind: mocap_dropped, start: {after: approach, s: 0.2}, end_s: 3}", "faults[0].end_s",
         "ends with duration_s"),
        ("{kind: mocap_dropped, start: {after: aproach}}", "faults[0].start.after", "approach"),
        ("{kind: onboard_killed, start: {after: approach}}", "faults[0].start", "give at_s or at only"),
        ("{kind: mocap_dropped, start_s: 1, phase: cruise}", "faults[0].phase", "takeoff"),
    ],
    ids=["both_starts", "end_with_relative_start", "unknown_event", "killed_takes_at", "unknown_phase"],
)
def test_bad_fault_timing_is_refused_naming_the_field(fault, field, message):
    text = f"description: x\nfaults:\n  - {fault}\n"
    with pytest.raises(ScenarioError) as err:
        loads_scenarios(text, source="f.scenario.yaml")
    assert err.value.field == field and message in err.value.message, str(err.value)


def test_a_relative_fault_round_trips_through_to_dict():
    s = loads_scenarios(RELATIVE)[0]
    assert s.to_dict()["faults"][0]["start"] == {"after": "approach", "s": 0.3}
    assert s.to_dict()["faults"][0]["duration_s"] == 0.4
