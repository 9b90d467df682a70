"""Real-time mode, as a pilot watching or a real TX2 on a USB-serial adapter uses it: simulated time
follows the wall clock, and the onboard program still takes control over its ptys."""

from __future__ import annotations

from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios

SHORT = """
description: real time - take control and start the takeoff, cut short
gap: {roll_deg: 0}
duration_s: 3.0
expect: {crosses_gap: false, recovery: false}
"""


def test_realtime_run_follows_the_wall_clock_and_the_onboard_takes_control(tmp_path):
    s = loads_scenarios(SHORT)[0]
    r = run_scenario(s, tmp_path, RunOptions(realtime=True, in_process=False))
    sm = r.summary
    assert sm["mode"]["realtime"] is True and sm["mode"]["in_process"] is False
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]
    assert abs(sm["sim_time_s"] - 3.0) < 0.02
    # paced by the wall clock: neither faster nor much slower than real time
    assert 0.8 <= sm["real_time_factor"] <= 1.05, sm["real_time_factor"]
    texts = [e["text"] for e in sm["events"] if e["source"] == "onboard"]
    assert "authority" in texts and "takeoff" in texts, texts
    assert sm["fc_final_state"] == "offboard"
