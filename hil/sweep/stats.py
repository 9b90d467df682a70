"""A sweep's answer from its runs: the success probability with a Wilson score interval, the failures
ranked by check and phase, the pass rate over each dispersed field and over two of them (the envelope
map), the smallest clearances, and go or no-go against the scenario's threshold."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any

import numpy as np

from hil.scenario.schema import Dispersions, Distribution
from hil.sweep.fly import RunRecord

#: reports linked per failure row of the page
LINKS_PER_FAILURE = 5


def wilson_interval(passed: int, n: int, confidence: float) -> tuple[float, float]:
    """Two-sided Wilson score interval of a success probability from ``passed`` of ``n`` runs."""
    if n == 0:
        return (0.0, 1.0)
    z = NormalDist().inv_cdf(0.5 + confidence / 2.0)
    p = passed / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


@dataclass(frozen=True)
class SweepResult:
    """The answer of a sweep (see the module docstring); ``to_dict`` is its JSON."""

    scenario_id: str
    runs: int
    counted: int
    passed: int
    probability: float | None
    interval: tuple[float, float]
    confidence: float
    min_success: float
    go: bool
    failures: list[dict[str, Any]]
    by_field: dict[str, list[dict[str, Any]]]
    envelope: dict[str, Any] | None
    clearances_m: list[float]
    invalid: list[dict[str, Any]] = field(default_factory=list)
    #: every dispersed field: its path, how it is drawn, and the range of the draws by component
    varied: list[dict[str, Any]] = field(default_factory=list)
    records: list[RunRecord] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario_id": self.scenario_id, "runs": self.runs, "counted": self.counted,
            "passed": self.passed, "success_probability": self.probability,
            "interval": list(self.interval), "confidence": self.confidence,
            "min_success": self.min_success, "go": self.go, "failures": self.failures,
            "by_field": self.by_field, "envelope": self.envelope, "clearances_m": self.clearances_m,
            "invalid": self.invalid, "varied": self.varied, "records": [r.to_dict() for r in self.records],
        }


def summarise(scenario_id: str, dispersions: Dispersions, records: list[RunRecord]) -> SweepResult:
    """The answer from ``records`` (in any order)."""
    records = sorted(records, key=lambda r: r.index)
    counted = [r for r in records if r.counted]
    n, k = len(counted), sum(r.passed for r in counted)
    go = dispersions.go
    lo, hi = wilson_interval(k, n, go.confidence)
    return SweepResult(
        scenario_id=scenario_id, runs=len(records), counted=n, passed=k,
        probability=k / n if n else None, interval=(lo, hi), confidence=go.confidence,
        min_success=go.min_success, go=n > 0 and lo >= go.min_success,
        failures=_failures(counted), by_field=_by_field(dispersions, counted),
        envelope=_envelope(dispersions, counted),
        clearances_m=[r.min_clearance_m for r in counted if r.min_clearance_m is not None],
        invalid=[{"index": r.index, "why": r.invalid} for r in records if not r.counted],
        varied=_varied(dispersions, records), records=records,
    )


def _failures(records: list[RunRecord]) -> list[dict[str, Any]]:
    """(check, phase) -> the runs that failed it there, most frequent first."""
    runs: dict[tuple[str, str], list[RunRecord]] = {}
    for r in records:
        if r.error is not None:
            runs.setdefault(("setup", "before the run"), []).append(r)
        for f in r.failed:
            runs.setdefault((f["check"], f["phase"]), []).append(r)
    counts = Counter({key: len(v) for key, v in runs.items()})
    return [
        {"check": check, "phase": phase, "runs": count, "fraction": count / len(records),
         "examples": [{"index": r.index, "report": r.report, "observed": _observed(r, check)}
                      for r in runs[(check, phase)][:LINKS_PER_FAILURE]]}
        for (check, phase), count in counts.most_common()
    ]


def _observed(r: RunRecord, check: str) -> str:
    if check == "setup":
        return r.error or ""
    return next((f["observed"] for f in r.failed if f["check"] == check), "")


def _scalar(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


def _edges(xs: np.ndarray, bins: int) -> np.ndarray:
    lo, hi = float(xs.min()), float(xs.max())
    if hi <= lo:
        hi = lo + 1e-9
    return np.linspace(lo, hi, bins + 1)


def _components(path: str, value: Any) -> list[tuple[str, float | None]]:
    """A drawn value as named numbers: a number as itself, a vector (``initial.pos_m``) by component
    (``initial.pos_m[0]``, ...); a value that is no number (a choice of names) as None."""
    if isinstance(value, list | tuple):
        return [(f"{path}[{i}]", _scalar(v)) for i, v in enumerate(value)]
    return [(path, _scalar(value))]


def _numbers(path: str, records: list[RunRecord]) -> dict[str, list[tuple[float, bool]]]:
    """Each numeric component of a dispersed field -> (its draw, the run passed), in the records' order."""
    out: dict[str, list[tuple[float, bool]]] = {}
    for r in records:
        for name, x in _components(path, r.values.get(path)):
            if x is not None:
                out.setdefault(name, []).append((x, r.passed))
    return out


