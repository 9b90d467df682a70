"""Runs with the motors on a DroneCAN bus: deterministic in lockstep (the bus in simulated time, its
loss and corruption drawn from the run's seed), its faults acting in their windows, and the shipped
ESC-loss scenario ending in the configured failsafe and a reported crash, never silence."""

from __future__ import annotations

from pathlib import Path

import pytest

from emulator.physics import backend_names
from hil.link.mavlink import decode_frame
from hil.link.tlog import read_tlog
from hil.runner import RunOptions, run_scenario
from hil.scenario import load_scenarios, loads_scenarios

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
LOSSY_BUS = """
description: a level gap flown with the motors on a lossy DroneCAN bus, cut short (determinism only)
gap: {roll_deg: 0}
links:
  esc_bus: {loss: 0.01, corruption: 0.01}
faults:
  - {kind: can_frame_loss, start_s: 1.0, end_s: 1.5, params: {fraction: 0.3}}
  - {kind: can_bus_off, start_s: 2.0, end_s: 2.04}
duration_s: 2.5
seed: 5
expect: {crosses_gap: false, recovery: false}
"""


def test_a_run_on_the_esc_bus_is_the_same_twice_and_its_faults_show(tmp_path):
    [s] = loads_scenarios(LOSSY_BUS)
    a, b = (run_scenario(s, tmp_path / n, RunOptions(in_process=True)) for n in "ab")
    assert (tmp_path / "a" / "run.tlog").read_bytes() == (tmp_path / "b" / "run.tlog").read_bytes()
    esc = a.summary["esc_bus"]
    assert esc == b.summary["esc_bus"]
    bus = esc["bus"]
    # 1 % all along, 30 % for 0.5 s: about 0.01 x 2.5 s + 0.3 x 0.5 s of ~1400 frames/s
    assert 150 < bus["lost"] < 400 and bus["error_frames"] > 10
    assert 40 < bus["bus_off_dropped"] < 80  # 40 ms of the bus's ~1400 frames/s
    assert esc["commands_sent"] == 1000  # 400 Hz for 2.5 s
    assert a.passed, a.failed_checks  # a 40 ms bus-off is shorter than the ESCs' 100 ms command timeout


@pytest.mark.parametrize("backend", backend_names())
def test_the_shipped_esc_loss_ends_in_the_failsafe_and_a_reported_crash(tmp_path, backend):
    [s] = load_scenarios(SCENARIOS / "esc_lost_approach.scenario.yaml")
    r = run_scenario(s, tmp_path, RunOptions(in_process=True, backend=backend))
    assert r.passed, r.failed_checks
    assert r.summary["failsafe_events"][0]["state"] == "failsafe_land"
    assert [e["failed"] for e in r.summary["esc_bus"]["escs"]] == [False, False, True, False]
    texts = [decode_frame(f).text for _, f in read_tlog(tmp_path / "run.tlog")
             if decode_frame(f).get_type() == "STATUSTEXT"]
    assert "ESC 2 silent for 0.1 s" in texts and any("ESC failed: land" in t for t in texts)
