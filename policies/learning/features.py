"""Input/output layouts of the planner, controller and end-to-end networks, and the paper's data ranges.

Planner input (17): [t (s), v_bar (m/s), dp = end - start (3, m), v0 (3, m/s), a0 (3, m/s^2),
vf (3, m/s), af (3, m/s^2)]; the duration is T = |dp| / v_bar. Output (9): [p(t) - p0 (3, m),
v(t) (3, m/s), a(t) (3, m/s^2)].
Controller input (12): [pos_err (3, m), vel_err (3, m/s), acc_err (3, m/s^2), euler (3, rad: roll,
pitch, yaw)], errors = reference - state, world ENU. Output (3): [roll (rad), pitch (rad), thrust (N)]
for desired yaw 0 and the paper's 0.9 kg vehicle.
End-to-end input (29): [pos - start (3), vel (3), acc (3), euler (3), the 17 planner inputs].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PLANNER_IN, PLANNER_OUT = 17, 9
CONTROLLER_IN, CONTROLLER_OUT = 12, 3
E2E_IN = 29
CONTROLLER_MASS_KG = 0.9  # mass the controller labels are computed for (the paper's release)


@dataclass(frozen=True)
class PlannerRanges:
    """The paper's planner data ranges (per axis, symmetric) and the average speed range."""

    dp_m: float = 30.0
    vel_m_s: float = 10.0
    acc_m_s2: float = 10.0
    v_bar_min_m_s: float = 1.0
    v_bar_max_m_s: float = 7.0


@dataclass(frozen=True)
class ControllerRanges:
    """Per-axis half-ranges of one controller data set (m, m/s, m/s^2, rad)."""

    pos_err_m: float
    vel_err_m_s: float
    acc_err_m_s2: float
    euler_rad: float


LARGE_RANGE = ControllerRanges(10.0, 5.0, 10.0, np.pi)
SHORT_RANGE = ControllerRanges(0.2, 0.3, 10.0, np.radians(30.0))


def planner_inputs(t_s: np.ndarray | float, dp_m: np.ndarray, v0_m_s: np.ndarray, a0_m_s2: np.ndarray,
                   vf_m_s: np.ndarray, af_m_s2: np.ndarray, duration_s: np.ndarray | float) -> np.ndarray:
    """Stack planner inputs (..., 17) from boundary states (..., 3) and times/durations (...) in s."""
    dp = np.asarray(dp_m, dtype=float)
    T = np.asarray(duration_s, dtype=float)
    if np.any(~np.isfinite(T)) or np.any(T <= 0):
        raise ValueError("duration_s must be finite and positive")
    v_bar = np.linalg.norm(dp, axis=-1) / T
    shape = np.broadcast_shapes(np.shape(t_s), v_bar.shape, dp.shape[:-1])
    cols = [np.broadcast_to(np.asarray(t_s, float), shape)[..., None],
            np.broadcast_to(v_bar, shape)[..., None]]
    cols += [np.broadcast_to(np.asarray(x, float), (*shape, 3))
             for x in (dp, v0_m_s, a0_m_s2, vf_m_s, af_m_s2)]
    return np.concatenate(cols, axis=-1)

