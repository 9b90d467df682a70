"""The JSBSim backend on its own: hover, free fall, ground contact, frames, the Earth model, cleanup."""

from __future__ import annotations

import math

import numpy as np
import pytest

from emulator.physics import make_backend
from emulator.physics.jsbsim_backend import JSBSimBackend
from emulator.physics.state import VehicleState
from emulator.profile import GRAVITY_M_S2, load_profile

G = np.array([0.0, 0.0, -GRAVITY_M_S2])


@pytest.fixture(scope="module")
def profile():
    return load_profile("n3_tx2")


@pytest.fixture
def backend(profile):
    b = JSBSimBackend(profile)
    yield b
    b.close()


def hover_speed(profile) -> float:
    return math.sqrt(profile.hover_throttle) * profile.max_rotor_speed_rad_s


def test_registered_under_its_name(profile):
    b = make_backend("jsbsim", profile, dt_s=0.002)
    try:
        assert isinstance(b, JSBSimBackend) and b.dt_s == 0.002
    finally:
        b.close()


def test_hover_holds_position_and_attitude(backend, profile):
    backend.reset(VehicleState(pos_m=[1.0, -2.0, 1.5], rotor_speed_rad_s=[hover_speed(profile)] * 4))
    backend.step(np.full(4, profile.hover_throttle), 2000)
    s = backend.state
    assert s.time_s == pytest.approx(2.0)
    np.testing.assert_allclose(s.pos_m, [1.0, -2.0, 1.5], atol=1e-4)
    np.testing.assert_allclose(s.vel_m_s, 0.0, atol=1e-4)
    assert abs(s.quat_wxyz[0]) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(s.rotor_speed_rad_s, hover_speed(profile), rtol=1e-12)


def test_free_fall_follows_g_t_squared(backend, profile):
    """Without drag, a dropped vehicle falls g t^2 / 2 and reports the world acceleration -g."""
    b = JSBSimBackend(profile.with_changes(linear_drag_n_s_m=[0.0, 0.0, 0.0]))
    try:
        b.reset(VehicleState(pos_m=[0.0, 0.0, 20.0]))
        b.step(np.zeros(4), 1500)
        s = b.state
        assert s.pos_m[2] == pytest.approx(20.0 - 0.5 * GRAVITY_M_S2 * 1.5**2, abs=1e-4)
        assert s.vel_m_s[2] == pytest.approx(-GRAVITY_M_S2 * 1.5, abs=1e-4)
        np.testing.assert_allclose(s.accel_m_s2, G, atol=1e-4)
    finally:
        b.close()


def test_rests_on_the_ground_at_box_bottom(backend, profile):
    half_h = profile.body_box_m[2] / 2
    backend.reset(VehicleState(pos_m=[0.0, 0.0, 0.5]))
    backend.step(np.zeros(4), 3000)
    s = backend.state
    assert s.pos_m[2] - half_h == pytest.approx(0.0, abs=2e-4)  # box bottom at z = 0
    np.testing.assert_allclose(s.vel_m_s, 0.0, atol=1e-3)
    # Below lift-off thrust it stays put (the contact springs only unload: under 0.4 mm); above it
    # it climbs.
    backend.step(np.full(4, 0.9 * profile.hover_throttle), 500)
    assert backend.state.pos_m[2] - half_h == pytest.approx(0.0, abs=4e-4)
    backend.step(np.full(4, 1.3 * profile.hover_throttle), 1000)
    assert backend.state.pos_m[2] > half_h + 0.3


@pytest.mark.parametrize("vz", [-3.0, -10.0])
def test_hard_landing_does_not_tunnel(backend, profile, vz):
    """The box sinks a few centimetres at most, bounces (restitution about 0.4) and comes to rest."""
    half_h = profile.body_box_m[2] / 2
    backend.reset(VehicleState(pos_m=[0.0, 0.0, 0.4], vel_m_s=[0.0, 0.0, vz]))
    lowest = np.inf
    for _ in range(3000):
        backend.step(np.zeros(4))
        lowest = min(lowest, backend.state.pos_m[2] - half_h)
    assert -0.06 < lowest < 0.0
    assert backend.state.pos_m[2] - half_h == pytest.approx(0.0, abs=2e-4)


def test_tumbling_crashes_settle_on_the_ground(backend, profile):
    """Random attitudes, spins and impacts: the box never sinks far, nothing blows up."""
    rng = np.random.default_rng(7)
    corners = (
        np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)])
        * np.array(profile.body_box_m)
        / 2
    )
    for _ in range(4):
        q = rng.normal(size=4)
        backend.reset(
            VehicleState(
                pos_m=[0.0, 0.0, 1.0],
                vel_m_s=rng.uniform(-4, 4, 3) + np.array([0.0, 0.0, -3.0]),
                quat_wxyz=q / np.linalg.norm(q),
                omega_rad_s=rng.uniform(-10, 10, 3),
            )
        )
        for _ in range(1500):
            backend.step(np.zeros(4))
            s = backend.state
            low = s.pos_m[2] + (corners @ s.rotation_matrix().T)[:, 2].min()
            assert low > -0.08
        assert np.all(np.isfinite(s.to_vector())) and np.abs(s.vel_m_s).max() < 2.0


