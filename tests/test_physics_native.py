"""Native physics: hover, free fall, ground contact, control signs, motor lag, wind, batch = single."""

from __future__ import annotations

import numpy as np
import pytest

from emulator.physics import make_backend
from emulator.physics.native import BatchPhysics, NativeBackend, hover_state
from emulator.physics.state import STATE_SIZE, VehicleState
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.vehicle import resting_state

PROFILE = load_profile("n3_tx2")
NO_DRAG = PROFILE.with_changes(linear_drag_n_s_m=(0.0, 0.0, 0.0), angular_drag_nm_s_rad=(0.0, 0.0, 0.0))
HOVER = PROFILE.hover_throttle
HALF_HEIGHT = 0.5 * PROFILE.body_box_m[2]


def _backend(profile=PROFILE, state: VehicleState | None = None) -> NativeBackend:
    b = NativeBackend(profile, dt_s=0.001)
    b.reset(state if state is not None else hover_state(profile, (0.0, 0.0, 10.0)))
    return b


def _throttle(front_right=0.0, rear_left=0.0, front_left=0.0, rear_right=0.0) -> np.ndarray:
    """Hover throttle plus the given offsets, in rotor order 0..3 (FR, RL, FL, RR)."""
    return HOVER + np.array([front_right, rear_left, front_left, rear_right])


def test_hover_holds_position_for_10_s() -> None:
    b = _backend()
    b.step(np.full(4, HOVER), 10_000)
    s = b.state
    assert s.time_s == pytest.approx(10.0)
    assert np.linalg.norm(s.pos_m - [0.0, 0.0, 10.0]) < 0.01
    assert np.linalg.norm(s.accel_m_s2) < 1e-3


def test_free_fall_matches_closed_form() -> None:
    b = _backend(NO_DRAG, VehicleState(pos_m=[1.0, 2.0, 100.0]))
    for _ in range(1000):  # one step per call, as the flight controller drives it
        b.step(np.zeros(4))
    s = b.state
    assert s.pos_m[2] == pytest.approx(100.0 - 0.5 * GRAVITY_M_S2, abs=1e-3)
    assert s.vel_m_s[2] == pytest.approx(-GRAVITY_M_S2, abs=1e-6)
    assert s.accel_m_s2 == pytest.approx([0.0, 0.0, -GRAVITY_M_S2])
    assert s.pos_m[:2] == pytest.approx([1.0, 2.0])


def test_rests_on_the_ground_without_drift_or_jitter() -> None:
    b = _backend(state=resting_state(PROFILE, 3.0, -2.0, yaw_rad=0.0))
    heights = []
    for _ in range(2000):
        b.step(np.full(4, 0.5 * HOVER))  # spinning, but below hover
        heights.append(b.state.pos_m[2])
    s = b.state
    assert np.all(np.array(heights) == HALF_HEIGHT)
    assert s.pos_m[:2] == pytest.approx([3.0, -2.0], abs=1e-12)
    assert np.all(s.vel_m_s == 0.0)
    assert s.accel_m_s2 == pytest.approx([0.0, 0.0, 0.0])


def test_fast_fall_never_tunnels_and_does_not_bounce() -> None:
    b = _backend(state=VehicleState(pos_m=[0.0, 0.0, 3.0], vel_m_s=[4.0, 0.0, -20.0]))
    bottoms, vz = [], []
    for _ in range(1500):
        b.step(np.zeros(4))
        bottoms.append(b.state.pos_m[2] - HALF_HEIGHT)
        vz.append(b.state.vel_m_s[2])
    assert min(bottoms) >= 0.0
    assert max(vz) <= 0.0  # never moves up again: no bounce
    s = b.state
    assert s.pos_m[2] == HALF_HEIGHT
    assert np.all(s.vel_m_s == 0.0)  # friction stopped the slide
    # 0.14 s of fall at 4 m/s, then a slide under friction 0.5 g (and drag): not frictionless, not stuck.
    assert 4.0 * 0.14 + 0.5 < s.pos_m[0] < 4.0 * 0.14 + 4.0**2 / (2 * 0.5 * GRAVITY_M_S2)


def test_takes_off_when_thrust_exceeds_weight() -> None:
    b = _backend(state=resting_state(PROFILE, yaw_rad=0.0))
    b.step(np.full(4, 0.95 * HOVER), 1000)
    assert b.state.pos_m[2] == HALF_HEIGHT
    b.step(np.full(4, 1.2 * HOVER), 1000)
    assert b.state.pos_m[2] > HALF_HEIGHT + 0.1
    assert b.state.vel_m_s[2] > 0.0


