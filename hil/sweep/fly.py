"""One dispersed run, as a worker flies it: the scenario with the run's draws, a lockstep run through
the links (`hil.runner.run_scenario`), and a record of what the sweep needs from it."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil.runner import RunOptions, RunSetupError, run_scenario
from hil.runner.run import SEGMENT_PHASES
from hil.scenario import ScenarioError
from hil.scenario.loader import dispersed
from hil.scenario.schema import Scenario

#: the recorded ``phase`` column's codes (see the runner's phase column), by name
_PHASE_NAMES = {code: name for name, code in SEGMENT_PHASES.items() if code} | {4: "abort or failsafe"}


@dataclass(frozen=True)
class RunRecord:
    """What one dispersed run gave: its draws and seed, the verdict, each failed check with the flight
    phase it failed in, the smallest clearance (m) and where a failed run's report is (relative to the
    sweep; a passed run's folder ``runs/NNNN`` holds its summary.json, run.tlog and timeseries.npz)."""

    index: int
    seed: int
    values: dict[str, Any]
    passed: bool
    invalid: str | None = None  # the draws made no valid scenario (the loader's message); not counted
    error: str | None = None  # the run could not be set up (RunSetupError's message)
    failed: tuple[dict[str, Any], ...] = ()
    min_clearance_m: float | None = None
    crossed_gap: bool | None = None
    report: str | None = None
    wall_time_s: float = 0.0
    worker: str = field(default="", compare=False)

    @property
    def counted(self) -> bool:
        """Whether the run counts towards the success probability (its draws made a scenario)."""
        return self.invalid is None

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["failed"] = list(self.failed)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RunRecord:
        return cls(**{**d, "failed": tuple(d.get("failed", ()))})


def run_name(scenario: Scenario, index: int) -> str:
    return f"{scenario.id}-{index:04d}"


def fly(scenario: Scenario, index: int, seed: int, values: dict[str, Any], sweep_dir: str,
        in_process: bool = True) -> RunRecord:
    """Fly run ``index`` of ``scenario``'s sweep (draws ``values``, ``seed``) into ``sweep_dir/runs/``."""
    import os
    import socket

    worker = f"{socket.gethostname()}:{os.getpid()}"
    name = run_name(scenario, index)
    try:
        s = dispersed(scenario, values, seed, name)
    except ScenarioError as exc:
        return RunRecord(index, seed, values, False, invalid=f"{exc.field}: {exc.message}", worker=worker)
    rel = Path("runs") / f"{index:04d}"
    out = Path(sweep_dir) / rel
    t0 = time.perf_counter()
    try:
        r = run_scenario(s, out, RunOptions(in_process=in_process, realtime=False, html_report="failed"))
    except (RunSetupError, ValueError) as exc:
        return RunRecord(index, seed, values, False, error=str(exc), worker=worker,
                         wall_time_s=time.perf_counter() - t0)
    failed = tuple(
        {"check": c.name, "phase": _phase_at(out, c.time_s), "time_s": c.time_s,
         "expected": str(c.expected), "observed": str(c.observed)}
        for c in r.failed_checks
    )
    sm = r.summary
    return RunRecord(
        index, seed, values, r.passed, failed=failed, min_clearance_m=sm.get("min_clearance_m"),
        crossed_gap=sm.get("crossed_gap"), report=None if r.passed else str(rel / "report.html"),
        wall_time_s=time.perf_counter() - t0, worker=worker,
    )


def _phase_at(out: Path, time_s: float | None) -> str:
    """The flight phase at sim time ``time_s`` as the run recorded it ("whole run" without a time)."""
    if time_s is None:
        return "whole run"
    if not (out / "timeseries.npz").is_file():  # refused before take-off: nothing was flown
        return "before take-off"
    with np.load(out / "timeseries.npz") as z:
        t, phase = z["t_s"], z["phase"]
    if len(t) == 0:
        return "takeoff"
    i = min(int(np.searchsorted(t, time_s)), len(t) - 1)
    code = int(phase[i])
    if code == 0:  # before the mission's first segment: the takeoff; after it: the hover
        return "hover" if np.any(phase[:i] > 0) else "takeoff"
    return _PHASE_NAMES.get(code, "unknown")
