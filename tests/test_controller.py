"""Tests for policies.controller: the expert geometric controller's signs, limits and tracking."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.link.mavlink import (
    quat_enu_flu_to_ned_frd,
    quat_enu_flu_to_ned_frd_tuple,
    quat_from_euler,
    quat_from_euler_tuple,
)
from policies.controller import ExpertController, ExpertGains, expert_command_batch
from policies.frames import euler_to_matrix, matrix_to_euler, quat_to_matrix
from policies.gap_planning import GapPose, LabVolume, plan_mission
from policies.primitives import solve

M = 0.9
Z3 = np.zeros(3)


def test_hover_is_level_with_weight_thrust() -> None:
    ctl = ExpertController(M)
    for yaw in (0.0, 0.7, -2.0):
        cmd = ctl.command([1, 2, 1.5], Z3, Z3, yaw, [1, 2, 1.5], Z3)
        assert cmd.roll_rad == pytest.approx(0.0, abs=1e-12)
        assert cmd.pitch_rad == pytest.approx(0.0, abs=1e-12)
        assert cmd.thrust_n == pytest.approx(M * 9.8, rel=1e-12)
        assert cmd.yaw_rad == yaw


def test_small_errors_give_correctly_signed_commands() -> None:
    ctl = ExpertController(M)
    ahead_x = ctl.command([0.1, 0, 1], Z3, Z3, 0.0, [0, 0, 1], Z3)  # target ahead in +x
    assert ahead_x.pitch_rad > 0 and abs(ahead_x.roll_rad) < 1e-12  # nose down accelerates +x (FLU/ENU)
    left_y = ctl.command([0, 0.1, 1], Z3, Z3, 0.0, [0, 0, 1], Z3)  # target to the left (+y)
    assert left_y.roll_rad < 0 and abs(left_y.pitch_rad) < 1e-12  # body z = (., -sin roll, .)
    up = ctl.command([0, 0, 1.1], Z3, Z3, 0.0, [0, 0, 1], Z3)
    assert up.thrust_n > M * 9.8 and abs(up.roll_rad) + abs(up.pitch_rad) < 1e-12
    slow_down = ctl.command(Z3, Z3, Z3, 0.0, Z3, [0.5, 0, 0])  # moving +x too fast: pitch back
    assert slow_down.pitch_rad < 0
    # the commanded attitude's body z is along the commanded force: check against R = Rz Ry Rx
    cmd = ctl.command([0.1, -0.2, 1.05], [0.3, 0.1, 0], [1, 2, 0.5], 0.4, [0, 0, 1], Z3)
    z_b = euler_to_matrix(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad)[:, 2]
    ep = np.array([0.1, -0.2, 0.05])
    force = M * (np.array([2.25, 2.25, 4.5]) * (np.array([0.3, 0.1, 0]) + np.array([6.5, 6.5, 8.5]) * ep)
                 + [0, 0, 9.8]) + M * 0.9 * np.array([1, 2, 0.5])
    np.testing.assert_allclose(z_b * cmd.thrust_n, force, rtol=1e-12)


def test_errors_are_clipped_and_tilt_is_limited() -> None:
    ctl = ExpertController(M)
    near = ctl.command([0.3, 0, 1], Z3, Z3, 0.0, [0, 0, 1], Z3)
    far = ctl.command([30, 0, 1], Z3, Z3, 0.0, [0, 0, 1], Z3)
    assert far == near  # 0.3 m clip
    fast = ctl.command(Z3, [50, 0, 0], Z3, 0.0, Z3, Z3)
    assert fast == ctl.command(Z3, [2, 0, 0], Z3, 0.0, Z3, Z3)  # 2 m/s clip
    rng = np.random.default_rng(7)
    acc = rng.normal(0, 60, (2000, 3))
    roll, pitch, _, thrust = expert_command_batch(np.zeros((2000, 3)), Z3, acc, 0.0, Z3, Z3, M)
    tilt = np.arccos(np.cos(roll) * np.cos(pitch))
    assert tilt.max() <= math.radians(75) + 1e-9
    assert tilt.max() > math.radians(74.9)  # the limit is reached, not undershot
    assert np.all(thrust > 0)
    tighter = ExpertGains(tilt_max_rad=math.radians(35))
    roll, pitch, _, _ = expert_command_batch(np.zeros((2000, 3)), Z3, acc, 0.0, Z3, Z3, M, tighter)
    assert np.arccos(np.cos(roll) * np.cos(pitch)).max() <= math.radians(35) + 1e-9


def test_batch_matches_single_and_bad_input_raises() -> None:
    rng = np.random.default_rng(8)
    n = 50
    args = [rng.normal(0, 1, (n, 3)) for _ in range(3)] + [rng.uniform(-3, 3, n)] + \
        [rng.normal(0, 1, (n, 3)) for _ in range(2)]
    roll, pitch, yaw, thrust = expert_command_batch(*args, mass_kg=1.3)
    ctl = ExpertController(1.3)
    for i in range(n):
        c = ctl.command(args[0][i], args[1][i], args[2][i], float(args[3][i]), args[4][i], args[5][i])
        assert (c.roll_rad, c.pitch_rad, c.yaw_rad, c.thrust_n) == pytest.approx(
            (roll[i], pitch[i], yaw[i], thrust[i]), rel=1e-12, abs=1e-12)
    with pytest.raises(ValueError):
        ctl.command([0, 0, np.nan], Z3, Z3, 0.0, Z3, Z3)
    with pytest.raises(ValueError):
        ctl.command([0, 0], Z3, Z3, 0.0, Z3, Z3)
    with pytest.raises(ValueError):
        ExpertController(0.0)


def _simulate(reference, t_end: float, p0: np.ndarray, dt: float = 0.001, tau_att: float = 0.03) -> float:
    """Point mass with a first-order attitude response and exact thrust; returns the worst position
    error (m) against the reference."""
    ctl = ExpertController(M)
    p, v = p0.astype(float).copy(), np.zeros(3)
    roll = pitch = yaw = 0.0
    worst = 0.0
    for k in range(round(t_end / dt)):
        t = k * dt
        pr, vr, ar, yr = reference(t)
        worst = max(worst, float(np.linalg.norm(pr - p)))
        cmd = ctl.command(pr, vr, ar, yr, p, v)
        alpha = dt / tau_att
        roll += alpha * (cmd.roll_rad - roll)
        pitch += alpha * (cmd.pitch_rad - pitch)
        yaw += alpha * (cmd.yaw_rad - yaw)
        acc = euler_to_matrix(roll, pitch, yaw)[:, 2] * cmd.thrust_n / M + np.array([0, 0, -9.8])
        p = p + v * dt + acc * dt * dt / 2
        v = v + acc * dt
    return worst


def test_tracks_a_primitive_within_a_few_cm() -> None:
    traj = solve([0, 0, 1], Z3, Z3, [2, 1, 1.5], [1, 0, 0], Z3, 2.5)

    def ref(t: float):
        p, v, a = traj.state(min(t, 2.5))
        return p, v, a, 0.0

    worst = _simulate(ref, 2.5, np.array([0.0, 0.0, 1.0]))
    assert worst < 0.03


def test_tracks_the_paper_approach_and_traverse() -> None:
    gap = GapPose.from_deg((0.0, 0.5, 2.1), -60.0, width_m=0.8, height_m=0.35)
    plan = plan_mission((-2.0, -1.0, 0.5), gap, LabVolume((-4, -3, 0), (4, 4, 4)))

    def ref(t: float):
        r = plan.reference(t)
        return r.pos_m, r.vel_m_s, r.acc_m_s2, r.yaw_rad

    worst = _simulate(ref, plan.t_recovery_start_s, np.array([-2.0, -1.0, 0.5]))
    assert worst < 0.1  # Ka = 0.9 leaves 10 % of the 8.5 m/s^2 traverse feed-forward to feedback


def test_plain_float_helpers_agree_with_the_array_ones():
    rng = np.random.default_rng(7)
    ctrl = ExpertController(0.9)
    for _ in range(300):
        q = rng.normal(size=4)
        np.testing.assert_allclose(quat_to_matrix(q), quat_to_matrix(q[None])[0], atol=1e-15)
        r = quat_to_matrix(q)
        assert matrix_to_euler(r) == pytest.approx([float(x[0]) for x in matrix_to_euler(r[None])], abs=1e-14)
        qu = q / np.linalg.norm(q)
        want = list(quat_enu_flu_to_ned_frd(qu))
        assert quat_enu_flu_to_ned_frd_tuple(*qu) == pytest.approx(want, abs=1e-15)
        e = rng.uniform(-3, 3, 3)
        assert quat_from_euler_tuple(*e) == pytest.approx(list(quat_from_euler(*e)), abs=1e-15)
        a = [rng.normal(0.0, s, 3) for s in (0.5, 2.0, 8.0, 0.5, 2.0)]
        yaw = float(rng.uniform(-math.pi, math.pi))
        cmd = ctrl.command(a[0], a[1], a[2], yaw, a[3], a[4])
        roll, pitch, _, thrust = expert_command_batch(a[0], a[1], a[2], yaw, a[3], a[4], 0.9)
        assert (cmd.roll_rad, cmd.pitch_rad, cmd.thrust_n) == pytest.approx(
            (float(roll), float(pitch), float(thrust)), abs=1e-12
        )
    with pytest.raises(ValueError):
        quat_to_matrix(np.zeros(4))
    with pytest.raises(ValueError):
        ctrl.command([0.0, 0.0], [0.0] * 3, [0.0] * 3, 0.0, [0.0] * 3, [0.0] * 3)
    with pytest.raises(ValueError):
        ctrl.command([0.0, 0.0, math.nan], [0.0] * 3, [0.0] * 3, 0.0, [0.0] * 3, [0.0] * 3)