# Torque about FLU x is sum(y_i f_i): the left rotors (y > 0) pushing harder raise the left side,
# a positive roll (right side down, "rolling right"); the tilted thrust then pushes the vehicle to -y.
# Torque about y is -sum(x_i f_i): more front thrust raises the nose, a negative pitch about FLU y
# (nose-up), and the vehicle accelerates backwards (-x). Counter-clockwise rotors (0, 1) react
# clockwise, so more throttle on them yaws the vehicle clockwise: negative rate about z.
@pytest.mark.parametrize(
    ("cmd", "axis", "sign", "vel_axis", "vel_sign"),
    [
        (_throttle(rear_left=0.02, front_left=0.02, front_right=-0.02, rear_right=-0.02), 0, 1, 1, -1),
        (_throttle(front_right=0.02, front_left=0.02, rear_left=-0.02, rear_right=-0.02), 1, -1, 0, -1),
        (_throttle(front_right=0.05, rear_left=0.05, front_left=-0.05, rear_right=-0.05), 2, -1, None, 0),
    ],
    ids=["left-up-rolls-right", "front-up-pitches-nose-up", "ccw-rotors-yaw-clockwise"],
)
def test_differential_throttle_signs(cmd, axis: int, sign: int, vel_axis, vel_sign: int) -> None:
    b = _backend()
    b.step(cmd, 300)
    omega = b.state.omega_rad_s
    assert sign * omega[axis] > 0.2
    others = [i for i in range(3) if i != axis]
    assert np.all(np.abs(omega[others]) < 1e-3 * abs(omega[axis]))
    if vel_axis is not None:
        assert vel_sign * b.state.vel_m_s[vel_axis] > 0.0
    # The attitude quaternion stays unit length.
    assert np.linalg.norm(b.state.quat_wxyz) == pytest.approx(1.0, abs=1e-12)


def test_motor_lag_follows_the_time_constant() -> None:
    tau = PROFILE.motor_time_constant_s
    b = _backend(state=VehicleState(pos_m=[0.0, 0.0, 50.0]))
    w_target = np.sqrt(0.64) * PROFILE.max_rotor_speed_rad_s
    n_tau = round(tau / b.dt_s)
    b.step(np.full(4, 0.64), n_tau)
    assert b.state.rotor_speed_rad_s == pytest.approx(np.full(4, (1 - np.exp(-1)) * w_target), rel=1e-6)
    b.step(np.full(4, 0.64), 4 * n_tau)
    assert b.state.rotor_speed_rad_s == pytest.approx(np.full(4, (1 - np.exp(-5)) * w_target), rel=1e-6)


def test_wind_force_accelerates_as_f_over_m() -> None:
    b = _backend(NO_DRAG, hover_state(NO_DRAG, (0.0, 0.0, 10.0)))
    force = np.array([0.45, -0.9, 0.18])
    b.set_external_force(force)
    b.step(np.full(4, HOVER), 1000)
    s = b.state
    assert s.accel_m_s2 == pytest.approx(force / PROFILE.mass_kg, rel=1e-6)
    assert s.vel_m_s == pytest.approx(force / PROFILE.mass_kg * 1.0, rel=1e-6)
    b.set_external_force(np.zeros(3))
    b.step(np.full(4, HOVER), 10)
    assert np.linalg.norm(b.state.accel_m_s2) < 1e-6


def _random_states(rng: np.random.Generator, n: int) -> np.ndarray:
    x = np.zeros((n, STATE_SIZE))
    x[:, 0:3] = rng.uniform(-5, 5, (n, 3))
    x[:, 2] += 10.0
    x[:, 3:6] = rng.normal(0, 2, (n, 3))
    q = rng.normal(0, 1, (n, 4))
    x[:, 6:10] = q / np.linalg.norm(q, axis=1, keepdims=True)
    x[:, 10:13] = rng.normal(0, 1, (n, 3))
    x[:, 13:17] = rng.uniform(300, 900, (n, 4))
    return x