def _how(d: Distribution) -> str:
    """How a field is drawn, as the scenario file says it (``normal [1, 0.02]``, ``offset``, ``clip``)."""
    text = f"{d.kind} {list(getattr(d, d.kind))}"
    return text + (" added to the scenario's value" if d.offset else "") + (
        f", clipped to {list(d.clip)}" if d.clip is not None else "")


def _varied(dispersions: Dispersions, records: list[RunRecord]) -> list[dict[str, Any]]:
    """Every dispersed field (numbers, vectors and choices alike): how it is drawn, and per component
    the smallest and largest draw (the values drawn, for a choice of names)."""
    out = []
    for path, dist in dispersions.vary:
        drawn = {name: [min(x for x, _ in xs), max(x for x, _ in xs)]
                 for name, xs in _numbers(path, records).items()}
        names = sorted({str(r.values.get(path)) for r in records if path in r.values and
                        all(x is None for _, x in _components(path, r.values[path]))})
        out.append({"path": path, "how": _how(dist), "drawn": drawn, "values": names})
    return out


def _by_field(dispersions: Dispersions, records: list[RunRecord]) -> dict[str, list[dict[str, Any]]]:
    """For each number a sweep disperses (each component of a vector): the pass rate in ``bins`` bins
    of its drawn values."""
    out: dict[str, list[dict[str, Any]]] = {}
    columns = {name: pairs for path, _ in dispersions.vary for name, pairs in _numbers(path, records).items()}
    for path, pairs in columns.items():
        xs = np.array([p[0] for p in pairs])
        ok = np.array([p[1] for p in pairs])
        edges = _edges(xs, dispersions.bins)
        idx = np.clip(np.searchsorted(edges, xs, side="right") - 1, 0, dispersions.bins - 1)
        out[path] = [
            {"lo": float(edges[b]), "hi": float(edges[b + 1]), "runs": int(np.sum(idx == b)),
             "passed": int(np.sum(ok[idx == b]))}
            for b in range(dispersions.bins)
        ]
    return out


def _envelope(dispersions: Dispersions, records: list[RunRecord]) -> dict[str, Any] | None:
    """The pass rate over two dispersed scalar fields (the block's ``envelope``, else the first two)."""
    scalars = [p for p, _ in dispersions.vary
               if any(_scalar(r.values.get(p)) is not None for r in records)]
    axes = dispersions.envelope or (tuple(scalars[:2]) if len(scalars) >= 2 else None)
    if axes is None or not records:
        return None
    pts = [(x, y, r.passed) for r in records
           if (x := _scalar(r.values.get(axes[0]))) is not None
           and (y := _scalar(r.values.get(axes[1]))) is not None]
    if not pts:
        return None
    b = dispersions.bins
    xs, ys = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
    ok = np.array([p[2] for p in pts])
    ex, ey = _edges(xs, b), _edges(ys, b)
    ix = np.clip(np.searchsorted(ex, xs, side="right") - 1, 0, b - 1)
    iy = np.clip(np.searchsorted(ey, ys, side="right") - 1, 0, b - 1)
    runs = np.zeros((b, b), dtype=int)
    passed = np.zeros((b, b), dtype=int)
    np.add.at(runs, (iy, ix), 1)
    np.add.at(passed, (iy, ix), ok.astype(int))
    return {"x": axes[0], "y": axes[1], "x_edges": ex.tolist(), "y_edges": ey.tolist(),
            "runs": runs.tolist(), "passed": passed.tolist(),
            "points": [[float(x), float(y), bool(o)] for x, y, o in pts]}
