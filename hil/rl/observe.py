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

_euler = njit(cache=True)(euler_from_quat)
_state_row = njit(cache=True)(e2e_state_row)


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
        roll, pitch, yaw = _euler(x[i, 6:10])
        o = obs[i]
        _state_row(pred_pos[i, 0] - row_start[i, 0], pred_pos[i, 1] - row_start[i, 1],
                   pred_pos[i, 2] - row_start[i, 2], pred_vel[i, 0], pred_vel[i, 1], pred_vel[i, 2],
                   0.0, 0.0, 0.0, roll, pitch, yaw, row_yaw[i], o)  # (acceleration input: the pilot's zero)
        t = tick[i] * dt_s + lead_s
        o[12] = min(max(t, 0.0), t_approach_s[i])
