"""A run with the command link in DJI's OPEN protocol: a whole crossing through ptys in lockstep whose
capture is byte for byte the same twice, the lockstep ticks kept out of it, and the program's own
counters of the OPEN link; the options that choose the protocol for any scenario."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from hil.link import dji_open
from hil.link.tlog import read_tlog
from hil.runner import RunOptions, RunSetupError, run_scenario
from hil.scenario import load_scenarios

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def test_a_crossing_over_the_open_protocol_through_ptys_gives_the_same_capture_twice(tmp_path):
    s = load_scenarios(SCENARIOS / "gap_roll30_2ms.scenario.yaml")[0]
    opts = RunOptions(in_process=False, protocol="dji_open")
    a, b = (run_scenario(s, tmp_path / name, opts) for name in "ab")
    assert a.passed, [f"{c.name}: {c.observed}" for c in a.failed_checks]
    log = (a.out_dir / "onboard_events.jsonl").read_text()
    events = [json.loads(line)["event"] for line in log.splitlines()]
    assert {"authority", "armed", "mission_done", "done"} <= set(events)
    assert a.summary["lockstep"] == {"held": True, "short_mocap_reads": 0, "lost_at_s": None}
    assert a.tlog_path.read_bytes() == b.tlog_path.read_bytes()
    frames = read_tlog(a.tlog_path)
    assert all(f[0] == dji_open.SOF and dji_open.crc32(f) == 0 for _, f in frames)
    kinds = {(f[12], f[13]) for _, f in frames if not f[3] & 0x20}
    assert (dji_open.SET_CONTROL, dji_open.CMD_SETPOINT) in kinds
    assert (dji_open.SET_CONTROL, dji_open.CMD_CONTROL_AUTHORITY) in kinds
    assert all(k[0] != dji_open.SET_HIL for k in kinds)  # the harness's ticks are not the FC's traffic
    summary = a.summary["onboard"]
    assert summary["dji_open"]["bad_crc"] == 0 and summary["dji_open"]["timeouts"] == 0


def test_the_protocol_option_must_name_a_protocol(tmp_path):
    s = load_scenarios(SCENARIOS / "gap_roll30_2ms.scenario.yaml")[0]
    with pytest.raises(RunSetupError, match="mavlink, dji_open"):
        run_scenario(replace(s, duration_s=1.0), tmp_path, RunOptions(protocol="dji"))
