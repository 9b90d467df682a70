"""The RL environment's observations, compiled over its rows: the end-to-end policy's 29 inputs as the
`e2e` pilot builds them onboard, from the vehicles' state predicted ``lead_s`` ahead.

The per-sample arithmetic is the pilot's own plain-float functions (`e2e_state_row`, and the link's
`euler_from_quat` for the Euler angles), compiled here by numba: one definition, run interpreted on the
onboard computer and compiled over 4096 rows here (the kernel cache's digest covers their modules).
"""

from __future__ import annotations

from numba import njit, prange

from hil.link.mavlink import euler_from_quat
from policies.learning.learned_pilots import e2e_state_row

euler_angles = njit(cache=True)(euler_from_quat)
_state_row = njit(cache=True)(e2e_state_row)


@njit(cache=True, inline="always")
def write_inputs(o, px, py, pz, vx, vy, vz, roll, pitch, yaw, start, plan_yaw, t_s,
                 t_approach_s):  # pragma: no cover
    """The policy's first 13 inputs into ``o`` (29,): the pilot's 12 state inputs of position ``px..pz``
    (m) relative to the approach start ``start`` (3,), velocity ``vx..vz`` (m/s) and attitude (rad) in
    the frame of the plan's yaw ``plan_yaw`` (rad; acceleration input: the pilot's zero), then the
    mission time ``t_s`` within [0, ``t_approach_s``] (s)."""
    _state_row(px - start[0], py - start[1], pz - start[2], vx, vy, vz, 0.0, 0.0, 0.0, roll, pitch, yaw,
               plan_yaw, o)
    o[12] = min(max(t_s, 0.0), t_approach_s)


@njit(cache=True, parallel=True)
def observe_rows(x, aux, rows, lead_s, row_start, row_yaw, tick, dt_s, t_approach_s, pred_pos, pred_vel,
                 obs):  # pragma: no cover
    """Rows ``rows`` of ``obs`` (N, 29), columns 0..12, from the state rows ``x`` and ``aux``
    (`BatchPhysics.kernel_arrays`): the state ``lead_s`` (s) ahead under the present acceleration into
    ``pred_pos`` and ``pred_vel`` (N, 3), the pilot's 12 state inputs relative to the approach start
    ``row_start`` (N, 3) in the frame of the plan's yaw ``row_yaw`` (N,), and the mission time
    ``tick * dt_s + lead_s`` within [0, ``t_approach_s``] (s). Columns 13.. (the planner's inputs) are
    set at each row's reset."""
    c = 0.5 * lead_s * lead_s
    for j in prange(rows.shape[0]):
        i = rows[j]
        for k in range(3):
            pred_pos[i, k] = x[i, k] + x[i, 3 + k] * lead_s + aux[i, 3 + k] * c
            pred_vel[i, k] = x[i, 3 + k] + aux[i, 3 + k] * lead_s
        roll, pitch, yaw = euler_angles(x[i, 6:10])
        write_inputs(obs[i], pred_pos[i, 0], pred_pos[i, 1], pred_pos[i, 2], pred_vel[i, 0], pred_vel[i, 1],
                     pred_vel[i, 2], roll, pitch, yaw, row_start[i], row_yaw[i], tick[i] * dt_s + lead_s,
                     t_approach_s[i])
