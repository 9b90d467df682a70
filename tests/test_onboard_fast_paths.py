"""The onboard program's per-step shortcuts give the same numbers as the general code: the plan's reference
in plain floats, the batched plane checks of the recovery search, the controller's one-pass input check,
the estimator's lazy attitude and the mocap reader's samples."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.link.linktrack import BodySample, MocapPacket, encode_mocap_payload
from hil.link.memory import MemoryTransport
from policies.controller import ExpertController, expert_command_batch
from policies.frames import matrix_to_euler, quat_to_matrix
from policies.gap_planning import (
    RECOVERY_DURATIONS_S,
    GapPose,
    LabVolume,
    Segment,
    VehicleLimits,
    plan_mission,
    search_recovery,
)
from policies.mocap_reader import MocapReader, PoseSample
from policies.onboard.estimator import PoseEstimator
from policies.primitives import Feasibility, solve

LAB = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))


def _plan(roll_deg: float = -60.0):
    gap = GapPose.from_deg((0.0, 0.5, 2.1), roll_deg, width_m=0.8, height_m=0.45)
    return plan_mission((-2.0, -1.0, 0.5), gap, LAB, crossing_speed_m_s=2.5, d_min_m=0.25)


def test_reference_in_floats_is_the_reference_in_every_segment():
    plan = _plan()
    times = np.concatenate([[-0.5, 0.0], np.linspace(0.0, plan.t_hover_start_s + 1.0, 301)])
    seen = set()
    for t in times:
        ref = plan.reference(float(t))
        p, v, a, yaw = plan.reference_tuples(float(t))
        seen.add(ref.segment)
        assert np.array_equal(ref.pos_m, p) and np.array_equal(ref.vel_m_s, v)
        assert np.array_equal(ref.acc_m_s2, a) and yaw == ref.yaw_rad
        assert all(type(x) is float for x in (*p, *v, *a))
    assert seen == set(Segment)


def test_single_trajectory_floats_match_the_array_evaluation():
    traj = solve((0.1, -2.0, 0.5), (0.3, 0.2, -0.1), (0.0, 0.5, 0.2), (1.0, 0.0, 1.5), (0.0, 2.0, 0.0),
                 (0.0, 0.0, -3.0), 2.6)
    for t in (0.0, 0.37, 1.3, 2.6, 3.1):
        p, v, a = traj.state(np.array([t]))  # the array path
        pf, vf, af = traj.state_tuples(t)
        assert np.array_equal(p[0], pf) and np.array_equal(v[0], vf) and np.array_equal(a[0], af)
    batch = solve(np.zeros((2, 3)), np.zeros(3), np.zeros(3), np.ones(3), np.zeros(3), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="single trajectory"):
        batch.state_tuples(0.5)


@pytest.mark.parametrize("start", [(-2.0, -1.0, 0.5), (1.5, 1.2, 1.0), (0.0, 2.4, 2.0), (-4.0, 0.5, 3.2)])
def test_batched_plane_checks_pick_the_recovery_the_plane_by_plane_checks_pick(start):
    hover = np.array([0.5, 2.5, 1.0])
    wall = (np.array([0.0, 0.5, 2.1]), np.array([0.0, 1.0, 0.0]))
    vel = np.array([0.0, 2.0, -0.5])
    traj = solve(start, vel, np.zeros(3), hover, np.zeros(3), np.zeros(3), RECOVERY_DURATIONS_S)
    ok = np.ones(traj.batch_shape, dtype=bool)
    for point, normal in LAB.half_spaces():
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
            search_recovery(start, vel, np.zeros(3), hover, LAB, wall=wall_arg, margin_m=0.2)
        return
    res = search_recovery(start, vel, np.zeros(3), hover, LAB, wall=wall_arg, margin_m=0.2)
    assert res.tried == good[0] + 1 and res.duration_s == float(RECOVERY_DURATIONS_S[good[0]])


def test_controller_checks_every_input_and_names_the_bad_one():
    ctl = ExpertController(0.9)
    rng = np.random.default_rng(7)
    for _ in range(50):
        pr, vr, ar, p, v = (rng.normal(size=3) for _ in range(5))
        yaw = float(rng.uniform(-3, 3))
        cmd = ctl.command(tuple(pr), vr, list(ar), yaw, p, v)
        roll, pitch, _, thrust = expert_command_batch(pr, vr, ar, yaw, p, v, 0.9)
        assert cmd.roll_rad == pytest.approx(float(roll), abs=1e-12)
        assert cmd.pitch_rad == pytest.approx(float(pitch), abs=1e-12)
        assert cmd.thrust_n == pytest.approx(float(thrust), abs=1e-12) and cmd.yaw_rad == yaw
    z = np.zeros(3)
    for k, name in enumerate(("pos_ref_m", "vel_ref_m_s", "acc_ref_m_s2", "pos_m", "vel_m_s")):
        for bad in (np.array([0.0, math.nan, 0.0]), (0.0, math.inf), "abc", None):
            args = [z, z, z, z, z]
            args[k] = bad
            with pytest.raises(ValueError, match=name):
                ctl.command(args[0], args[1], args[2], 0.0, args[3], args[4])
    # finite inputs whose sum overflows are still accepted (errors are clipped, so the command is sane)
    cmd = ctl.command((1e308, 1e308, 1e308), z, z, 0.0, z, z)
    assert math.isfinite(cmd.thrust_n) and cmd.thrust_n > 0
    with pytest.raises(ValueError, match="yaw"):
        ctl.command(z, z, z, math.nan, z, z)


def test_estimator_attitude_follows_the_latest_pose():
    est = PoseEstimator()
    rng = np.random.default_rng(3)
    for k in range(20):
        q = rng.normal(size=4)
        assert est.update(0.01 * (k + 1), np.array([0.1 * k, 0.0, 1.0]), q * 2.0, 0.01 * (k + 1) + 0.028)
        if k % 3:
            continue  # the attitude of poses nobody asked about is never computed, but must still be right
        e = est.estimate(0.01 * (k + 1) + 0.03)
        want = matrix_to_euler(quat_to_matrix(q))
        assert np.allclose(e.euler_rad, want, atol=1e-12)
        assert np.allclose(e.quat_wxyz, q / np.linalg.norm(q), atol=1e-15)
    assert not est.update(1.0, (0.0, math.nan, 0.0), (1.0, 0.0, 0.0, 0.0), 1.0)
    assert not est.update(1.0, (0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 1.0)
    assert est.rejected == 2 and est.updates == 20


def test_reader_samples_are_ordinary_pose_samples():
    a, _b = MemoryTransport.pair()
    got: list[PoseSample] = []
    reader = MocapReader(a, on_sample=got.append)
    packet = MocapPacket(42, (BodySample(1, 1.5, (1.0, 2.0, 3.0), (1.004, 0.0, 0.0, 0.0)),
                              BodySample(7, 1.5, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
                              BodySample(2, 1.5, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), valid=False),
                              BodySample(3, 1.5, (0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0))))
    assert reader._take(encode_mocap_payload(packet), 2.0) == 1
    assert [s.name for s in got] == ["vehicle", "body7"]
    want = PoseSample("vehicle", 1, np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.0, 0.0, 0.0]), 1.5, 2.0, 42)
    s = got[0]
    assert repr(s) == repr(want) and s.frame_no == 42 and s.age_s(2.25) == 0.25
    with pytest.raises(AttributeError):
        s.stamp_s = 0.0  # type: ignore[misc]
    assert reader.latest("vehicle") is s and reader.latest(7) is got[1] and reader.latest("body7") is got[1]
    assert reader.latest("gap") is None and reader.counters.bodies_invalid == 1
    assert reader.counters.bodies_bad_quat == 1  # body 3's quaternion of norm 2
    with pytest.raises(KeyError, match="unknown body"):
        reader.latest("wing")
