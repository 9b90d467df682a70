"""Closed loop through the real emulator: the traditional pilot crosses gaps tilted 0, 30, 45, 60 and
-60 deg at 1-3 m/s without touching anything and ends hovering in the lab, handed back to the FC's HOLD.

The FC emulator (physics, inner loop, MAVLink server), the mocap system and its UWB link and the gap
world are the real ones; they meet the onboard program over in-memory links in simulated time (see
`onboard_rig`). The gap is 1.1 m x 0.55 m: with the default 0.8 m x 0.35 m opening this 0.52 m vehicle
grazes the wall at 60 deg even on a perfectly tracked reference.
"""

from __future__ import annotations

import numpy as np
import pytest
from onboard_rig import run_mission

CASES = [(0.0, 1.0), (30.0, 1.5), (45.0, 2.0), (60.0, 2.5), (-60.0, 3.0)]


@pytest.mark.parametrize(("roll_deg", "speed_m_s"), CASES, ids=[f"roll{r:+.0f}-{s:g}mps" for r, s in CASES])
def test_traditional_pilot_crosses_the_tilted_gap(roll_deg: float, speed_m_s: float) -> None:
    r = run_mission(roll_deg, speed_m_s, traverse_lead_m=0.2, after_s=2.0)
    summary = r.tracker.to_dict()
    assert r.program.exit_code == 0, r.program.events.events[-3:]
    assert summary["crossings"] == 1 and r.tracker.crossed_through_opening, summary
    assert r.tracker.first_collision is None, summary
    assert summary["min_clearance_m"] is not None and summary["min_clearance_m"] > 0.0
    # crossed close to the planned time, at about the commanded speed
    plan = r.event("plan")
    t_cross = summary["crossing_time_s"]
    assert abs(t_cross - (plan["t_s"] + plan["t_gap_s"])) < 0.15
    # ends hovering near the planned point, inside the lab, with the FC holding it 2 s later
    done = r.event("done")
    assert done["hold"] is True and done["in_lab"] is True
    final = r.vehicle.state
    assert r.vehicle.fc.state.value == "hold"
    assert r.lab.contains(final.pos_m)
    assert np.linalg.norm(final.pos_m - np.array(plan["hover_m"])) < 0.5
    assert np.linalg.norm(final.vel_m_s) < 0.1
