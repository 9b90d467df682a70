"""The FC's gains tuned from the vehicle profile (emulator.fc.tuning): the rule gives the n3_tx2 gains
it always flew with, slower motors get slower loops, a profile may set its own, and a vehicle the FC
cannot stabilise is refused with the reason, before anything flies."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from emulator.fc import FcState, fc_gains
from emulator.fc.tuning import MIN_ATTITUDE_P_PER_S
from emulator.physics.native import hover_state
from emulator.profile import ProfileError, builtin_profiles, load_profile
from emulator.vehicle import EmulatedVehicle

N3 = load_profile("n3_tx2")
F450 = load_profile("f450")


def test_n3_tx2_gains_are_the_ones_it_flew_with():
    g = fc_gains(N3)
    assert g.inner.rate_p_per_s == (50.0, 50.0, 12.0)
    assert g.inner.attitude_p_per_s == (11.0, 11.0, 4.0)
    assert (g.hold.horizontal_p_per_s, g.hold.vertical_p_per_s) == (1.5, 3.0)


def test_slower_motors_get_a_rate_loop_they_can_follow():
    g = fc_gains(F450)
    tau = F450.motor_time_constant_s
    # the fixed 50 /s loop was 2.75 / tau on the F450; the tuned one sits at the n3_tx2's 1.75 / tau
    assert g.inner.rate_p_per_s[0] * tau == pytest.approx(1.75, rel=0.01)
    assert g.inner.attitude_p_per_s[0] == pytest.approx(0.22 * g.inner.rate_p_per_s[0], rel=0.01)
    assert g.hold.horizontal_p_per_s < fc_gains(N3).hold.horizontal_p_per_s


def test_a_profile_sets_its_own_gains():
    p = F450.with_changes(fc_rate_p_per_s=(40.0, 40.0, 9.0), fc_attitude_p_per_s=(9.0, 9.0, 3.0),
                          fc_hold_p_per_s=(1.2, 2.0))
    g = fc_gains(p)
    assert g.inner.rate_p_per_s == (40.0, 40.0, 9.0) and g.inner.attitude_p_per_s == (9.0, 9.0, 3.0)
    assert (g.hold.horizontal_p_per_s, g.hold.vertical_p_per_s) == (1.2, 2.0)
    assert EmulatedVehicle(p).fc.inner.gains == g.inner


@pytest.mark.parametrize(
    ("changes", "field", "words"),
    [
        ({"motor_time_constant_s": 0.12}, "motor_time_constant_s", "cannot stabilise"),
        ({"fc_rate_p_per_s": (80.0, 80.0, 9.0)}, "fc_rate_p_per_s", "faster than the motors"),
        ({"fc_attitude_p_per_s": (20.0, 20.0, 3.0)}, "fc_attitude_p_per_s", "more than half the rate loop"),
    ],
)
def test_a_vehicle_the_fc_cannot_stabilise_is_refused_with_the_reason(changes, field, words):
    p = F450.with_changes(**changes)
    with pytest.raises(ProfileError, match=words) as info:
        fc_gains(p)
    assert info.value.field == field
    with pytest.raises(ProfileError):  # the FC refuses it too: nothing flies
        EmulatedVehicle(p)


def test_the_slow_motor_refusal_says_what_is_missing():
    with pytest.raises(ProfileError) as info:
        fc_gains(F450.with_changes(motor_time_constant_s=0.12))
    text = str(info.value)
    assert "0.12 s time constant" in text and f"{MIN_ATTITUDE_P_PER_S:g} /s" in text and "f450" in text


def test_heavier_inertia_and_a_0p08_s_motor_still_tune():
    heavier = tuple(1.5 * i for i in F450.inertia_kgm2)
    slow = F450.with_changes(inertia_kgm2=heavier, motor_time_constant_s=0.08)
    g = fc_gains(slow)
    assert MIN_ATTITUDE_P_PER_S <= g.inner.attitude_p_per_s[0] < fc_gains(F450).inner.attitude_p_per_s[0]


@pytest.mark.parametrize("name", builtin_profiles())
def test_hold_steadies_a_tilted_moving_vehicle_of_each_profile(name):
    """The FC's own hover (velocity hold) on the tuned gains brings a vehicle thrown at 2 m/s, tilted
    20 deg, to a stop within 4 s."""
    p = load_profile(name)
    tilt = math.radians(20.0)  # about body x
    st = dataclasses.replace(hover_state(p, (0.0, 0.0, 2.0)), vel_m_s=np.array([2.0, -1.0, 0.5]),
                             quat_wxyz=np.array([math.cos(tilt / 2), math.sin(tilt / 2), 0.0, 0.0]))
    v = EmulatedVehicle(p, initial_state=st)
    v.fc.arm(0.0)
    assert v.fc.state is FcState.HOLD
    v.step(4000)
    assert abs(v.state.vel_m_s).max() < 0.05, v.state.vel_m_s
    assert abs(v.state.omega_rad_s).max() < 0.05
