"""The reward of `CrossGap-v0` and an episode's end, per vehicle row, compiled (the only form:
`hil.rl.env.CrossGapCore.step` calls it once a control step for the whole batch).

By default the reward the paper's release ran (cross_grap_env_v2.py, `RewardWeights()`); the paper's
own form (section V-B, `RewardWeights.paper()`) is the same kernel with other constants and switches.
Terms, in `REWARD_TERMS` order, per control step of ``dt`` s, with ``k = dt / step_unit_s`` (the
release: dt / 0.005; the paper: dt in seconds):

- ``position``: w_r max(0, d_a - |p - p_gap|), times k where ``position_scaled`` (the paper; the release
  pays it per step, unscaled);
- ``arrival``: S once, on the first positive position reward;
- ``rate``: w_w (o_w - |w|) k, w the body rates (rad/s) and o_w the release's offset 2 (paper: 0);
- ``angular_acceleration``: w_alpha (o_alpha - |dw/dt|) k, dw/dt the change of the body rates over the
  control step / dt (rad/s^2; the release read AirSim's angular acceleration), o_alpha 2 (paper: 0);
- ``jerk``: -w_j |a_t - a_{t-1}| k with ``jerk_as_difference`` (the release: the change of the world
  acceleration over the step), else -w_j |da/dt| k (the paper);
- ``collision``: -C on a collision, which ends the episode; with ``collision_replaces`` (the release)
  the step's other terms are dropped, so the step pays -C exactly.

With ``end_step_zero`` (the release) the last step of an episode that ends without a collision pays
nothing. The first step of an episode is scored against the hover it starts from (rates and
accelerations zero); the release paid no shaping on it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numba import njit, prange

if TYPE_CHECKING:  # (env imports this module)
    from hil.rl.env import RewardWeights

REWARD_TERMS = ("position", "arrival", "rate", "angular_acceleration", "jerk", "collision")

#: layout of the packed weights (`pack_weights`)
(W_POSITION, W_ACTIVE, W_POSITION_K, W_ARRIVAL, W_RATE, W_RATE_OFF, W_ANG_ACC, W_ANG_ACC_OFF, W_JERK,
 W_JERK_DIFF, W_COLLISION, W_REPLACE, W_END_ZERO, W_DT, W_K) = range(15)


def pack_weights(w: RewardWeights, dt_s: float) -> np.ndarray:
    """A `hil.rl.env.RewardWeights` and the control period (s) as the kernel's vector (15,)."""
    k = dt_s / w.step_unit_s
    return np.array([w.position_per_m, w.active_distance_m, k if w.position_scaled else 1.0, w.arrival,
                     w.rate_per_rad_s, w.rate_offset_rad_s, w.angular_acceleration_per_rad_s2,
                     w.angular_acceleration_offset_rad_s2, w.jerk_per_m_s2, float(w.jerk_as_difference),
                     w.collision, float(w.collision_replaces), float(w.end_step_zero), dt_s, k], np.float64)


@njit(cache=True, parallel=True)
def score_rows(x, aux, weights, centre, direction, tick, steps, codes, arrived, prev_w, prev_a, terms,
               reward, terminated, truncated, success):  # pragma: no cover
    """After a control step, for each row of the states ``x`` (N, STATE_SIZE) and ``aux`` (N, AUX_SIZE):
    the reward ``terms`` (N, 6) and their sum ``reward`` (N,); ``terminated`` (a collision: ``codes`` != 0),
    ``truncated`` (``tick`` reached the episode's ``steps``, no collision) and ``success`` (truncated with
    the body past the gap's plane: (p - ``centre``) . ``direction`` > 0); ``arrived`` latched; the last
    rates and accelerations in ``prev_w``, ``prev_a``. ``weights``: `pack_weights`."""
    dt, k = weights[W_DT], weights[W_K]
    for i in prange(x.shape[0]):
        px, py, pz = x[i, 0] - centre[i, 0], x[i, 1] - centre[i, 1], x[i, 2] - centre[i, 2]
        dist = math.sqrt(px * px + py * py + pz * pz)
        position = weights[W_POSITION] * max(0.0, weights[W_ACTIVE] - dist) * weights[W_POSITION_K]
        first = position > 0.0 and not arrived[i]
        if first:
            arrived[i] = True
        wx, wy, wz = x[i, 10], x[i, 11], x[i, 12]
        ax, ay, az = aux[i, 3], aux[i, 4], aux[i, 5]
        dwx, dwy, dwz = wx - prev_w[i, 0], wy - prev_w[i, 1], wz - prev_w[i, 2]
        dax, day, daz = ax - prev_a[i, 0], ay - prev_a[i, 1], az - prev_a[i, 2]
        d_acc = math.sqrt(dax * dax + day * day + daz * daz)
        collided = codes[i] != 0
        ended = tick[i] >= steps[i] and not collided
        t = terms[i]
        t[0] = position
        t[1] = weights[W_ARRIVAL] if first else 0.0
        t[2] = weights[W_RATE] * (weights[W_RATE_OFF] - math.sqrt(wx * wx + wy * wy + wz * wz)) * k
        alpha = math.sqrt(dwx * dwx + dwy * dwy + dwz * dwz) / dt
        t[3] = weights[W_ANG_ACC] * (weights[W_ANG_ACC_OFF] - alpha) * k
        t[4] = -weights[W_JERK] * (d_acc if weights[W_JERK_DIFF] != 0.0 else d_acc / dt) * k
        t[5] = 0.0
        if (collided and weights[W_REPLACE] != 0.0) or (ended and weights[W_END_ZERO] != 0.0):
            for j in range(5):
                t[j] = 0.0
        if collided:
            t[5] = -weights[W_COLLISION]
        reward[i] = t[0] + t[1] + t[2] + t[3] + t[4] + t[5]
        prev_w[i, 0], prev_w[i, 1], prev_w[i, 2] = wx, wy, wz
        prev_a[i, 0], prev_a[i, 1], prev_a[i, 2] = ax, ay, az
        terminated[i] = collided
        truncated[i] = ended
        success[i] = ended and px * direction[i, 0] + py * direction[i, 1] + pz * direction[i, 2] > 0.0
