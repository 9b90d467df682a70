"""Tests for policies.gap_planning: traverse geometry, approach, recovery search, mission timeline."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import time
from collections.abc import Callable

import numpy as np
import pytest

from policies.gap_planning import (
    APPROACH_DURATIONS_S,
    POINT_BODY,
    RECOVERY_DURATIONS_S,
    BodyClearance,
    GapPose,
    LabVolume,
    MissionRequest,
    PlanningError,
    RecoveryResult,
    Segment,
    VehicleLimits,
    plan_mission,
    plan_traverse,
    search_recovery,
    start_height,
    start_plan,
)
from policies.primitives import Feasibility, Trajectory, solve

G = np.array([0.0, 0.0, -9.8])
LAB = LabVolume((-4.0, -3.0, 0.0), (4.0, 4.0, 4.0))
PAPER_START = (-2.0, -1.0, 0.5)


def paper_gap(roll_deg: float = -60.0) -> GapPose:
    return GapPose.from_deg((0.0, 0.5, 2.1), roll_deg, width_m=0.8, height_m=0.35)


@pytest.mark.parametrize("roll_deg", [-60.0, -30.0, 0.0, 30.0, 60.0])
@pytest.mark.parametrize("speed", [1.0, 2.0, 3.0])
def test_traverse_through_centre_with_thrust_orthogonal_to_long_side(roll_deg: float, speed: float) -> None:
    gap = paper_gap(roll_deg)
    tr = plan_traverse(gap, speed)
    p, v, _ = tr.state(tr.t_c_s)
    np.testing.assert_allclose(p, gap.centre, atol=1e-12)
    np.testing.assert_allclose(v, speed * gap.e1, atol=1e-12)  # through the centre along the normal
    for t in np.linspace(0, tr.duration_s, 11):
        _, _, a = tr.state(t)
        thrust_dir = (a - G) / np.linalg.norm(a - G)
        assert abs(thrust_dir @ gap.e0) < 1e-12  # body z orthogonal to the long side
        assert abs(thrust_dir @ gap.e1) < 1e-12
    # the start is l along the long side (below the centre) and d before the plane: p0 = p_g - l e0 - d e1
    p0, v0, _ = tr.start_state
    e0_up = gap.e0 if gap.e0[2] >= 0 else -gap.e0
    np.testing.assert_allclose(p0, gap.centre - tr.l_m * e0_up - tr.d_m * gap.e1, atol=1e-12)
    assert 0 <= tr.l_m <= 0.5 and tr.d_m >= 0.1 - 1e-12
    if roll_deg != 0:
        g0 = abs(G @ gap.e0)
        assert tr.t_c_s == pytest.approx(math.sqrt(2 * tr.l_m / g0), rel=1e-12)
    else:
        assert tr.l_m == 0.0 and np.allclose(tr.acc_m_s2, 0.0)  # straight, no drop
    assert np.linalg.norm(v0) <= VehicleLimits().max_speed_m_s
    pe, _, _ = tr.end_state
    assert (pe - gap.centre) @ gap.e1 == pytest.approx(0.3)  # leaves 0.3 m past the plane


def test_traverse_limits_are_enforced() -> None:
    with pytest.raises(PlanningError, match="tilt"):
        plan_traverse(paper_gap(80.0), 2.0)
    with pytest.raises(PlanningError, match="speed"):
        plan_traverse(paper_gap(), 2.0, VehicleLimits(max_speed_m_s=1.0))
    with pytest.raises(PlanningError):
        plan_traverse(paper_gap(), -1.0)


def test_paper_case_plans_and_segments_join() -> None:
    start = time.perf_counter()
    plan = plan_mission(PAPER_START, paper_gap(), LAB, approach_duration_s=2.6, body=POINT_BODY)
    elapsed = time.perf_counter() - start
    print(f"\npaper case: planned in {elapsed * 1e3:.1f} ms, recovery search "
          f"{plan.recovery.search_time_s * 1e3:.1f} ms ({plan.recovery.duration_s} s, "
          f"{plan.recovery.tried} durations)")
    assert plan.recovery.search_time_s < 0.25  # the paper needed < 50 ms on a TX2; shared machine here
    assert plan.approach_feasibility is not Feasibility.INFEASIBLE
    assert float(plan.approach.T) == 2.6 and plan.yaw_rad == pytest.approx(0.0)
    # the approach ends exactly in the traverse start state
    for got, want in zip(plan.approach.state(2.6), plan.traverse.start_state, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    # the reference is continuous in p, v, a across every segment boundary
    for t_b in (plan.t_traverse_start_s, plan.t_recovery_start_s, plan.t_hover_start_s):
        before, after = plan.reference(t_b - 1e-9), plan.reference(t_b)
        assert before.segment != after.segment
        for x, y in ((before.pos_m, after.pos_m), (before.vel_m_s, after.vel_m_s),
                     (before.acc_m_s2, after.acc_m_s2)):
            np.testing.assert_allclose(x, y, atol=1e-6)
    assert [plan.segment_at(t) for t in (-1.0, 1.0, plan.t_gap_s, plan.t_hover_start_s + 5)] == [
        Segment.APPROACH, Segment.APPROACH, Segment.TRAVERSE, Segment.HOVER]
    # a segment holds until its end, where the next begins (the hover never ends)
    for t in np.linspace(-1.0, plan.t_hover_start_s + 5, 400):
        end = plan.segment_end_s(t)
        assert end > t and plan.segment_at(np.nextafter(end, -np.inf)) == plan.segment_at(t)
        seg = plan.segment_at(t)
        assert end == np.inf if seg is Segment.HOVER else plan.segment_at(end) != seg
    np.testing.assert_allclose(plan.reference(plan.t_gap_s).pos_m, [0.0, 0.5, 2.1], atol=1e-12)
    np.testing.assert_allclose(plan.reference(-1.0).pos_m, PAPER_START)


@pytest.mark.parametrize("roll_deg", [-60.0, 0.0, 45.0, 60.0])
def test_recovery_stays_in_lab_and_ends_hovering(roll_deg: float) -> None:
    plan = plan_mission(PAPER_START, paper_gap(roll_deg), LAB)
    rec = plan.recovery.trajectory
    ts = np.linspace(0, rec.T, 2001)
    p, _, _ = rec.state(ts)
    body = BodyClearance()  # the body box's reach plus the margin from the floor and the lab's faces
    clear = body.clearance_m
    assert np.all(p >= np.array(LAB.min_m) + clear - 1e-9) and np.all(p <= np.array(LAB.max_m) - clear + 1e-9)
    # never back towards the wall: the body's reach stays past its plane
    assert np.all((p - plan.gap.centre) @ np.array(plan.traverse.direction) >= body.reach_m - 1e-9)
    pf, vf, af = rec.state(rec.T)
    np.testing.assert_allclose(pf, [2.5, 0.5, 1.0], atol=1e-9)  # 2.5 m past the centre, 1 m up
    np.testing.assert_allclose(vf, 0.0, atol=1e-9)
    np.testing.assert_allclose(af, 0.0, atol=1e-9)
    lim = VehicleLimits()
    assert rec.input_feasible(lim.f_min_m_s2, lim.f_max_m_s2, lim.max_body_rate_rad_s,
                              lim.min_dt_s) == Feasibility.FEASIBLE
    assert plan.recovery.duration_s in np.round(np.arange(0.5, 3.01, 0.3), 10)
    ref = plan.reference(plan.t_hover_start_s + 3.0)
    assert ref.segment is Segment.HOVER and np.allclose(ref.vel_m_s, 0.0)


def test_recovery_search_takes_the_first_duration_that_fits() -> None:
    lab = LabVolume((-10, -10, 0), (10, 10, 10))
    res = search_recovery((0, 0, 2), (0.2, 0, 0), (0, 0, 0), (0.1, 0, 2), lab)
    assert res.duration_s == 0.5 and res.tried == 1  # nothing in the way: the shortest wins
    # sideways at 2 m/s: the short durations need more than the body-rate/thrust limits allow, the
    # longer ones overshoot further sideways; a strong vehicle takes the shortest, a near wall leaves none
    strong = VehicleLimits(f_max_m_s2=200.0, max_body_rate_rad_s=500.0)
    state = ((0, 0, 2), (0, 2, 0), (0, 0, 0), (1.0, 0, 1.5))
    assert search_recovery(*state, lab, strong).duration_s == 0.5
    res2 = search_recovery(*state, lab)
    assert res2.duration_s > 0.5
    y_top = res2.trajectory.state(np.linspace(0, res2.duration_s, 2001))[0][:, 1].max()
    ok_wall = search_recovery(*state, LabVolume((-10, -10, 0), (10, y_top + 0.01, 10)))
    assert ok_wall.duration_s == res2.duration_s
    with pytest.raises(PlanningError, match="no recovery"):
        search_recovery(*state, LabVolume((-10, -10, 0), (10, y_top - 0.01, 10)))
    with pytest.raises(PlanningError, match="outside the lab"):
        search_recovery((0, 0, 2), (1, 0, 0), (0, 0, 0), (20, 0, 2), lab)
    tiny = LabVolume((-0.5, -0.5, 0), (1.5, 0.5, 2.5))  # 6 m/s cannot stop within 1.5 m
    with pytest.raises(PlanningError, match="no recovery"):
        search_recovery((0, 0, 2), (6, 0, 0), (0, 0, 0), (1.0, 0, 1), tiny)


def test_crossing_direction_follows_the_start_side_and_gap_yaw() -> None:
    gap = GapPose.from_deg((0.0, 0.5, 2.1), 30.0, 0.0, 90.0, width_m=0.8, height_m=0.35)
    plan = plan_mission((0.0, -2.0, 1.0), gap, LAB)
    np.testing.assert_allclose(plan.traverse.direction, [0, 1, 0], atol=1e-12)
    assert plan.yaw_rad == pytest.approx(math.pi / 2)
    far_gap = GapPose.from_deg((0, 0.5, 2.1), 30, 0, 90, width_m=0.8, height_m=0.35)
    far = plan_mission((0.0, 2.5, 1.0), far_gap, LabVolume((-4, -4, 0), (4, 4, 4)))
    np.testing.assert_allclose(far.traverse.direction, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(far.hover_m, [0, -2.0, 1.0], atol=1e-12)


def test_gap_pose_validation_and_quaternion() -> None:
    with pytest.raises(ValueError):
        GapPose((0, 0, 0), ((1, 0, 0), (0, 1, 0), (0, 0, 2)), 0.8, 0.3)
    with pytest.raises(ValueError):
        GapPose.from_deg((0, 0, float("nan")), 10, width_m=0.8, height_m=0.3)
    with pytest.raises(ValueError):
        LabVolume((0, 0, 0), (1, -1, 1))
    half = math.radians(-60) / 2
    q_wxyz = (math.cos(half), math.sin(half), 0, 0)
    q = GapPose.from_quaternion((0, 0.5, 2.1), q_wxyz, width_m=0.8, height_m=0.3)
    np.testing.assert_allclose(q.R, paper_gap().R, atol=1e-12)
    np.testing.assert_allclose(q.e2, -q.R[:, 2], atol=1e-12)


def _same_trajectory(a: Trajectory, b: Trajectory) -> None:
    for name in ("p0", "v0", "a0", "alpha", "beta", "gamma", "T"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)  # equal here; other numpy builds may round


def _outcome(search: Callable[[], RecoveryResult]) -> RecoveryResult | str:
    try:
        return search()
    except PlanningError as exc:
        return str(exc)


@pytest.mark.parametrize("roll_deg", [-60.0, -20.0, 0.0, 35.0, 60.0])
def test_plan_mission_gives_the_numpy_pipeline_plan(roll_deg: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """The plan is the one the numpy pipeline (solve, exact plane distances) gives with the paper's
    recovery search, and the usual case never needs the exact plane distances."""
    from policies.gap_planning import hover_point

    gap = GapPose.from_deg((0.0, 0.5, 2.1), roll_deg, width_m=0.8, height_m=0.45)
    lab = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
    start, vel = np.array([-2.0, -1.0, 0.5]), np.array([0.05, -0.02, 0.01])
    calls: list[str] = []

    def counted(name: str) -> Callable[..., object]:
        original = getattr(Trajectory, name)

        def method(self: Trajectory, *a: object, **k: object) -> object:
            calls.append(name)
            return original(self, *a, **k)
        return method

    monkeypatch.setattr(Trajectory, "min_plane_distance", counted("min_plane_distance"))
    plan = plan_mission(start, gap, lab, start_vel_m_s=vel, approach_duration_s=2.6, crossing_speed_m_s=2.5,
                        d_min_m=0.25, body=POINT_BODY)
    assert calls == []  # plain floats throughout
    monkeypatch.undo()
    lim = VehicleLimits()
    trav = plan_traverse(gap, 2.5, lim, 1.0, 0.25, 0.3)
    assert plan.traverse == trav
    approach = solve(start, vel, np.zeros(3), *trav.start_state, 2.6)
    _same_trajectory(plan.approach, approach)
    assert plan.approach_feasibility == approach.input_feasible(lim.f_min_m_s2, lim.f_max_m_s2,
                                                                lim.max_body_rate_rad_s, lim.min_dt_s)
    planes = lab.half_spaces()
    points, normals = np.array([p for p, _ in planes]), np.array([n for _, n in planes])
    assert np.all(approach.position_feasible(points, normals))
    u = np.array(trav.direction)
    hover = hover_point(gap, u, 2.5, 1.0)
    rec = search_recovery(*trav.end_state, hover, lab, lim, wall=(gap.centre, u))
    assert (plan.recovery.duration_s, plan.recovery.tried) == (rec.duration_s, rec.tried)
    _same_trajectory(plan.recovery.trajectory, rec.trajectory)
    assert plan.hover_m == tuple(hover.tolist()) and plan.yaw_rad == math.atan2(u[1], u[0])


def _lowest_and_outermost(plan) -> tuple[float, float]:
    """The reference's lowest z (m) and how near it gets to the lab's side faces and ceiling (m), over
    approach, traverse and recovery, sampled every millisecond."""
    ts = np.arange(0.0, plan.t_hover_start_s, 1e-3)
    p = np.array([plan.reference(t).pos_m for t in ts])
    lab = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
    side = min(float((p[:, :2] - np.array(lab.min_m[:2])).min()), float((np.array(lab.max_m) - p).min()))
    return float(p[:, 2].min()), side


def test_the_approach_keeps_the_body_off_the_floor() -> None:
    """A gap at 1.5 m rolled 54 deg from a 0.5 m hover: the 2.6 s approach dips the centre to 4 cm above
    the floor (the body box would hit it); the plan flown keeps the body's clearance everywhere."""
    lab = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
    gap = GapPose.from_deg((0.0, 0.5, 1.5), 54.0, width_m=0.8, height_m=0.45)
    point = plan_mission(PAPER_START, gap, lab, crossing_speed_m_s=2.5, d_min_m=0.25, body=POINT_BODY)
    assert float(point.approach.T) == 2.6 and _lowest_and_outermost(point)[0] < 0.1  # what the centre allows
    plan = plan_mission(PAPER_START, gap, lab, crossing_speed_m_s=2.5, d_min_m=0.25)
    clear = BodyClearance().clearance_m
    lowest, side = _lowest_and_outermost(plan)
    assert lowest >= clear - 1e-6 and side >= clear - 1e-6
    assert plan.traverse.crossing_speed_m_s == 2.5  # found at the speed asked for, with another duration
    assert float(plan.approach.T) in APPROACH_DURATIONS_S and plan.candidates_tried > 1
    np.testing.assert_allclose(plan.reference(plan.t_gap_s).pos_m, gap.centre, atol=1e-12)


