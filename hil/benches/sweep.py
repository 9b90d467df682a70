"""Sweep benches: dispersed runs a second on local Ray (`hil dryrun`) against `hil suite -j 2` flying
the same dispersed scenarios as files, in the same sitting."""

from __future__ import annotations

import contextlib
import io
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import yaml

from hil.benches import BenchRow
from hil.cli import main
from hil.scenario import load_scenarios
from hil.scenario.loader import dispersed
from hil.sweep import plan_sweep, run_sweep

SCENARIO = Path(__file__).resolve().parents[2] / "scenarios" / "gap_roll60_2p5ms.scenario.yaml"
JOBS = 2


def collect(quick: bool) -> Iterator[BenchRow]:
    runs = 8 if quick else 60
    [s] = load_scenarios(SCENARIO)
    with tempfile.TemporaryDirectory() as tmp:
        plan = plan_sweep(s, Path(tmp) / "ray", runs=runs)
        files = Path(tmp) / "files"
        files.mkdir()
        for i in range(runs):
            d = dispersed(s, plan.values[i], plan.seeds[i], f"{s.id}-{i:04d}")
            (files / f"{d.id}.scenario.yaml").write_text(yaml.safe_dump(d.to_dict(include_meta=False)))
        t0 = time.perf_counter()
        run_sweep(plan, jobs=JOBS)
        ray_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            main(["suite", str(files), "--in-process", "-j", str(JOBS), "--out", str(Path(tmp) / "suite")])
        suite_s = time.perf_counter() - t0
    ray_rate, suite_rate = runs / ray_s, runs / suite_s
    yield BenchRow("sweep_ray_runs_per_s", ray_rate, "runs/s",
                   f"hil dryrun of {runs} dispersed 11 s runs of the 60 deg scenario on local Ray, {JOBS} "
                   f"CPUs, Ray's start-up included ({ray_s:.1f} s)")
    yield BenchRow("sweep_suite_runs_per_s", suite_rate, "runs/s",
                   f"hil suite -j {JOBS} --in-process on the same {runs} runs as scenario files "
                   f"({suite_s:.1f} s)")
    yield BenchRow("sweep_ray_vs_suite", ray_rate / suite_rate, "x",
                   "the two above, Ray over the suite's pool")
