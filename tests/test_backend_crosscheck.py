"""The native and JSBSim backends fly the same motor-command sequence to the same trajectory.

Sequence (n3_tx2, from rest on the ground, 1 kHz): spin-up to 115 % of hover throttle and lift-off
(1 s), hover throttle (1 s), a roll doublet (+/-0.04 throttle on the left/right pairs, 0.1/0.2/0.1 s),
hover (0.5 s), a climb at 120 % (1 s). The vehicle ends 4.6 m up, 0.6 m to the side, at 2.7 m/s.

Tolerances: position 1.5 cm, velocity 1.5 cm/s, attitude 5 mrad (0.29 deg); measured 3.9 mm,
6.4 mm/s and 2.5 mrad. Where the differences come from:
- Integrators. The native kernel steps velocity with explicit Euler from the start-of-step
  acceleration; JSBSim uses Adams-Bashforth 2 (velocity) and 3 (position). The two lag each other by
  half a step, so velocities differ by about dt/2 times the change in acceleration since the start
  (dt/2 * 15 m/s^2 ~ 7.5 mm/s here) and positions by the integral of that (a few mm over 4.7 s).
  Rotation: native turns the quaternion by the mid-step rate, JSBSim by the start-of-step rate, which
  during the doublet's 10 rad/s^2 rate changes gives the mrad-level attitude difference.
- Ground: native clamps the box bottom at z = 0; JSBSim holds it on stiff springs that unload over
  a few milliseconds at lift-off (under 1 mm/s of vertical speed).
- Frames and the Earth model: JSBSim runs on a non-rotating 1e8 m sphere; over this flight that
  bends the world by under 1 um and tilts gravity by under 1e-7 rad: negligible. A frame-convention
  error (a sign, a swapped axis) would show as centimetres to metres, far above the tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest

from emulator.physics import backend_names, make_backend
from emulator.profile import load_profile
from emulator.vehicle import resting_state

POS_TOL_M = 0.015
VEL_TOL_M_S = 0.015
ATT_TOL_RAD = 0.005


def command_sequence(hover: float) -> list[tuple[float, np.ndarray]]:
    d = 0.04
    left_up = np.array([hover - d, hover + d, hover + d, hover - d])  # rotors 1, 2 on the left
    right_up = np.array([hover + d, hover - d, hover - d, hover + d])
    return [
        (1.0, np.full(4, 1.15 * hover)),
        (1.0, np.full(4, hover)),
        (0.1, left_up),
        (0.2, right_up),
        (0.1, left_up),
        (0.5, np.full(4, hover)),
        (1.0, np.full(4, 1.2 * hover)),
    ]


def fly(name: str) -> np.ndarray:
    """Rows of [t, pos(3), vel(3), quat(4)] every 10 ms."""
    profile = load_profile("n3_tx2")
    backend = make_backend(name, profile)
    try:
        backend.reset(resting_state(profile, yaw_rad=0.0))
        rows = []
        for duration_s, cmd in command_sequence(profile.hover_throttle):
            for _ in range(round(duration_s / 0.01)):
                backend.step(cmd, 10)
                s = backend.state
                rows.append(np.r_[s.time_s, s.pos_m, s.vel_m_s, s.quat_wxyz])
        return np.array(rows)
    finally:
        backend.close()


@pytest.fixture(scope="module")
def trajectories() -> tuple[np.ndarray, np.ndarray]:
    return fly("native"), fly("jsbsim")


def test_sequence_is_a_real_flight(trajectories):
    native, _ = trajectories
    assert native[-1, 3] > 4.0  # climbed
    assert abs(native[:, 2]).max() > 0.3  # the doublet moved it sideways
    roll = 2 * np.arcsin(np.clip(native[:, 8], -1, 1))
    assert roll.max() > 0.1 and roll.min() < 0.05


def test_trajectories_agree(trajectories):
    native, jsb = trajectories
    np.testing.assert_allclose(jsb[:, 0], native[:, 0], atol=1e-9)
    pos_err = np.linalg.norm(jsb[:, 1:4] - native[:, 1:4], axis=1)
    vel_err = np.linalg.norm(jsb[:, 4:7] - native[:, 4:7], axis=1)
    dot = np.abs(np.sum(jsb[:, 7:11] * native[:, 7:11], axis=1))
    att_err = 2 * np.arccos(np.clip(dot, 0.0, 1.0))
    worst_t = jsb[pos_err.argmax(), 0]
    assert pos_err.max() < POS_TOL_M, f"position differs by {pos_err.max():.4f} m at t={worst_t:.2f} s"
    assert vel_err.max() < VEL_TOL_M_S, f"velocity differs by {vel_err.max():.4f} m/s"
    assert att_err.max() < ATT_TOL_RAD, f"attitude differs by {att_err.max():.4f} rad"


@pytest.mark.parametrize("name", backend_names())
def test_an_external_torque_turns_the_body_at_torque_over_inertia(name):
    """A gust's yaw moment (body FLU, N m) on a body held up against gravity: the yaw rate grows at
    tau / Izz, nose to the left for a positive moment, in both backends; removing it stops the push."""
    from emulator.physics.state import VehicleState
    from emulator.profile import GRAVITY_M_S2

    p = load_profile("n3_tx2")
    be = make_backend(name, p)
    try:
        be.reset(VehicleState(pos_m=np.array([0.0, 0.0, 10.0])))
        be.set_external_force(np.array([0.0, 0.0, p.mass_kg * GRAVITY_M_S2]))
        be.set_external_torque(np.array([0.0, 0.0, 0.01]))
        be.step(np.zeros(4), 100)
        wz = be.state.omega_rad_s[2]
        assert wz == pytest.approx(0.01 / p.inertia_kgm2[2] * 0.1, rel=0.02)
        assert abs(be.state.omega_rad_s[0]) < 1e-6 and abs(be.state.omega_rad_s[1]) < 1e-6
        be.set_external_torque(np.zeros(3))
        be.step(np.zeros(4), 100)
        assert be.state.omega_rad_s[2] == pytest.approx(wz, rel=0.02)  # only the angular drag is left
        with pytest.raises(ValueError):
            be.set_external_torque(np.array([0.0, np.nan, 0.0]))
    finally:
        be.close()
