"""Evaluation in physical units, torch-free: planner errors on held-out data and on the paper's test case,
controller angle/thrust errors. Every function takes a predictor ``(N, n_in) -> (N, n_out)`` (numpy)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from policies.gap_planning import POINT_BODY, GapPose, LabVolume, plan_mission
from policies.learning.features import planner_inputs

Predictor = Callable[[np.ndarray], np.ndarray]

# The release's test case (REFERENCE.md) and its network's worst errors against the expert.
PAPER_START_M = (-2.0, -1.0, 0.5)
PAPER_GAP_CENTRE_M = (0.0, 0.5, 2.1)
PAPER_GAP_ROLL_RAD = math.radians(-60.0)
PAPER_APPROACH_S = 2.6
PAPER_WORST_ERRORS = {"pos_m": 0.058, "vel_m_s": 0.125, "acc_m_s2": 0.505}


def planner_errors(pred: np.ndarray, label: np.ndarray) -> dict[str, float]:
    """Mean and max of the Euclidean position (m), velocity (m/s) and acceleration (m/s^2) errors."""
    out: dict[str, float] = {}
    for name, sl in (("pos_m", slice(0, 3)), ("vel_m_s", slice(3, 6)), ("acc_m_s2", slice(6, 9))):
        e = np.linalg.norm(np.asarray(pred)[:, sl] - np.asarray(label)[:, sl], axis=1)
        out[f"mean_{name}"], out[f"max_{name}"] = float(e.mean()), float(e.max())
    return out


def paper_case(n_samples: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """Planner inputs (n, 17) and expert labels (n, 9) along the test case's approach trajectory
    (start to the traverse start state of the gap planner, 2.6 s), ``n_samples`` uniform in [0, T].

    Planned for the centre point, as the release checks it (with the body box the 2.6 s approach
    comes within 0.2 m of the floor and the planner takes a shorter one)."""
    gap = GapPose.from_euler(PAPER_GAP_CENTRE_M, PAPER_GAP_ROLL_RAD, width_m=0.8, height_m=0.35)
    plan = plan_mission(PAPER_START_M, gap, LabVolume((-4.0, -3.0, 0.0), (4.0, 4.0, 4.0)),
                        approach_duration_s=PAPER_APPROACH_S, body=POINT_BODY)
    tr = plan.approach
    t = np.linspace(0.0, float(tr.T), n_samples)
    p, v, a = (z.reshape(-1, 3) for z in tr.state(t))
    pf, vf, af = plan.traverse.start_state
    x = planner_inputs(t, pf - tr.p0, tr.v0, tr.a0, vf, af, float(tr.T))
    return x, np.concatenate([p - tr.p0, v, a], axis=1)


def paper_case_errors(predict: Predictor) -> dict[str, float]:
    """Worst (max over time) Euclidean errors of ``predict`` on the test case, next to the paper's."""
    x, y = paper_case()
    errs = planner_errors(predict(x), y)
    return {**{k: v for k, v in errs.items() if k.startswith("max_")},
            **{f"paper_max_{k}": v for k, v in PAPER_WORST_ERRORS.items()}}


def controller_errors(pred: np.ndarray, label: np.ndarray) -> dict[str, float]:
    """Mean and max attitude error (deg, geodesic angle between the paper's R_d) and thrust error (N)."""
    pred, label = np.asarray(pred, float), np.asarray(label, float)

    def rot(roll: np.ndarray, pitch: np.ndarray) -> np.ndarray:
        # the paper's eq. (1), as in losses.paper_rotation
        cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
        z = np.zeros_like(roll)
        return np.stack([np.stack([cp, z, -sp], -1), np.stack([sr * sp, cr, sr * cp], -1),
                         np.stack([cr * sp, -sr, cr * cp], -1)], -2)

    rel = rot(label[:, 0], label[:, 1]) @ np.swapaxes(rot(pred[:, 0], pred[:, 1]), -1, -2)
    cos = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    thr = np.abs(pred[:, 2] - label[:, 2])
    return {"mean_angle_deg": float(ang.mean()), "max_angle_deg": float(ang.max()),
            "p99_angle_deg": float(np.percentile(ang, 99)), "mean_thrust_n": float(thr.mean()),
            "max_thrust_n": float(thr.max()), "p99_thrust_n": float(np.percentile(thr, 99))}
