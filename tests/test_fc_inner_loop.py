"""The FC's inner loop for a batch of vehicles: each row flies what one vehicle's own loop gives."""

from __future__ import annotations

import numpy as np
import pytest

from emulator.fc.inner_loop import InnerLoop
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
