"""Runner benches: the full stack in lockstep over ptys (real-time factor) and the suite's wall time."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hil.benches import BenchRow, time_per_call
from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios
from hil.scenario.loader import find_scenario_files, load_scenarios

SCENARIOS_DIR = Path(__file__).resolve().parents[2] / "scenarios"
RTF_SCENARIO = """
description: bench - the release's 60 deg gap at 2.5 m/s, traditional pilot
gap: {roll_deg: -60}
approach: {speed_m_s: 2.5}
duration_s: 11
"""


#: runs of the scenario per figure: the figure is their median (one run on a shared machine can meet a
#: busy host; the spread is printed beside it)
RTF_RUNS = 3


def collect(quick: bool) -> Iterator[BenchRow]:
    if SCENARIOS_DIR.is_dir():
        files = find_scenario_files(SCENARIOS_DIR)
        per_load = time_per_call(lambda: [load_scenarios(f) for f in files], min_time_s=0.3 if quick else 1.0)
        yield BenchRow("scenario_load_ms", 1e3 * per_load, "ms",
                       f"the {len(files)} files under scenarios/ parsed and validated, dispersions too")
    s = loads_scenarios(RTF_SCENARIO)[0]
    with tempfile.TemporaryDirectory() as tmp:
        for in_process, name in ((False, "full_stack_rtf"), (True, "in_process_rtf")):
            summaries = []
            for k in range(RTF_RUNS):
                r = run_scenario(s, Path(tmp) / f"{name}_{k}", RunOptions(in_process=in_process))
                if not r.passed:  # a figure from a failed flight would not be the figure asked for
                    failed = "; ".join(f"{c.name}: {c.observed}" for c in r.failed_checks)
                    raise RuntimeError(f"bench scenario failed its checks ({name}): {failed}")
                summaries.append(r.summary)
            summaries.sort(key=lambda sm: sm["real_time_factor"])
            sm = summaries[len(summaries) // 2]
            spread = ", ".join(f"{x['real_time_factor']:.1f}" for x in summaries)
            yield BenchRow(
                name,
                sm["real_time_factor"],
                "x real time",
                f"60 deg gap, {'one process, memory links' if in_process else 'two processes over ptys'}"
                f", lockstep, median of {RTF_RUNS} runs ({spread}); {sm['loop_sim_time_s']:.2f} s sim in "
                f"{sm['loop_wall_time_s']:.2f} s (onboard start-up before the loop "
                f"{sm['onboard_startup_s']:.2f} s, whole run {sm['wall_time_s']:.2f} s)",
            )
            if not in_process:
                yield BenchRow(
                    "full_stack_rtf_with_startup",
                    sm["sim_time_s"] / (sm["loop_wall_time_s"] + sm["onboard_startup_s"]),
                    "x real time",
                    "the same run, the onboard program's start-up counted in the loop",
                )
        if quick or not SCENARIOS_DIR.is_dir():
            return
        yield from suite_rows(Path(tmp) / "suite")
        t0 = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", str(SCENARIOS_DIR)],
            capture_output=True,
            timeout=3600,
        )
        yield BenchRow(
            "suite_wall_s",
            time.perf_counter() - t0,
            "s",
            "pytest scenarios/ -n 2 (whole shipped suite, pass or fail)",
        )


def suite_rows(out: Path, jobs: int = 2) -> Iterator[BenchRow]:
    """``suite_rtf``, ``onboard_startup_ms`` and ``suite_cpu_ms_per_sim_s``: the shipped suite as
    `hil suite` flies it (``jobs`` workers, two processes per run over ptys, lockstep, the onboard
    program started warm)."""
    proc = subprocess.run(
        [sys.executable, "-m", "hil.cli", "suite", str(SCENARIOS_DIR), "--out", str(out), "-j", str(jobs)],
        capture_output=True, text=True, timeout=3600,
    )
    index = json.loads((out / "index.json").read_text(encoding="utf-8"))
    results = index["results"]
    failed = [r["id"] for r in results if not r["passed"]]
    if failed or proc.returncode != 0:  # the figure is the suite's with its verdicts, or none
        raise RuntimeError(f"the shipped suite did not pass: {failed or proc.stderr[-2000:]}")
    sim_s = sum(r["sim_time_s"] for r in results)
    yield BenchRow(
        "suite_rtf",
        sim_s / index["wall_time_s"],
        "x real time",
        f"hil suite scenarios/ -j {jobs}: {len(results)} runs, {sim_s:.0f} s sim in "
        f"{index['wall_time_s']:.1f} s wall, all passed",
    )
    summaries = [json.loads((out / r["id"] / "summary.json").read_text(encoding="utf-8")) for r in results]
    yield from suite_cpu_rows(summaries, sim_s)


def suite_cpu_rows(summaries: list[dict], sim_s: float) -> Iterator[BenchRow]:
    """``onboard_startup_ms``, the tick CPU rows and ``suite_cpu_ms_per_sim_s`` from a suite's summaries
    (``sim_s``: its simulated seconds); a run refused before take-off starts no program and flies no tick."""
    flown = [sm for sm in summaries if sm.get("ticks")]
    startups = sorted(sm["onboard_startup_s"] for sm in flown)
    yield BenchRow(
        "onboard_startup_ms",
        1e3 * float(np.median(startups)),
        "ms",
        f"median over the suite's {len(startups)} flown runs, from the onboard program's spawn to its first "
        f"answered tick (max {1e3 * startups[-1]:.0f} ms)",
    )
    yield from tick_cpu_rows(flown)
    harness = sum(sm["cpu_s"]["harness"] for sm in flown)
    onboard = [sm["cpu_s"]["onboard"] for sm in flown]
    if all(isinstance(v, float) for v in onboard):  # (every program forked warm: its CPU time is known)
        yield BenchRow(
            "suite_cpu_ms_per_sim_s",
            1e3 * (harness + sum(onboard)) / sim_s,
            "ms",
            f"CPU time of both sides a simulated second over the suite's runs (harness {harness:.1f} s + "
            f"onboard programs {sum(onboard):.1f} s, reports excluded): what a suite costs, which the "
            "host's load moves less than its wall time",
        )


def tick_cpu_rows(summaries: list[dict]) -> Iterator[BenchRow]:
    """``tick_cpu_us_emulator`` and ``tick_cpu_us_onboard``: each side's process CPU time over a run
    (summary.json's ``cpu_s``) per lockstep tick, medians over the flown runs of ``summaries`` (a refused
    run flies no tick; a run's onboard CPU is known where its program was forked warm)."""
    flown = [sm for sm in summaries if sm.get("ticks")]
    for side, key, what in (("emulator", "harness", "the harness's process (emulator side, runner, recorder, "
                             "checks)"), ("onboard", "onboard", "the onboard program's process")):
        per_tick = sorted(1e6 * sm["cpu_s"][key] / sm["ticks"] for sm in flown
                          if isinstance(sm["cpu_s"][key], float))
        if per_tick:
            yield BenchRow(
                f"tick_cpu_us_{side}",
                float(np.median(per_tick)),
                "us",
                f"CPU time of {what} per tick, its start-up included, median over {len(per_tick)} runs "
                f"of the suite ({per_tick[0]:.0f}..{per_tick[-1]:.0f})",
            )