def test_frames_roll_pitch_yaw_signs(backend, profile):
    """Left rotors up -> +roll (FLU x); front rotors up -> nose up (-pitch rate about FLU y);
    counter-clockwise rotors faster -> the body yaws clockwise (-z)."""
    h, d = profile.hover_throttle, 0.05
    cases = {
        0: (np.array([h, h + d, h + d, h]), +1),  # rotors 1, 2 are on the left
        1: (np.array([h + d, h, h + d, h]), -1),  # rotors 0, 2 are in front
        2: (np.array([h + d, h + d, h, h]), -1),  # rotors 0, 1 spin counter-clockwise
    }
    for axis, (cmd, sign) in cases.items():
        backend.reset(VehicleState(pos_m=[0.0, 0.0, 2.0], rotor_speed_rad_s=[hover_speed(profile)] * 4))
        backend.step(cmd, 100)
        w = backend.state.omega_rad_s
        assert np.sign(w[axis]) == sign and abs(w[axis]) > 10 * np.abs(np.delete(w, axis)).max()


def test_reset_round_trips_a_general_state(backend):
    q = np.array([math.cos(0.6), 0.3 * math.sin(0.6), -0.5 * math.sin(0.6), 0.812404 * math.sin(0.6)])
    q /= np.linalg.norm(q)
    s0 = VehicleState(
        time_s=3.5,
        pos_m=[4.0, -7.0, 12.0],
        vel_m_s=[1.0, 2.0, -3.0],
        quat_wxyz=q,
        omega_rad_s=[0.4, -0.2, 1.1],
    )
    backend.reset(s0)
    s = backend.state
    assert s.time_s == 3.5
    np.testing.assert_allclose(s.pos_m, s0.pos_m, atol=1e-6)
    np.testing.assert_allclose(s.vel_m_s, s0.vel_m_s, atol=1e-9)
    np.testing.assert_allclose(s.quat_wxyz * np.sign(s.quat_wxyz[0] * q[0]), q, atol=1e-9)
    np.testing.assert_allclose(s.omega_rad_s, s0.omega_rad_s, atol=1e-9)


def test_external_force_acts_in_world_enu(backend):
    backend.reset(VehicleState(pos_m=[0.0, 0.0, 5.0]))
    m = backend.profile.mass_kg
    backend.set_external_force(np.array([m * 1.0, -m * 2.0, m * GRAVITY_M_S2]))  # cancels gravity
    backend.step(np.zeros(4), 10)
    np.testing.assert_allclose(backend.state.accel_m_s2, [1.0, -2.0, 0.0], atol=0.01)
    backend.reset(VehicleState(pos_m=[0.0, 0.0, 5.0]))  # the force is kept across a reset
    backend.step(np.zeros(4), 10)
    np.testing.assert_allclose(backend.state.accel_m_s2, [1.0, -2.0, 0.0], atol=0.01)


def test_round_earth_is_flat_to_a_millimetre_over_ten_seconds(profile):
    """A 10 s drag-free ballistic flight (50 m across, 128 m up) against the flat-world parabola."""
    b = JSBSimBackend(profile.with_changes(linear_drag_n_s_m=[0.0, 0.0, 0.0]))
    try:
        p0, v0 = np.array([1.0, 2.0, 1.0]), np.array([4.0, -3.0, 50.0])
        b.reset(VehicleState(pos_m=p0, vel_m_s=v0))
        b.step(np.zeros(4), 10_000)
        s = b.state
        np.testing.assert_allclose(s.pos_m, p0 + v0 * 10.0 + 0.5 * G * 100.0, atol=1e-3)
        np.testing.assert_allclose(s.vel_m_s, v0 + G * 10.0, atol=5e-4)
    finally:
        b.close()


def test_bad_input_is_rejected_or_failsafe(backend, profile):
    with pytest.raises(ValueError, match="4 throttles"):
        backend.step(np.zeros(3))
    with pytest.raises(ValueError, match="n_steps"):
        backend.step(np.zeros(4), -1)
    with pytest.raises(ValueError, match="non-finite"):
        backend.reset(VehicleState(pos_m=[0.0, np.nan, 1.0]))
    with pytest.raises(ValueError):
        backend.set_external_force(np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="dt_s"):
        JSBSimBackend(profile, dt_s=0.0)
    # A NaN throttle counts as motor off, as in the native backend.
    backend.reset(VehicleState(pos_m=[0.0, 0.0, 2.0], rotor_speed_rad_s=[hover_speed(profile)] * 4))
    backend.step(np.array([np.nan, 2.0, -1.0, 0.5]), 200)
    w = backend.state.rotor_speed_rad_s
    assert w[0] < 0.01 * hover_speed(profile) and w[2] < 0.01 * hover_speed(profile)
    assert w[1] == pytest.approx(profile.max_rotor_speed_rad_s, rel=0.01)


def test_close_is_idempotent_and_removes_the_model(profile):
    b = JSBSimBackend(profile)
    root = b._root
    assert (root / "aircraft").is_dir()
    b.close()
    b.close()
    assert not root.exists()
    with pytest.raises(RuntimeError, match="closed"):
        b.step(np.zeros(4))
