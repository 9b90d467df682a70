"""The FC's inner loop: a batch of vehicles (each row flies what one vehicle's own loop gives) and its mixer's
priorities at saturation (roll/pitch first, then the collective, yaw last with a bounded share of thrust)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from emulator.fc.inner_loop import YAW_THRUST_MARGIN, InnerLoop, allocation_matrix
from emulator.fc.tuning import fc_gains
from emulator.profile import load_profile


def test_a_batch_gives_each_vehicle_its_own_loops_throttles():
    profile = load_profile("n3_tx2")
    loop = InnerLoop(profile, fc_gains(profile).inner)
    rng = np.random.default_rng(3)
    n = 64
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    w = rng.normal(0, 2.0, (n, 3))
    target = np.column_stack([rng.normal(0, 0.5, (n, 3)), rng.uniform(0, profile.max_total_thrust_n, n)])
    got = loop.update_batch(q, w, target)
    for i in range(n):
        assert np.array_equal(got[i], loop.update(q[i], w[i], *target[i]))
    assert (got.min() >= 0.0) and (got.max() <= 1.0) and got.max() == 1.0  # saturated rows among them
    with pytest.raises(ValueError, match="shapes"):
        loop.update_batch(q, w[:3], target)


def _torques(profile, throttles: np.ndarray) -> np.ndarray:
    """[total thrust (N), torque x, y, z (N m)] of the throttles (4,)."""
    return allocation_matrix(profile) @ (throttles * profile.max_thrust_per_rotor_n)


@pytest.mark.parametrize("roll_rate_rad_s", [0.0, 3.0])
def test_at_full_throttle_yaw_lowers_the_collective_a_bounded_share_never_roll_or_pitch(roll_rate_rad_s):
    """PX4's sequential desaturation: with every motor at full throttle the FC keeps some yaw authority
    by lowering the collective, by at most YAW_THRUST_MARGIN of the throttle range, and roll and pitch
    get the torque they would have without a yaw demand."""
    profile = load_profile("n3_tx2")
    loop = InnerLoop(profile, fc_gains(profile).inner)
    level_east = np.array([1.0, 0.0, 0.0, 0.0])  # body FLU -> ENU: level, heading 90 deg (NED)
    w = np.array([roll_rate_rad_s, 0.0, 0.0])
    full = profile.max_total_thrust_n
    held = _torques(profile, loop.update(level_east, w, 0.0, 0.0, math.pi / 2, full).copy())
    turned = _torques(profile, loop.update(level_east, w, 0.0, 0.0, math.pi / 2 + 0.3, full).copy())
    assert held[3] == pytest.approx(0.0, abs=1e-12)
    assert turned[1:3] == pytest.approx(held[1:3], abs=1e-9)  # roll and pitch untouched
    assert abs(turned[3]) > 0.02  # N m: yaw torque at full throttle (none before: yaw strictly last)
    idle = loop.gains.idle_throttle * profile.max_thrust_per_rotor_n
    given_up = (held[0] - turned[0]) / 4  # N per rotor
    assert 0.0 < given_up <= YAW_THRUST_MARGIN * (profile.max_thrust_per_rotor_n - idle) + 1e-9


def test_yaw_never_raises_the_collective_nor_takes_roll_authority():
    """Near idle, yaw fits between the idle floor and the commanded collective (no thrust added for it),
    and a roll demand that spans the whole throttle range leaves yaw nothing."""
    profile = load_profile("n3_tx2")
    loop = InnerLoop(profile, fc_gains(profile).inner)
    level_east = np.array([1.0, 0.0, 0.0, 0.0])
    low = 0.1 * profile.max_total_thrust_n
    u = loop.update(level_east, np.zeros(3), 0.0, 0.0, math.pi / 2 + 0.3, low).copy()
    assert _torques(profile, u)[0] == pytest.approx(low)
    assert u.min() >= loop.gains.idle_throttle - 1e-12
    rolling = np.array([40.0, 0.0, 0.0])  # rad/s: a rate error no rotor spread can answer in full
    alone = _torques(profile, loop.update(level_east, rolling, 0.0, 0.0, math.pi / 2, low).copy())
    both = _torques(profile, loop.update(level_east, rolling, 0.0, 0.0, math.pi / 2 + 0.3, low).copy())
    assert both[1] == pytest.approx(alone[1]) and both[3] == pytest.approx(0.0, abs=1e-12)
