"""Dispersed scenarios: a field's path in a scenario document, each run's draws from its seed, and the
scenario document with the draws applied (`hil.scenario.loader.dispersed` validates it again, as a file).

A path names a field as a scenario file nests it: ``gap.roll_deg``, ``links.mocap.latency_ms``,
``initial.pos_m[2]``, ``faults[0].params.force_n``. Two paths name no field of the file but a steady
wind over the whole run: ``wind.speed_m_s`` (m/s, the drag model of a ``wind_gust``) and
``wind.direction_deg`` (where it blows towards, deg from world +x, horizontal; default 90: +y).
"""

from __future__ import annotations

import copy
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from hil.scenario.schema import FIXED_FIELDS, Dispersions, Distribution, Scenario

WIND_SPEED, WIND_DIRECTION = "wind.speed_m_s", "wind.direction_deg"
WIND_PATHS = (WIND_SPEED, WIND_DIRECTION)
DEFAULT_WIND_DIRECTION_DEG = 90.0
_PART_RE = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)")
SEED_HI = 2**63 - 1


class PathError(ValueError):
    """A dispersion's path names no field of the scenario (the message says why)."""


def parse_path(path: str) -> list[str | int]:
    """``a.b[1].c`` -> ``["a", "b", 1, "c"]``; PathError when malformed."""
    parts: list[str | int] = []
    for piece in path.split("."):
        m = _PART_RE.fullmatch(piece)
        if m is None:
            raise PathError(f"expected a field path such as gap.roll_deg or initial.pos_m[2], got {path!r}")
        parts.append(m.group(1))
        parts += [int(i) for i in re.findall(r"\[(\d+)\]", m.group(2))]
    return parts


def value_at(doc: dict[str, Any], path: str) -> Any:
    """The value at ``path`` in a scenario document (``Scenario.to_dict``); PathError when none."""
    if path in WIND_PATHS:
        return 0.0 if path == WIND_SPEED else DEFAULT_WIND_DIRECTION_DEG
    parts = parse_path(path)
    if parts[0] in FIXED_FIELDS:
        raise PathError(f"{parts[0]} is not dispersed (each run draws its own seed)")
    node: Any = doc
    walked = ""
    for part in parts:
        if isinstance(part, int):
            if not isinstance(node, list) or part >= len(node):
                raise PathError(f"{walked} has no item [{part}]")
            node = node[part]
            walked += f"[{part}]"
            continue
        if not isinstance(node, dict) or part not in node:
            what = "is null in this scenario (give it in the file to vary its fields)" if node is None \
                else "has no field " + repr(part)
            raise PathError(f"{walked or 'the scenario'} {what}")
        node = node[part]
        walked = f"{walked}.{part}" if walked else part
    if isinstance(node, dict):
        raise PathError(f"{path} is a block of fields; name one of them ({', '.join(node)})")
    if node is None:
        raise PathError(f"{path} is null in this scenario: give it a value in the file to vary it")
    return node


def _set(doc: dict[str, Any], path: str, value: Any) -> None:
    parts = parse_path(path)
    node: Any = doc
    for part in parts[:-1]:
        node = node[part]
    node[parts[-1]] = value


def draw(dist: Distribution, current: Any, rng: np.random.Generator) -> Any:
    """One draw of ``dist`` for a field whose scenario value is ``current`` (a vector draws each
    component); whole-number fields get whole numbers."""
    if isinstance(current, list):
        return [draw(dist, c, rng) for c in current]
    if dist.choice is not None:
        value = dist.choice[int(rng.integers(len(dist.choice)))]
    elif dist.uniform is not None:
        value = float(rng.uniform(*dist.uniform))
    else:
        assert dist.normal is not None
        value = float(rng.normal(*dist.normal))
    if dist.offset:
        value = current + value
    if dist.clip is not None and isinstance(value, int | float) and not isinstance(value, bool):
        value = min(max(value, dist.clip[0]), dist.clip[1])
    if isinstance(current, int) and not isinstance(current, bool) and isinstance(value, float):
        value = round(value)
    return value


def run_seeds(dispersions: Dispersions, runs: int) -> list[int]:
    """Each run's seed, drawn from one generator seeded with the block's ``seed``: run i's seed is the
    same whatever the number of runs (a longer sweep extends a shorter one)."""
    master = np.random.default_rng(dispersions.seed)
    return [int(x) for x in master.integers(0, SEED_HI, size=runs, dtype=np.int64)]


def sample(dispersions: Dispersions, doc: dict[str, Any], seed: int) -> dict[str, Any]:
    """Run ``seed``'s draw of every dispersed field (path -> value), from a generator of its own."""
    rng = np.random.default_rng(seed)
    return {path: draw(dist, value_at(doc, path), rng) for path, dist in dispersions.vary}


def apply(doc: dict[str, Any], values: dict[str, Any]) -> dict[str, Any]:
    """``doc`` (a `Scenario.to_dict` without meta) with ``values`` set; a wind adds a ``wind_gust`` over
    the whole run. ``doc`` itself is left as it was."""
    out = copy.deepcopy(doc)
    for path, value in values.items():
        if path not in WIND_PATHS:
            _set(out, path, value)
    speed = float(values.get(WIND_SPEED, 0.0))
    if speed > 0.0:
        a = math.radians(float(values.get(WIND_DIRECTION, DEFAULT_WIND_DIRECTION_DEG)))
        out["faults"] = [*out.get("faults", []), {
            "kind": "wind_gust", "start_s": 0.0,
            "params": {"direction": [math.cos(a), math.sin(a), 0.0], "speed_m_s": speed}}]
    return out


def base_document(scenario: Scenario) -> dict[str, Any]:
    """The scenario as a document to apply draws to: no dispersions, a vehicle file's path absolute."""
    doc = scenario.to_dict(include_meta=False)
    doc.pop("dispersions", None)
    if str(doc["vehicle"]).endswith((".yaml", ".yml")):
        doc["vehicle"] = str(Path(doc["vehicle"]).resolve())
    return doc
