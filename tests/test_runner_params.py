"""FC parameters in scenario files: set before the flight, and changed in flight by a param_set fault;
each change reaches the FC at its sim time and is in the run's .tlog."""

from __future__ import annotations

from hil.link.mavlink import decode_frame
from hil.link.tlog import read_tlog
from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios

LAND_SOONER = """
description: failsafe land, its timeout cut to 0.4 s in flight; the command link then drops at 1 s
gap: {roll_deg: 0}
params: {COM_OBL_RC_ACT: 4}
faults:
  - {kind: param_set, start_s: 0.5, params: {name: COM_OF_LOSS_T, value: 0.4}}
  - {kind: param_set, start_s: 0.2, end_s: 0.3, params: {name: N3_FS_HOVER_T, value: 2}}
  - {kind: command_link_down, start_s: 1.0}
duration_s: 2.0
expect:
  crosses_gap: false
  recovery: false
  failsafe_expected: land
"""


def test_scenario_parameters_and_an_in_flight_change_act_and_are_recorded(tmp_path):
    [s] = loads_scenarios(LAND_SOONER)
    r = run_scenario(s, tmp_path, RunOptions(in_process=True))
    assert r.passed, r.failed_checks
    [fs] = r.summary["failsafe_events"][:1]
    assert fs["state"] == "failsafe_land" and 1.35 <= fs["time_s"] <= 1.5  # 0.4 s after the last setpoint
    frames = [(t, decode_frame(f)) for t, f in read_tlog(tmp_path / "run.tlog")]
    changes = [(m.param_id, round(m.param_value, 3)) for _, m in frames if m.get_type() == "PARAM_VALUE"]
    assert changes[1:] == [("N3_FS_HOVER_T", 2.0), ("N3_FS_HOVER_T", 5.0), ("COM_OF_LOSS_T", 0.4)]
    assert changes[0][0] == "COM_OBL_RC_ACT"
