"""timeseries.npz: a run's recorded signals as named, equally long 1-D columns (numpy .npz).

Conventional column names (units in the name; any other identifier is stored too):

=====================================  ==========================================================
``t_s``                                sim time (s), required, non-decreasing
``pos_m_x``, ``pos_m_y``, ``pos_m_z``  position, world ENU (m)
``vel_m_s_x`` .. ``vel_m_s_z``         velocity, world ENU (m/s)
``roll_deg``, ``pitch_deg``,           measured attitude (deg)
``yaw_deg``
``roll_cmd_deg``, ``pitch_cmd_deg``,   commanded attitude as the FC received it (deg)
``yaw_cmd_deg``
``thrust_cmd_pct``                     commanded thrust (N3 vertical thrust, 0..100 %)
``clearance_m``                        signed clearance to the gap's edges (m); NaN away from the wall
``phase``                              pilot phase code (0 hover/idle, 1 approach, 2 traverse,
                                       3 recovery, 4 failsafe/abort)
``command_rate_hz``                    setpoints arriving at the FC, over the last second (Hz)
``mocap_rate_hz``                      mocap frames arriving at the onboard computer (Hz)
``command_lost``, ``mocap_lost``       messages lost so far (count)
``yaw_sp_deg``                         heading the FC steers to (deg): the offboard setpoint's, or
                                       the one it holds in hold, hover and land; NaN when none
``motor_max_pct``                      the largest of the four motor commands (% of full throttle)
``setpoint_age_s``                     time since the FC last took a setpoint (s; inf: none yet)
=====================================  ==========================================================
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

TIMESERIES_NAME = "timeseries.npz"
PHASES = ("hover", "approach", "traverse", "recovery", "failsafe")
_COLUMN_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def check_columns(columns: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Validated float/int 1-D columns of one length with a non-decreasing ``t_s``; raises ValueError."""
    if "t_s" not in columns:
        raise ValueError(f"time series needs a 't_s' column; got {sorted(columns)}")
    out: dict[str, np.ndarray] = {}
    n = None
    for name, values in columns.items():
        if not isinstance(name, str) or not _COLUMN_RE.match(name):
            raise ValueError(f"column name {name!r}: expected an identifier like 'pos_m_x'")
        a = np.asarray(values)
        if a.ndim != 1:
            raise ValueError(f"column '{name}': expected 1-D, got shape {a.shape}")
        if a.dtype.kind not in "biuf":
            raise ValueError(f"column '{name}': expected numbers, got dtype {a.dtype}")
        if n is None:
            n = len(a)
        elif len(a) != n:
            raise ValueError(f"column '{name}': {len(a)} rows, other columns have {n}")
        out[name] = a
    t = out["t_s"].astype(float)
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise ValueError("column 't_s': expected finite, non-decreasing times")
    return out


def write_timeseries(out_dir: str | Path, columns: Mapping[str, np.ndarray]) -> Path:
    """Write the columns to ``out_dir/timeseries.npz`` (compressed); returns the path."""
    data = check_columns(columns)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / TIMESERIES_NAME
    np.savez_compressed(path, **data)
    return path


def read_timeseries(path: str | Path) -> dict[str, np.ndarray]:
    """Columns of a timeseries.npz (a file, or the run folder holding one)."""
    p = Path(path)
    if p.is_dir():
        p = p / TIMESERIES_NAME
    with np.load(p, allow_pickle=False) as npz:
        return {name: npz[name] for name in npz.files}