def test_the_papers_rl_case_plans() -> None:
    """The paper's RL case (gap at (2, 1, 1.5) m rolled 60 deg, start near the origin): no 2.6 s
    approach fits the lab, a shorter one does."""
    lab = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
    gap = GapPose.from_deg((2.0, 1.0, 1.5), 60.0, width_m=0.8, height_m=0.45)
    plan = plan_mission((0.0, 0.0, 0.5), gap, lab, crossing_speed_m_s=2.5, d_min_m=0.25)
    lowest, side = _lowest_and_outermost(plan)
    clear = BodyClearance().clearance_m
    assert lowest >= clear - 1e-6 and side >= clear - 1e-6
    assert plan.approach_feasibility is not Feasibility.INFEASIBLE
    np.testing.assert_allclose(plan.reference(plan.t_gap_s).pos_m, gap.centre, atol=1e-12)
    assert plan.reference(plan.t_hover_start_s).pos_m[0] == pytest.approx(4.5)


def test_the_search_keeps_what_was_asked_when_it_fits_and_says_why_when_nothing_does() -> None:
    gap = paper_gap(30.0)
    plan = plan_mission(PAPER_START, gap, LabVolume((-5, -5, 0), (5, 5, 4)), crossing_speed_m_s=2.0)
    assert (plan.candidates_tried, float(plan.approach.T), plan.traverse.crossing_speed_m_s) == (1, 2.6, 2.0)
    assert plan.search_time_s > 0
    # a lab so low that the body cannot pass under its ceiling at the gap's height
    with pytest.raises(PlanningError, match=r"no plan keeps the body's 0\.43 m clearance.*lab's faces"):
        plan_mission(PAPER_START, gap, LabVolume((-5, -5, 0), (5, 5, 2.4)))
    # a gap too near the floor for the body to cross
    with pytest.raises(PlanningError, match="floor"):
        plan_mission(PAPER_START, GapPose.from_deg((0, 0.5, 0.35), 0.0, width_m=0.8, height_m=0.45),
                     LabVolume((-5, -5, 0), (5, 5, 4)))
    # a bigger body needs more room: the same plan with a 1 m box is refused
    with pytest.raises(PlanningError, match=r"0\.92 m clearance"):
        plan_mission(PAPER_START, gap, LabVolume((-5, -5, 0), (5, 5, 2.8)),
                     body=BodyClearance((1.0, 1.0, 1.0), 0.05))
    with pytest.raises(ValueError):
        BodyClearance((0.5, -0.1, 0.2))


