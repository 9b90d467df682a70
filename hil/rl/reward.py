"""The paper's reward of `CrossGap-v0` and an episode's end, per vehicle row, compiled (the only form:
`hil.rl.env.CrossGapCore.step` calls it once a control step for the whole batch).

Terms (Lin et al. 2019, section V-B, with the release's constants, `hil.rl.env.RewardWeights`), in
`REWARD_TERMS` order: ``position`` w_r max(0, d_a - |p - p_gap|) dt, ``arrival`` S once on the first
positive position reward, ``rate`` -w_w |w| dt, ``angular_acceleration`` -w_a |dw/dt| dt, ``jerk``
-w_j |da/dt| dt (w body rates, a world acceleration, derivatives over the control period), ``collision``
-C on a collision.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

REWARD_TERMS = ("position", "arrival", "rate", "angular_acceleration", "jerk", "collision")

#: layout of the packed weights (`pack_weights`)
W_POSITION, W_ACTIVE, W_ARRIVAL, W_RATE, W_ANG_ACC, W_JERK, W_COLLISION, W_DT = range(8)


def pack_weights(weights: object, dt_s: float) -> np.ndarray:
    """A `RewardWeights` and the control period (s) as the kernel's vector (8,)."""
    w = weights
    return np.array([w.position_per_m_s, w.active_distance_m, w.arrival,  # type: ignore[attr-defined]
                     w.rate_per_rad, w.angular_acceleration_per_rad, w.jerk_per_m,  # type: ignore[attr-defined]
                     w.collision, dt_s], np.float64)  # type: ignore[attr-defined]


@njit(cache=True, parallel=True)
def score_rows(x, aux, weights, centre, direction, tick, steps, codes, arrived, prev_w, prev_a, terms,
               reward, terminated, truncated, success):  # pragma: no cover
    """After a control step, for each row of the states ``x`` (N, STATE_SIZE) and ``aux`` (N, AUX_SIZE):
    the reward ``terms`` (N, 6) and their sum ``reward`` (N,); ``terminated`` (a collision: ``codes`` != 0),
    ``truncated`` (``tick`` reached the episode's ``steps``, no collision) and ``success`` (truncated with
    the body past the gap's plane: (p - ``centre``) . ``direction`` > 0); ``arrived`` latched; the last
    rates and accelerations in ``prev_w``, ``prev_a``. ``weights``: `pack_weights`."""
    dt = weights[W_DT]
    for i in prange(x.shape[0]):
        px, py, pz = x[i, 0] - centre[i, 0], x[i, 1] - centre[i, 1], x[i, 2] - centre[i, 2]
        dist = math.sqrt(px * px + py * py + pz * pz)
        position = weights[W_POSITION] * max(0.0, weights[W_ACTIVE] - dist) * dt
        first = position > 0.0 and not arrived[i]
        if first:
            arrived[i] = True
        wx, wy, wz = x[i, 10], x[i, 11], x[i, 12]
        ax, ay, az = aux[i, 3], aux[i, 4], aux[i, 5]
        dwx, dwy, dwz = wx - prev_w[i, 0], wy - prev_w[i, 1], wz - prev_w[i, 2]
        dax, day, daz = ax - prev_a[i, 0], ay - prev_a[i, 1], az - prev_a[i, 2]
        collided = codes[i] != 0
        t = terms[i]
        t[0] = position
        t[1] = weights[W_ARRIVAL] if first else 0.0
        t[2] = -weights[W_RATE] * math.sqrt(wx * wx + wy * wy + wz * wz) * dt
        t[3] = -weights[W_ANG_ACC] * math.sqrt(dwx * dwx + dwy * dwy + dwz * dwz)  # |dw/dt| dt
        t[4] = -weights[W_JERK] * math.sqrt(dax * dax + day * day + daz * daz)  # |da/dt| dt
        t[5] = -weights[W_COLLISION] if collided else 0.0
        reward[i] = t[0] + t[1] + t[2] + t[3] + t[4] + t[5]
        prev_w[i, 0], prev_w[i, 1], prev_w[i, 2] = wx, wy, wz
        prev_a[i, 0], prev_a[i, 1], prev_a[i, 2] = ax, ay, az
        terminated[i] = collided
        truncated[i] = tick[i] >= steps[i] and not collided
        success[i] = truncated[i] and px * direction[i, 0] + py * direction[i, 1] + pz * direction[i, 2] > 0.0
