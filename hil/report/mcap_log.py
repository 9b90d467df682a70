"""A run folder as an MCAP recording (``run.mcap`` beside ``run.tlog``) for Foxglove and other MCAP
tools: the vehicle's pose (``foxglove.PoseInFrame`` in frame ``world``, ENU), every time-series column
by name (``/state``), and the run's events (``foxglove.Log``). Written from the folder's files after
the run (`hil run --mcap`, `hil view RUN_DIR --mcap`): nothing is recorded while it flies."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from hil.link.mavlink import quat_enu_flu_to_ned_frd, quat_from_euler
from hil.report.timeseries import read_timeseries

MCAP_NAME = "run.mcap"
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_VEC = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
POSE_SCHEMA = {"type": "object", "properties": {
    "timestamp": _TIME, "frame_id": {"type": "string"},
    "pose": {"type": "object", "properties": {"position": _VEC, "orientation": _QUAT}}}}
LOG_SCHEMA = {"type": "object", "properties": {
    "timestamp": _TIME, "level": {"type": "integer"}, "message": {"type": "string"},
    "name": {"type": "string"}, "file": {"type": "string"}, "line": {"type": "integer"}}}
_INFO, _WARNING = 2, 3  # foxglove.Log levels


def _stamp(t_s: float) -> tuple[int, dict[str, int]]:
    ns = max(0, round(t_s * 1e9))
    return ns, {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def write_mcap(run_dir: str | Path) -> Path:
    """``run_dir/run.mcap`` from the folder's timeseries.npz and summary.json; returns its path.
    ValueError when the mcap package is missing (``pip install 'crossgap-hil[mcap]'``)."""
    try:
        from mcap.writer import Writer
    except ImportError as exc:
        raise ValueError("MCAP recordings need the mcap package: pip install 'crossgap-hil[mcap]'") from exc

    d = Path(run_dir)
    cols = read_timeseries(d)
    summary: dict[str, Any] = json.loads((d / "summary.json").read_text(encoding="utf-8"))
    names = list(cols)
    state_schema = {"type": "object", "properties": {n: {"type": ["number", "null"]} for n in names}}
    path = d / MCAP_NAME
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="", library="crossgap-hil")

        def channel(topic: str, schema_name: str, schema: dict[str, Any]) -> int:
            sid = w.register_schema(name=schema_name, encoding="jsonschema", data=json.dumps(schema).encode())
            return w.register_channel(topic=topic, message_encoding="json", schema_id=sid)

        pose_ch = channel("/vehicle/pose", "foxglove.PoseInFrame", POSE_SCHEMA)
        state_ch = channel("/state", "crossgap_hil.State", state_schema)
        log_ch = channel("/events", "foxglove.Log", LOG_SCHEMA)
        data = np.column_stack([cols[n] for n in names]).tolist()
        rad = math.radians
        for row in data:
            r = dict(zip(names, row, strict=True))
            ns, stamp = _stamp(r["t_s"])
            clean = {k: (v if math.isfinite(v) else None) for k, v in r.items()}
            w.add_message(channel_id=state_ch, log_time=ns, publish_time=ns,
                          data=json.dumps(clean, separators=(",", ":")).encode())
            if not all(math.isfinite(r[k]) for k in ("pos_m_x", "roll_deg", "pitch_deg", "yaw_deg")):
                continue
            # the recorded attitude is body FRD -> world NED; the same map takes it back to FLU -> ENU
            q = quat_enu_flu_to_ned_frd(quat_from_euler(rad(r["roll_deg"]), rad(r["pitch_deg"]),
                                                        rad(r["yaw_deg"])))
            pose = {"timestamp": stamp, "frame_id": "world", "pose": {
                "position": {"x": r["pos_m_x"], "y": r["pos_m_y"], "z": r["pos_m_z"]},
                "orientation": {"w": q[0], "x": q[1], "y": q[2], "z": q[3]}}}
            w.add_message(channel_id=pose_ch, log_time=ns, publish_time=ns,
                          data=json.dumps(pose, separators=(",", ":")).encode())
        for ev in summary.get("events", []):
            t = ev.get("time_s")
            if not isinstance(t, int | float):
                continue
            ns, stamp = _stamp(float(t))
            text = str(ev.get("text", ""))
            level = _WARNING if any(k in text for k in ("failsafe", "abort", "collision")) else _INFO
            msg = {"timestamp": stamp, "level": level, "message": text, "name": str(ev.get("source", "")),
                   "file": "", "line": 0}
            w.add_message(channel_id=log_ch, log_time=ns, publish_time=ns, data=json.dumps(msg).encode())
        w.finish()
    return path