@pytest.mark.parametrize("roll_deg", [70.0, -70.0])
@pytest.mark.parametrize("speed", [3.0, 4.0])
def test_seventy_degree_gaps_plan_at_the_speed_asked_for(roll_deg: float, speed: float) -> None:
    lab = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
    gap = GapPose.from_deg((0.0, 0.5, 2.1), roll_deg, width_m=0.8, height_m=0.45)
    plan = plan_mission(PAPER_START, gap, lab, crossing_speed_m_s=speed, d_min_m=0.25)
    assert plan.traverse.crossing_speed_m_s == speed
    lowest, side = _lowest_and_outermost(plan)
    assert lowest >= BodyClearance().clearance_m - 1e-6 and side >= BodyClearance().clearance_m - 1e-6


LAB5 = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))


@pytest.mark.parametrize("start", [(-2.0, -1.0, 0.5), (1.5, 1.2, 1.0), (0.0, 2.4, 2.0), (-4.0, 0.5, 3.2)])
def test_recovery_search_picks_the_first_duration_that_passes_every_check(start):
    hover = np.array([0.5, 2.5, 1.0])
    wall = (np.array([0.0, 0.5, 2.1]), np.array([0.0, 1.0, 0.0]))
    vel = np.array([0.0, 2.0, -0.5])
    traj = solve(start, vel, np.zeros(3), hover, np.zeros(3), np.zeros(3), RECOVERY_DURATIONS_S)
    ok = np.ones(traj.batch_shape, dtype=bool)
    for point, normal in LAB5.half_spaces():
        ok &= traj.position_feasible(point, normal, 0.2)
    if start[1] > wall[0][1]:
        ok &= traj.position_feasible(*wall)
    cand = np.flatnonzero(ok)
    lim = VehicleLimits()
    feas = traj.input_feasible(lim.f_min_m_s2, lim.f_max_m_s2, lim.max_body_rate_rad_s, lim.min_dt_s)
    good = [i for i in cand if feas[i] == Feasibility.FEASIBLE]
    wall_arg = wall if start[1] > wall[0][1] else None
    if not good:
        with pytest.raises(ValueError, match="no recovery duration"):
            search_recovery(start, vel, np.zeros(3), hover, LAB5, wall=wall_arg, margin_m=0.2)
        return
    res = search_recovery(start, vel, np.zeros(3), hover, LAB5, wall=wall_arg, margin_m=0.2)
    assert res.tried == good[0] + 1 and res.duration_s == float(RECOVERY_DURATIONS_S[good[0]])


