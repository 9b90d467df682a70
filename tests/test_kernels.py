"""The onboard computer's compiled chains (`policies.compiling`): where they are cached, and the plan's
reference they compute segment by segment."""

from __future__ import annotations

from pathlib import Path

import pytest

from policies.compiling import cache_folder
from policies.gap_planning import BodyClearance, GapPose, LabVolume, MissionRequest


def test_the_cache_folder_changes_with_any_source_the_kernels_compile(tmp_path: Path, monkeypatch) -> None:
    """numba checks a cached kernel against its own file only: a change to a function it inlines from
    another file must compile afresh, so the folder is named by every source's bytes."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("x = 1\n")
    b.write_text("y = 2\n")
    first = cache_folder((a, b))
    assert Path(first).parent == tmp_path / "cache" and cache_folder((a, b)) == first
    b.write_text("y = 3\n")  # the inlined file alone changed
    assert cache_folder((a, b)) != first


@pytest.mark.parametrize("vehicle", ["n3_tx2", "f450"])  # a minimum-jerk recovery, a minimum-snap one (f450)
def test_the_plans_reference_is_each_segments_own_state(vehicle: str) -> None:
    from policies.vehicle import load_vehicle

    v = load_vehicle(vehicle)
    plan = MissionRequest((-2.0, -1.0, 0.5), (0.0, 0.0, 0.0),
                          GapPose.from_deg((0.0, 0.5, 2.1), -60.0, width_m=0.85, height_m=0.57),
                          LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0)), 2.6, 2.5, v.traverse_lead_m,
                          BodyClearance(v.body_box_m), v.max_body_rate_rad_s).plan()
    assert (plan.recovery.trajectory.delta is not None) == (vehicle == "f450")
    t1, t2, t3 = plan.t_traverse_start_s, plan.t_recovery_start_s, plan.t_hover_start_s
    for t in (-0.5, 0.0, 0.37 * t1, t1, (t1 + t2) / 2, t2, (t2 + t3) / 2, t3, t3 + 2.0):
        p, v3, a, yaw = plan.reference_tuples(t)
        if t < t1:
            want = plan.approach.state_tuples(max(t, 0.0))
        elif t < t2:
            want = plan.traverse.state_tuples(t - t1)
        elif t < t3:
            want = plan.recovery.trajectory.state_tuples(t - t2)
        else:
            want = (tuple(plan.hover_m), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        assert (tuple(p), tuple(v3), tuple(a)) == tuple(map(tuple, want)) and yaw == plan.yaw_rad
