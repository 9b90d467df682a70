"""summary.json: one run's verdict, checks, crossing, link statistics and events, as plain JSON.

The runner fills the dict; the keys the report page reads (all optional except ``passed``):

- ``passed`` (bool), ``end_reason`` (str), ``sim_time_s``, ``wall_time_s`` (s)
- ``checks``: list of {``name``, ``passed``, ``expected``, ``observed``, ``time_s``} (sim s or null)
- ``crossing``: {``time_s``, ``point_m`` [x, y, z] world ENU, ``through_opening`` bool} or null
- ``links``: {link name: {statistic name: number}}, e.g. ``{"mocap": {"delivered_fraction": 0.98}}``
- ``events``: list of {``time_s``, ``source``, ``text``} (FC state changes, faults, aborts)
- ``onboard``: the onboard program's closing summary (its counters: ``mocap`` refusals by kind,
  ``foreign`` messages, ``commands_refused``, ...) or null when it wrote none (killed)
- ``scenario``: `Scenario.to_dict()`
"""

from __future__ import annotations

import json
import math
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

SUMMARY_NAME = "summary.json"


def to_jsonable(value: Any) -> Any:
    """Plain JSON types: numpy scalars/arrays -> numbers/lists, dataclasses -> dicts, NaN/inf -> None."""
    kind = type(value)  # (the plain types first, as most of a summary is: the same answers, fewer checks)
    if kind is str or kind is int or kind is bool or value is None:
        return value
    if kind is float:
        return value if math.isfinite(value) else None
    if kind is dict or isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if is_dataclass(value) and not isinstance(value, type):
        to_dict = getattr(value, "to_dict", None)
        if callable(to_dict):
            return to_jsonable(to_dict())
        return {f.name: to_jsonable(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, list | tuple | set | frozenset):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return str(value)


def write_summary(out_dir: str | Path, summary: dict[str, Any]) -> Path:
    """Write ``summary`` as ``out_dir/summary.json`` (created if needed); returns the path. Written
    whole or not at all (a temporary file renamed over it): a run writes it after its other files, so
    that a reader never finds a verdict without the report and data behind it."""
    if not isinstance(summary, dict):
        raise TypeError(f"summary must be a dict, got {type(summary).__name__}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / SUMMARY_NAME
    text = json.dumps(to_jsonable(summary), indent=2, allow_nan=False)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(text + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def read_summary(path: str | Path) -> dict[str, Any]:
    """Read a summary.json (a file, or the run folder holding one)."""
    p = Path(path)
    if p.is_dir():
        p = p / SUMMARY_NAME
    data = json.loads(p.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        raise ValueError(f"{p}: expected a JSON object")
    return data
