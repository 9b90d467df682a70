"""The N3-style FC stepped in simulated time: inner-loop response, limits, flags, arming, failsafe."""

from __future__ import annotations

import math

import numpy as np
import pytest

from emulator.fc import FcConfig, FcState, N3Setpoint, SetpointRejected
from emulator.fc.n3 import (
    ATTITUDE_THRUST_YAW_ANGLE,
    ATTITUDE_THRUST_YAW_RATE,
    FRAME_BODY,
    HORIZONTAL_ANGULAR_RATE,
    HORIZONTAL_VELOCITY,
    VERTICAL_THRUST,
    VERTICAL_VELOCITY,
    tilt_of,
)
from emulator.physics.native import hover_state
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.vehicle import EmulatedVehicle
from hil.link.mavlink import euler_from_quat, quat_enu_flu_to_ned_frd

PROFILE = load_profile("n3_tx2")
HOVER_PCT = PROFILE.force_to_thrust_percent(PROFILE.mass_kg * GRAVITY_M_S2)


def ned_euler(vehicle: EmulatedVehicle) -> tuple[float, float, float]:
    return euler_from_quat(quat_enu_flu_to_ned_frd(vehicle.state.quat_wxyz))


def airborne(config: FcConfig | None = None, z_m: float = 5.0) -> EmulatedVehicle:
    """A vehicle hovering at ``z_m`` in OFFBOARD, heading north, fed level hover setpoints."""
    start = hover_state(PROFILE, (0.0, 0.0, z_m))
    north = np.array([math.sqrt(0.5), 0, 0, math.sqrt(0.5)])
    v = EmulatedVehicle(
        PROFILE,
        config=config,
        initial_state=start.__class__(
            pos_m=start.pos_m, quat_wxyz=north, rotor_speed_rad_s=start.rotor_speed_rad_s
        ),
    )
    level = N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, HOVER_PCT, 0.0)
    v.fc.set_setpoint(level, 0.0)
    v.fc.set_setpoint(level, 0.0)
    assert v.fc.arm(0.0).accepted
    assert v.fc.request_offboard(0.0).accepted
    return v


def fly(v: EmulatedVehicle, sp: N3Setpoint, duration_s: float, rate_hz: float = 50.0) -> None:
    """Stream ``sp`` at ``rate_hz`` for ``duration_s`` of simulated time."""
    end = v.time_s + duration_s
    while v.time_s < end - 1e-9:
        v.fc.set_setpoint(sp, v.time_s)
        v.step(round(1.0 / rate_hz / v.dt_s))


def test_roll_step_reaches_90_percent_in_0p1_to_0p2_s_with_small_overshoot():
    v = airborne()
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, HOVER_PCT, 0.0), 0.2)
    t0 = v.time_s
    step = N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 20.0, 0.0, HOVER_PCT / math.cos(math.radians(20)), 0.0)
    times, rolls = [], []
    while v.time_s < t0 + 0.8:
        v.fc.set_setpoint(step, v.time_s)
        v.step(1)
        times.append(v.time_s - t0)
        rolls.append(math.degrees(ned_euler(v)[0]))
    rolls_a = np.array(rolls)
    rise_s = times[int(np.argmax(rolls_a >= 18.0))]
    assert 0.1 <= rise_s <= 0.2, f"90 % rise time {rise_s:.3f} s"
    assert rolls_a.max() < 20.0 * 1.10, f"overshoot to {rolls_a.max():.1f} deg"
    assert abs(rolls_a[-100:].mean() - 20.0) < 0.5
    # roll positive is right side down: the vehicle accelerates east (world +x)
    assert v.state.vel_m_s[0] > 0.5


def test_sixty_degree_roll_is_flown_and_tilt_is_limited_by_the_profile_not_the_sdk():
    v = airborne()
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, -60.0, 0.0, 2 * HOVER_PCT, 0.0), 0.5)
    roll, _, _ = ned_euler(v)
    assert math.degrees(roll) == pytest.approx(-60.0, abs=1.5)  # beyond the SDK's 35 deg
    target = v.fc.set_setpoint(N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 70.0, 60.0, 50.0, 0.0), v.time_s)
    assert math.degrees(tilt_of(target.roll_rad, target.pitch_rad)) == pytest.approx(
        PROFILE.max_tilt_deg, abs=0.01
    )
    assert target.roll_rad > target.pitch_rad > 0  # direction kept


