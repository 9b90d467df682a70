"""A made-up run through a tilted gap, to see the report without flying (``python -m
hil.report.synthetic OUT``).

The trajectory is a smooth curve (no physics): hover at the start, approach, pass the gap's centre
along its crossing axis with the body rolled to the gap, then settle at a recovery point 2.5 m past
the gap, 1 m above the ground. Measurement noise comes from the injected generator.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from emulator.world import rotation_zyx
from hil.report.html import write_report_html
from hil.report.summary import write_summary
from hil.report.timeseries import write_timeseries
from hil.scenario.loader import loads_scenarios
from hil.scenario.schema import Scenario

DEMO_SCENARIO = """\
name: demo_roll60
description: made-up crossing of a 60 deg gap (no physics), to show the report
gap: {roll_deg: -60}
approach: {speed_m_s: 2.5}
faults:
  - {kind: mocap_dropped, start_s: 5.0, end_s: 5.4}
"""


def _hermite(
    p0: np.ndarray, v0: np.ndarray, p1: np.ndarray, v1: np.ndarray, s: np.ndarray, dur: float
) -> np.ndarray:
    """Cubic Hermite curve between two states over ``dur`` seconds, at fractions ``s`` (N,)."""
    s = s[:, None]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * p0 + h10 * dur * v0 + h01 * p1 + h11 * dur * v1


def synthetic_run(
    scenario: Scenario, rng: np.random.Generator, rate_hz: float = 200.0
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(summary, columns) of a made-up run of ``scenario``; ``rng`` adds measurement noise."""
    gap = scenario.gap
    rot = rotation_zyx(gap.roll_rad, gap.pitch_rad, gap.yaw_rad)
    e1 = rot[:, 0]
    centre = np.asarray(gap.centre_m, dtype=float)
    start = np.asarray(scenario.initial.pos_m, dtype=float)
    speed = scenario.approach.speed_m_s or 2.0
    hover_s, approach_s = 1.0, scenario.approach.duration_s
    t_cross = hover_s + approach_s
    recover_point = centre + 2.5 * np.array([e1[0], e1[1], 0.0]) / max(math.hypot(e1[0], e1[1]), 1e-9)
    recover_point[2] = 1.0
    t = np.arange(0.0, scenario.duration_s, 1.0 / rate_hz)
    pos = np.repeat(start[None, :], len(t), axis=0)
    a = (t >= hover_s) & (t < t_cross)
    pos[a] = _hermite(start, np.zeros(3), centre, speed * e1, (t[a] - hover_s) / approach_s, approach_s)
    rec_s = 3.0
    b = (t >= t_cross) & (t < t_cross + rec_s)
    pos[b] = _hermite(centre, speed * e1, recover_point, np.zeros(3), (t[b] - t_cross) / rec_s, rec_s)
    pos[t >= t_cross + rec_s] = recover_point
    vel = np.gradient(pos, t, axis=0)
    # body roll follows the gap's roll in a bell around the crossing; pitch follows forward accel.
    bell = np.exp(-(((t - t_cross) / 0.35) ** 2))
    roll_cmd = gap.roll_deg * bell
    acc = np.gradient(vel, t, axis=0)
    pitch_cmd = np.degrees(np.arctan2(-(acc @ np.array([e1[0], e1[1], 0.0])), 9.81)) * -1.0
    pitch_cmd = np.clip(pitch_cmd, -35, 35) * (1 - bell)
    lag = int(0.04 * rate_hz)
    roll = np.concatenate([np.full(lag, roll_cmd[0]), roll_cmd[:-lag]]) + rng.normal(0, 0.4, len(t))
    pitch = np.concatenate([np.full(lag, pitch_cmd[0]), pitch_cmd[:-lag]]) + rng.normal(0, 0.4, len(t))
    yaw_cmd = np.zeros(len(t))
    yaw = yaw_cmd + rng.normal(0, 0.3, len(t))
    thrust = 48.0 + 0.35 * acc[:, 2] * 10 - 14.0 * bell
    side = (pos - centre) @ e1
    clearance = np.where(np.abs(side) < 0.25, 0.045 + 0.1 * np.abs(side), np.nan)
    phase = np.select([t < hover_s, t < t_cross, t < t_cross + rec_s], [0, 1, 2], 3).astype(float)
    phase[(t > t_cross - 0.15) & (t < t_cross + 0.15)] = 2
    mocap_rate = 120.0 + rng.normal(0, 1.5, len(t))
    mocap_rate[(t >= 5.0) & (t < 6.4)] = np.linspace(20, 120, int(np.count_nonzero((t >= 5.0) & (t < 6.4))))
    command_rate = 50.0 + rng.normal(0, 0.5, len(t))
    columns = {
        "t_s": t,
        "pos_m_x": pos[:, 0], "pos_m_y": pos[:, 1], "pos_m_z": pos[:, 2],
        "vel_m_s_x": vel[:, 0], "vel_m_s_y": vel[:, 1], "vel_m_s_z": vel[:, 2],
        "roll_deg": roll, "pitch_deg": pitch, "yaw_deg": yaw,
        "roll_cmd_deg": roll_cmd, "pitch_cmd_deg": pitch_cmd, "yaw_cmd_deg": yaw_cmd,
        "thrust_cmd_pct": thrust, "clearance_m": clearance, "phase": phase,
        "command_rate_hz": command_rate, "mocap_rate_hz": mocap_rate,
    }  # fmt: skip
    min_clear = float(np.nanmin(clearance))
    k = int(np.argmin(np.abs(t - t_cross)))
    att_err = abs(float(roll[k]) - gap.roll_deg)
    rest = float(np.linalg.norm(pos[-1] - recover_point))

    def check(name: str, passed: bool, expected: Any, observed: Any, time_s: float | None) -> dict[str, Any]:
        return {"name": name, "passed": passed, "expected": expected, "observed": observed, "time_s": time_s}

    checks = [
        check("crosses_gap", True, True, True, t_cross),
        check("no_collision", True, "no contact", "none", None),
        check("min_clearance_m", min_clear >= 0.0, ">= 0", min_clear, t_cross),
        check("max_attitude_error_deg", att_err <= 10.0, "<= 10", att_err, t_cross),
        check("recovery", rest <= 0.5, "within 0.5 m in 4 s", rest, t_cross + rec_s),
        check("stays_in_lab", True, True, True, None),
    ]
    summary = {
        "scenario": scenario.to_dict(),
        "passed": all(c["passed"] for c in checks),
        "end_reason": "duration reached",
        "sim_time_s": float(t[-1]),
        "wall_time_s": 0.0,
        "checks": checks,
        "crossing": {"time_s": t_cross, "point_m": centre.tolist(), "through_opening": True},
        "links": {
            "command": {
                "sent": 400,
                "delivered": 400,
                "lost": 0,
                "corrupted": 0,
                "rate_hz": 50.0,
                "latency_ms_mean": 0.6,
            },
            "mocap": {
                "sent": 960,
                "delivered": 912,
                "lost": 48,
                "corrupted": 0,
                "rate_hz": 114.0,
                "latency_ms_mean": 6.1,
            },
        },
        "events": [
            {"time_s": 0.0, "source": "fc", "text": "armed, offboard"},
            {"time_s": 5.0, "source": "fault", "text": "mocap_dropped begins"},
            {"time_s": 5.4, "source": "fault", "text": "mocap_dropped ends"},
        ],
    }
    return summary, columns


def write_demo(out_dir: str | Path, seed: int = 0) -> Path:
    """Write summary.json, timeseries.npz and report.html of the made-up run; returns the report path."""
    scenario = loads_scenarios(DEMO_SCENARIO, source="demo.scenario.yaml")[0]
    summary, columns = synthetic_run(scenario, np.random.default_rng(seed))
    write_timeseries(out_dir, columns)
    report = write_report_html(out_dir, summary, columns, scenario)
    write_summary(out_dir, summary)  # last, as a run writes it
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hil.report.synthetic", description=__doc__.split("(")[0])
    parser.add_argument("out_dir", help="folder for summary.json, timeseries.npz and report.html")
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    args = parser.parse_args(argv)
    print(write_demo(args.out_dir, args.seed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
