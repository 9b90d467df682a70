"""The traditional pilot through the real serial path: the emulator side and the onboard program as two
processes joined by pseudo-terminals (MAVLink command link and LinkTrack-style mocap link), in lockstep.
No in-process shortcut: the onboard program is `python -m policies.onboard` reading /dev/pts/N.

Each case crosses a gap tilted 0, +-30, 45 or +-60 deg at an approach speed in 1-3 m/s through the default
0.8 m x 0.45 m opening, without collision, within 4 cm of the centre (3.4 cm at +-60 deg and 3 m/s, where
the 2.6 s approach would take the body box within 0.2 m of the floor and the planner flies a 2.0 s one),
and ends hovering at the recovery point inside the lab (the speeds per tilt are the feasible ones: see
test_closed_loop_gaps.py).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios

CASES = [(0.0, 1.0), (0.0, 3.0), (30.0, 1.5), (30.0, 3.0), (-30.0, 2.0), (45.0, 2.0), (-45.0, 3.0),
         (60.0, 2.5), (60.0, 3.0), (-60.0, 2.5), (-60.0, 3.0)]


@pytest.mark.parametrize(("roll_deg", "speed_m_s"), CASES, ids=[f"roll{r:+.0f}-{s:g}mps" for r, s in CASES])
def test_traditional_pilot_crosses_over_ptys(tmp_path, roll_deg: float, speed_m_s: float) -> None:
    [scenario] = loads_scenarios(
        f"description: roll {roll_deg} deg at {speed_m_s} m/s over ptys\n"
        f"gap: {{roll_deg: {roll_deg}}}\napproach: {{speed_m_s: {speed_m_s}}}\nduration_s: 11\n"
    )
    r = run_scenario(scenario, tmp_path, RunOptions(in_process=False))
    s = r.summary
    assert s["mode"]["in_process"] is False and s["mode"]["realtime"] is False, s["mode"]
    assert r.passed, [f"{c.name}: expected {c.expected}, observed {c.observed}" for c in r.failed_checks]
    assert s["crossing"]["through_opening"] and not s["collision"]
    assert s["min_clearance_m"] > 0.0
    # offset from the gap centre, in the gap plane
    offset = np.asarray(s["crossing"]["point_m"]) - np.asarray(scenario.gap.centre_m)
    assert np.linalg.norm(offset) < 0.04, offset
    assert s["onboard_exit_code"] == 0 and s["fc_final_state"] == "hold"
    # lockstep: the program answered every 10 ms tick until it handed the vehicle to the FC's Hold and exited
    events = [json.loads(line) for line in (r.out_dir / "onboard_events.jsonl").read_text().splitlines()]
    done_s = next(e["t_s"] for e in events if e.get("event") == "done")
    assert s["ticks_answered"] >= round(done_s / 0.01) - 1, (s["ticks_answered"], done_s)