def test_thrust_percent_maps_through_the_profile_and_hover_holds_altitude():
    v = airborne()
    z0 = v.state.pos_m[2]
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, HOVER_PCT, 0.0), 1.0)
    assert abs(v.state.pos_m[2] - z0) < 0.25  # drag and motor lag only
    target = v.fc.set_setpoint(N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0, 0, 50.0, 0.0), v.time_s)
    assert target.thrust_n == pytest.approx(0.5 * PROFILE.n3_full_thrust_n)
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, 1.3 * HOVER_PCT, 0.0), 1.0)
    assert v.state.vel_m_s[2] > 1.5  # 0.3 g up for most of a second


def test_yaw_angle_and_yaw_rate_modes():
    v = airborne()
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, HOVER_PCT, 45.0), 1.5)
    assert math.degrees(ned_euler(v)[2]) == pytest.approx(45.0, abs=2.0)
    yaw0 = ned_euler(v)[2]
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_RATE, 0.0, 0.0, HOVER_PCT, 30.0), 2.0)
    turned = math.degrees(ned_euler(v)[2] - yaw0)
    assert turned == pytest.approx(60.0, abs=8.0)  # 30 deg/s clockwise for 2 s
    clamped = v.fc.set_setpoint(N3Setpoint(ATTITUDE_THRUST_YAW_RATE, 0, 0, HOVER_PCT, 1000.0), v.time_s)
    assert math.degrees(clamped.yaw_rate_rad_s) == pytest.approx(PROFILE.max_yaw_rate_deg_s)


@pytest.mark.parametrize(
    ("flag", "words"),
    [
        (HORIZONTAL_VELOCITY | VERTICAL_THRUST, "VELOCITY"),
        (HORIZONTAL_ANGULAR_RATE | VERTICAL_THRUST, "ANGULAR_RATE"),
        (VERTICAL_VELOCITY, "vertical VELOCITY"),
        (VERTICAL_THRUST | FRAME_BODY, "BODY"),
        (0x1FF, "byte"),
    ],
)
def test_unsupported_control_flags_are_rejected_with_a_reason(flag, words):
    v = airborne()
    with pytest.raises(SetpointRejected, match=words):
        v.fc.set_setpoint(N3Setpoint(flag, 0.0, 0.0, 40.0, 0.0), 0.0)


@pytest.mark.parametrize(
    "values",
    [
        (math.nan, 0, 40, 0),
        (0, math.inf, 40, 0),
        (0, 0, -1.0, 0),
        (0, 0, 100.5, 0),
        (0, 0, 40, math.nan),
        (95, 0, 40, 0),
    ],
)
def test_bad_setpoint_values_are_rejected_and_the_previous_one_is_kept(values):
    v = airborne()
    before = v.fc.target
    with pytest.raises(SetpointRejected):
        v.fc.set_setpoint(N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, *values), 0.0)
    assert v.fc.target is before


def test_offboard_needs_a_setpoint_stream_above_2_hz():
    v = EmulatedVehicle(PROFILE)
    assert v.fc.arm(0.0).accepted and v.fc.state is FcState.HOLD
    sp = N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0, 0, 10.0, 0.0)
    v.fc.set_setpoint(sp, 0.0)
    res = v.fc.request_offboard(0.01)
    assert not res.accepted and "2 Hz" in res.reason
    v.fc.set_setpoint(sp, 0.6)  # 1.67 Hz: still too slow
    assert not v.fc.request_offboard(0.61).accepted
    v.fc.set_setpoint(sp, 0.9)
    assert v.fc.request_offboard(0.91).accepted and v.fc.state is FcState.OFFBOARD


def test_disarm_in_the_air_is_refused_unless_forced():
    v = airborne()
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0, 0, HOVER_PCT, 0.0), 0.2)
    res = v.fc.disarm(v.time_s)
    assert not res.accepted and "air" in res.reason
    assert v.fc.disarm(v.time_s, force=True).accepted
    assert v.fc.state is FcState.DISARMED
    v.step(300)
    assert v.state.vel_m_s[2] < -2.0  # motors off: falling


