"""Tests for policies.controller: the expert geometric controller's signs, limits and tracking."""

from __future__ import annotations

import math

import numpy as np
import pytest

from policies.controller import (
    AttitudeThrustCommand,
    ExpertController,
    ExpertGains,
    expert_command_batch,
    limit_tilt_step,
)
from policies.frames import euler_to_matrix
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
        # the same numbers: one law, compiled, for a batch (the RL environment's expert) and one vehicle
        assert (c.roll_rad, c.pitch_rad, c.yaw_rad, c.thrust_n) == (roll[i], pitch[i], yaw[i], thrust[i])
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


def test_a_tilt_step_limit_moves_roll_and_pitch_at_most_the_step_and_keeps_the_rest() -> None:
    """A command swinging from the tilt limit across (-65 to +40 deg roll) moves at most the step from
    the last one, each of roll and pitch; yaw and thrust as commanded; one within the step as it is."""
    last = AttitudeThrustCommand(math.radians(-65.0), math.radians(-2.0), 0.3, 5.0)
    swing = AttitudeThrustCommand(math.radians(40.0), math.radians(-30.0), 0.4, 12.0)
    out = limit_tilt_step(swing, last.roll_rad, last.pitch_rad, 0.06)
    assert out.roll_rad == pytest.approx(last.roll_rad + 0.06)
    assert out.pitch_rad == pytest.approx(last.pitch_rad - 0.06)
    assert (out.yaw_rad, out.thrust_n) == (0.4, 12.0)
    near = AttitudeThrustCommand(last.roll_rad + 0.05, last.pitch_rad - 0.01, 0.3, 6.0)
    assert limit_tilt_step(near, last.roll_rad, last.pitch_rad, 0.06) is near