def test_batch_equals_single_runs_exactly() -> None:
    rng = np.random.default_rng(7)
    n = 6
    states = _random_states(rng, n)
    states[1, 2] = 0.3  # one starts near the ground
    cmds = rng.uniform(0, 1, (n, 4))
    forces = rng.normal(0, 1, (n, 3))
    batch = BatchPhysics(PROFILE, n)
    batch.reset(states)
    batch.set_external_force(forces)
    for _ in range(50):
        batch.step(cmds, 4)
    for i in range(n):
        single = _backend(state=VehicleState.from_vector(states[i]))
        single.set_external_force(forces[i])
        for _ in range(200):
            single.step(cmds[i])
        assert np.array_equal(single.state_vector(), batch.states[i])
        assert np.array_equal(single.state.accel_m_s2, batch.accelerations[i])
    # Identical inputs give identical rows.
    same = BatchPhysics(PROFILE, 4)
    same.reset(states[0])
    same.set_external_force(forces[0])
    same.step(cmds[0], 200)
    assert np.all(same.states == batch.states[0])
    # Its clock tells the time of the steps taken, as a compiled caller that steps it reads it.
    t0_s, steps = same.clock
    assert steps == 200 and t0_s + steps * same.dt_s == same.time_s


def test_batch_rows_are_independent() -> None:
    rng = np.random.default_rng(11)
    states = _random_states(rng, 5)
    cmds = rng.uniform(0, 1, (5, 4))
    ref, other = BatchPhysics(PROFILE, 5), BatchPhysics(PROFILE, 5)
    ref.reset(states)
    other.reset(states)
    cmds2 = cmds.copy()
    cmds2[2] = [1.0, 0.0, np.nan, 0.3]
    other.set_external_force(np.array([[0, 0, 0]] * 2 + [[5.0, 0, 0]] + [[0, 0, 0]] * 2))
    other.reset(VehicleState(pos_m=[0, 0, 40.0]), rows=[2])
    ref.step(cmds, 100)
    other.step(cmds2, 100)
    keep = [0, 1, 3, 4]
    assert np.array_equal(ref.states[keep], other.states[keep])
    assert not np.array_equal(ref.states[2], other.states[2])
    assert batch_views_are_read_only(other)


def batch_views_are_read_only(batch: BatchPhysics) -> bool:
    with pytest.raises(ValueError):
        batch.positions[0, 0] = 1.0
    return batch.positions.shape == (batch.n, 3) and batch.states.shape == (batch.n, 17)


def test_bad_inputs_give_clear_errors_or_failsafe() -> None:
    b = _backend()
    with pytest.raises(ValueError, match="motor_cmd"):
        b.step(np.zeros(3))
    with pytest.raises(ValueError, match="n_steps"):
        b.step(np.zeros(4), -1)
    with pytest.raises(ValueError, match="non-finite"):
        b.set_external_force([0.0, np.inf, 0.0])
    with pytest.raises(ValueError, match="zero length"):
        b.reset(VehicleState(quat_wxyz=[0, 0, 0, 0]))
    with pytest.raises(ValueError, match="dt_s"):
        NativeBackend(PROFILE, dt_s=0.0)
    with pytest.raises(ValueError, match="motor_cmd"):
        BatchPhysics(PROFILE, 3).step(np.zeros((2, 4)))
    # Failsafe: a NaN throttle stops that motor; throttles above 1 are clipped.
    b.step(np.array([np.nan, 2.0, HOVER, HOVER]), 500)
    w = b.state.rotor_speed_rad_s
    assert w[0] < 1.0
    assert w[1] == pytest.approx(PROFILE.max_rotor_speed_rad_s, rel=1e-4)
    assert np.all(np.isfinite(b.state_vector()))


def test_make_backend_gives_native_and_state_round_trips() -> None:
    b = make_backend("native", PROFILE)
    assert isinstance(b, NativeBackend)
    start = VehicleState(
        time_s=2.5, pos_m=[1, 2, 3], quat_wxyz=[0.5, 0.5, 0.5, 0.5], rotor_speed_rad_s=[1, 2, 3, 4]
    )
    b.reset(start)
    assert np.array_equal(b.state.to_vector(), start.to_vector())
    b.step(np.zeros(4), 250)
    assert b.state.time_s == pytest.approx(2.75)
    b.close()
    b.close()


def test_a_caller_stepping_the_kernel_arrays_keeps_the_batch_and_its_clock() -> None:
    # what a batched FC loop fused with the physics does: step the rows in place, then count the steps
    from emulator.physics.kernels import step_vehicle

    fused, ref = BatchPhysics(PROFILE, 3), BatchPhysics(PROFILE, 3)
    for b in (fused, ref):
        b.reset(hover_state(PROFILE))
    cmd = np.full(4, PROFILE.hover_throttle * 1.05)
    x, aux, p = fused.kernel_arrays
    for i in range(3):
        step_vehicle(x[i], aux[i], p, cmd, 50)
    fused.advance_clock(50)
    ref.step(cmd, 50)
    assert np.array_equal(fused.states, ref.states) and fused.time_s == ref.time_s == pytest.approx(0.05)