def test_setpoint_loss_failsafe_hover_then_land_and_disarm_with_timed_events():
    cfg = FcConfig(failsafe_timeout_s=0.5, failsafe_hover_s=2.0, land_speed_m_s=1.0)
    v = airborne(cfg, z_m=3.0)
    fly(v, N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0, 0, HOVER_PCT, 0.0), 1.0)
    last_sp = v.fc.last_setpoint_s
    v.step(round(0.55 / v.dt_s))
    ev = v.fc.events[-1]
    assert ev.to_state is FcState.FAILSAFE_HOVER and "lost" in ev.reason
    assert 0.5 < ev.time_s - last_sp <= 0.5 + 0.002
    z_hover = v.state.pos_m[2]
    v.step(round(1.5 / v.dt_s))
    assert abs(v.state.pos_m[2] - z_hover) < 0.3 and v.fc.state is FcState.FAILSAFE_HOVER
    v.step(round(6.0 / v.dt_s))
    states = [e.to_state for e in v.fc.events]
    assert states[-3:] == [FcState.FAILSAFE_HOVER, FcState.FAILSAFE_LAND, FcState.DISARMED]
    land, disarm = v.fc.events[-2], v.fc.events[-1]
    assert land.time_s - ev.time_s == pytest.approx(2.0, abs=0.002)
    assert disarm.reason.startswith("landed") and v.fc.landed
    assert np.all(v.fc.motor_cmd == 0.0)
    assert [e.time_s for e in v.fc.events] == sorted(e.time_s for e in v.fc.events)


def test_resting_vehicle_arms_to_idle_and_stays_on_the_ground():
    v = EmulatedVehicle(PROFILE)
    z0 = v.state.pos_m[2]
    assert v.fc.landed and v.fc.state is FcState.DISARMED
    v.fc.arm(0.0)
    v.step(500)
    assert v.fc.state is FcState.HOLD and v.fc.landed
    assert abs(v.state.pos_m[2] - z0) < 1e-3
    assert np.all(v.fc.motor_cmd == pytest.approx(v.fc.gains.inner.idle_throttle))


def test_config_rejects_nonsense():
    with pytest.raises(ValueError, match="failsafe_timeout_s"):
        FcConfig(failsafe_timeout_s=-1.0)
    with pytest.raises(ValueError, match="failsafe_timeout_s"):
        FcConfig(failsafe_timeout_s=math.nan)


def _hovering_east(z_m: float = 2.0) -> EmulatedVehicle:
    """Hovering at ``z_m``, heading east (NED yaw 90 deg), disarmed: the runner's start in the air."""
    start = hover_state(PROFILE, (0.0, 0.0, z_m))
    return EmulatedVehicle(PROFILE, initial_state=start)  # hover_state: body x along world +x (east)


@pytest.mark.parametrize("batched", [False, True])
def test_hold_keeps_the_heading_it_had_when_armed_in_the_air(batched):
    """Armed in the air the FC holds (PX4's Hold: the heading on entry), on the per-step path and the
    batched one: the heading stays at 90 deg (it used to swing toward north at ~60 deg/s)."""
    from emulator.loops.batched_steps import FastStepper

    v = _hovering_east()
    assert ned_euler(v)[2] == pytest.approx(math.pi / 2, abs=1e-9)
    v.fc.arm(0.0)
    assert v.fc.state is FcState.HOLD
    stepper = FastStepper.for_vehicle(v) if batched else None
    worst = 0.0
    for _ in range(100):  # 1 s
        stepper.step(10) if stepper is not None else v.step(10)
        worst = max(worst, abs(math.degrees(ned_euler(v)[2]) - 90.0))
        assert v.fc.heading_setpoint_rad() == pytest.approx(math.pi / 2, abs=1e-6)
    assert worst < 0.05


def test_a_failsafe_hover_and_landing_hold_the_heading_on_entry():
    """Setpoints at a 30 deg heading stop: the failsafe hover and the landing after it keep 30 deg."""
    v = airborne()
    sp = N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, HOVER_PCT, 30.0)
    fly(v, sp, 2.0)
    assert math.degrees(ned_euler(v)[2]) == pytest.approx(30.0, abs=0.5)
    heading_at_entry = None
    while v.time_s < 9.0:
        v.step(10)
        if v.fc.state.failsafe and heading_at_entry is None:
            heading_at_entry = math.degrees(ned_euler(v)[2])
        if v.fc.state.failsafe:
            assert math.degrees(ned_euler(v)[2]) == pytest.approx(heading_at_entry, abs=0.2)
    assert v.fc.state is FcState.FAILSAFE_LAND
    assert heading_at_entry == pytest.approx(30.0, abs=0.5)