def _f450_request(roll_deg: float, max_body_rate_rad_s: float) -> MissionRequest:
    gap = GapPose.from_deg((0.0, 0.5, 2.1), roll_deg, width_m=0.85, height_m=0.57)
    lab = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
    return MissionRequest((-2.0, -1.0, 0.5), (0.0, 0.0, 0.0), gap, lab,
                          2.6, 2.0 if abs(roll_deg) < 50 else 2.5, 0.4, BodyClearance((0.569, 0.569, 0.3048)),
                          max_body_rate_rad_s)


def test_a_request_prefers_plans_within_the_vehicles_body_rate_and_keeps_it_through_json() -> None:
    """A slow vehicle's request (6 rad/s, the f450's FC) gets the recovery it can turn through after a
    30 deg gap, where the planner's own 15 rad/s takes the first, 1.1 s one; after a 60 deg traverse no
    recovery is within 6 rad/s and the plan is the first within twice it (a 1.7 s recovery, not the 1.4 s
    one of 13.8 rad/s). The limit goes through the plan event's JSON, so the harness derives the same
    plan."""
    slow, fast = _f450_request(30.0, 6.0).plan(), _f450_request(30.0, 15.0).plan()
    assert fast.recovery.duration_s == pytest.approx(1.1)
    assert slow.recovery.duration_s > fast.recovery.duration_s
    limits = VehicleLimits(max_body_rate_rad_s=6.0)
    for traj in (slow.approach, slow.recovery.trajectory):
        assert traj.input_feasible(limits.f_min_m_s2, limits.f_max_m_s2, 6.0, limits.min_dt_s) == \
            Feasibility.FEASIBLE
    assert fast.recovery.trajectory.input_feasible(limits.f_min_m_s2, limits.f_max_m_s2, 6.0,
                                                   limits.min_dt_s) != Feasibility.FEASIBLE
    steep = _f450_request(60.0, 6.0)
    with pytest.raises(PlanningError, match="no recovery duration"):
        plan_mission(steep.start_pos_m, steep.gap, steep.lab, approach_duration_s=2.6, crossing_speed_m_s=2.5,
                     d_min_m=0.4, body=steep.body, limits=limits)
    twice = steep.plan().recovery
    own = _f450_request(60.0, 15.0).plan().recovery
    assert (twice.duration_s, own.duration_s) == pytest.approx((1.7, 1.4))
    assert twice.trajectory.input_feasible(limits.f_min_m_s2, limits.f_max_m_s2, 12.0, limits.min_dt_s) == \
        Feasibility.FEASIBLE
    again = MissionRequest.from_dict(json.loads(json.dumps(_f450_request(30.0, 6.0).to_dict())))
    assert again.max_body_rate_rad_s == 6.0 and again.plan().recovery.duration_s == slow.recovery.duration_s
    legacy = {k: v for k, v in _f450_request(30.0, 6.0).to_dict().items() if k != "max_body_rate_rad_s"}
    assert MissionRequest.from_dict(legacy).max_body_rate_rad_s == VehicleLimits().max_body_rate_rad_s


def _max_body_rate_rad_s(traj: Trajectory) -> float:
    """The roll/pitch body rate |jerk x z| / |a - g| (rad/s) a trajectory asks for, densely sampled."""
    ts = np.linspace(0.0, float(traj.T), 4001)
    f = traj.state(ts)[2] - G
    z = f / np.linalg.norm(f, axis=-1, keepdims=True)
    j = traj.jerk(ts)
    return float(np.max(np.linalg.norm(j - np.sum(j * z, -1, keepdims=True) * z, axis=-1)
                        / np.linalg.norm(f, axis=-1)))


def test_a_slow_vehicles_recovery_from_a_60_deg_traverse_is_within_its_body_rate() -> None:
    """The f450 (its FC turns at 6 rad/s: its onboard configuration) through the -60 deg gap: every
    minimum-jerk recovery from the traverse's low thrust starts turning faster than that (its start jerk
    is free); the plan's recovery is the jerk-continuous one (zero jerk at the traverse's end and at the
    hover), within the vehicle's rate, where it used to ask 11 rad/s. The default vehicle's plan keeps
    its minimum-jerk recovery."""
    from policies.vehicle import load_vehicle

    f450 = load_vehicle("f450")
    w = f450.max_body_rate_rad_s
    request = MissionRequest((-2.0, -1.0, 0.5), (0.0, 0.0, 0.0),
                             GapPose.from_deg((0.0, 0.5, 2.1), -60.0, width_m=0.85, height_m=0.57),
                             LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0)), 2.6, 2.5, f450.traverse_lead_m,
                             BodyClearance(f450.body_box_m), w)
    plan = request.plan()
    rec = plan.recovery.trajectory
    assert _max_body_rate_rad_s(rec) <= w  # (the minimum-jerk one of the planner before asked 11.2 rad/s)
    assert rec.delta is not None  # the minimum-snap primitive
    t_end = plan.traverse.duration_s
    _, _, a_tr = plan.traverse.state(t_end)
    np.testing.assert_allclose(rec.jerk(0.0), 0.0, atol=1e-9)  # the ballistic traverse's jerk
    np.testing.assert_allclose(rec.state(0.0)[2], a_tr, atol=1e-12)
    np.testing.assert_allclose(rec.jerk(plan.recovery.duration_s), 0.0, atol=1e-6)
    np.testing.assert_allclose(rec.state(plan.recovery.duration_s)[0], plan.hover_m, atol=1e-9)
    limits = VehicleLimits(max_body_rate_rad_s=w)
    verdict = rec.input_feasible(limits.f_min_m_s2, limits.f_max_m_s2, w, limits.min_dt_s)
    assert verdict == Feasibility.FEASIBLE
    assert _max_body_rate_rad_s(rec) <= w
    # from the same traverse end, no minimum-jerk recovery is within the rate; the jerk-continuous one is
    pe, ve, ae = plan.traverse.state(t_end)
    u = tuple(plan.traverse.direction)
    clear = request.body.clearance_m
    room = request.lab
    kwargs = {"wall": (request.gap.centre_m, u), "margin_m": clear, "wall_margin_m": request.body.reach_m}
    with pytest.raises(PlanningError, match="no recovery duration"):
        search_recovery(pe, ve, ae, plan.hover_m, room, limits, **kwargs)
    again = search_recovery(pe, ve, ae, plan.hover_m, room, limits, jerk_m_s3=(0.0, 0.0, 0.0), **kwargs)
    assert again.duration_s == plan.recovery.duration_s and again.tried > len(RECOVERY_DURATIONS_S)
    rates = []
    for T in RECOVERY_DURATIONS_S:  # every minimum-jerk one in the lab, whatever its rate
        with contextlib.suppress(PlanningError):
            rates.append(_max_body_rate_rad_s(search_recovery(
                pe, ve, ae, plan.hover_m, room, VehicleLimits(max_body_rate_rad_s=100.0),
                durations_s=np.array([T]), **kwargs).trajectory))
    assert rates and min(rates) > 1.3 * w  # 8 rad/s and more
    # the planner's own limits (the default vehicle): the paper's minimum-jerk recovery, as before
    default = MissionRequest(request.start_pos_m, request.start_vel_m_s, request.gap, request.lab, 2.6, 2.5,
                             f450.traverse_lead_m, request.body).plan()
    assert default.recovery.trajectory.delta is None


def test_a_slow_vehicle_starts_as_high_as_its_approach_needs_and_a_fast_one_where_it_is() -> None:
    """The f450 (6 rad/s) through the -60 deg gap at 2.5 m/s from the 0.5 m take-off: the approaches
    that keep its 0.48 m floor clearance are short and turn it fast, and the plan crosses at 4.5 m/s in a
    2 s approach. From the start height the planner chooses (the lowest, 0.1 m apart, where the same
    stage of the search flies its first approach, with half a step of room) it crosses at the speed and
    in the approach duration asked for, turning slower. Where the plan from the take-off height is within
    the vehicle's own rate (the f450 through 30 deg), and for the default vehicle (the planner's own
    limits: its plans are as before), the start is the take-off height."""
    low = _f450_request(-60.0, 6.0)
    z = start_height(low)
    assert z == pytest.approx(1.85)
    assert z <= low.lab.max_m[2] - low.body.clearance_m
    before, after = low.plan(), dataclasses.replace(low, start_pos_m=(-2.0, -1.0, z)).plan()
    assert before.traverse.crossing_speed_m_s == 4.5 and float(before.approach.T) == pytest.approx(2.0)
    assert after.traverse.crossing_speed_m_s == low.crossing_speed_m_s == 2.5
    assert float(after.approach.T) == pytest.approx(low.approach_duration_s) and after.candidates_tried == 1
    assert _max_body_rate_rad_s(after.approach) < _max_body_rate_rad_s(before.approach)
    assert after.approach.state(0.0)[0][2] == pytest.approx(z)
    assert start_height(_f450_request(30.0, 6.0)) == 0.5
    assert start_height(_f450_request(-60.0, 15.0)) == 0.5


def test_the_start_and_its_plan_are_the_plan_from_that_start() -> None:
    """`start_plan` (the program's check before its take-off) gives the start height and the very plan
    `plan` makes from there: planned afresh where the start moves up, the search's own plan where it
    stays (made once)."""
    for request in (_f450_request(-60.0, 6.0), _f450_request(30.0, 6.0), _f450_request(-60.0, 15.0)):
        z, plan = start_plan(request)
        assert z == start_height(request)
        x, y, _ = request.start_pos_m
        again = dataclasses.replace(request, start_pos_m=(x, y, z)).plan()
        assert plan.packed.tobytes() == again.packed.tobytes()
        assert (plan.traverse.crossing_speed_m_s, plan.candidates_tried) == (
            again.traverse.crossing_speed_m_s, again.candidates_tried)
