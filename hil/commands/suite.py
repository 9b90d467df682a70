"""`hil suite DIR`: fly every scenario under DIR (in parallel workers), write each report and an
index.html linking them all; exit 0 all passed, 1 some failed, 2 bad input, 130 interrupted (SIGINT: the
index lists the runs that finished and marks the others interrupted)."""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from html import escape
from pathlib import Path
from typing import Any

from emulator.profile import load_profile
from hil.commands import output_folder, say_if_compiling
from hil.commands.run import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_PASSED, add_run_options, options_from
from hil.report.summary import SUMMARY_NAME, read_summary
from hil.runner import RunOptions, RunSetupError, run_scenario
from hil.runner.onboard_side import prestart
from hil.runner.run import not_applicable
from hil.runner.warm_up import Compiling, compile_beside, families_of, warm_up
from hil.scenario import ScenarioError, find_scenario_files, load_scenarios
from hil.scenario.schema import Scenario

EXIT_INTERRUPTED = 130  # as the shell's for SIGINT


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "suite", help="fly every *.scenario.yaml under a folder and write reports + index.html"
    )
    p.add_argument("folder", metavar="DIR", help="folder of scenario files (searched recursively)")
    p.add_argument("--out", default="reports", metavar="DIR", help="output folder (default reports/)")
    p.add_argument("-j", "--jobs", type=int, default=min(2, os.cpu_count() or 1), help="parallel runs (2)")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="fly the runs as tasks on this Ray cluster (e.g. auto) instead of local processes")
    add_run_options(p)
    p.set_defaults(func=main)


def _run(args: tuple[Scenario, str, RunOptions]) -> dict[str, Any]:
    s, out, options = args
    options = replace(options, worker=_worker)
    _compiling.wait_for(s)  # (rather than compile them a second time)
    try:
        r = run_scenario(s, out, options)
    except (RunSetupError, ValueError) as exc:
        return {"id": s.id, "passed": False, "error": str(exc), "source": s.source}
    return _result(s, r.summary)


def _result(s: Scenario, summary: dict[str, Any]) -> dict[str, Any]:
    """The index's entry of a finished run of ``s``, from its summary."""
    return {
        "id": s.id,
        "passed": summary["passed"],
        "source": s.source,
        "description": s.description,
        "report": str(Path(s.id) / "report.html"),
        "sim_time_s": summary["sim_time_s"],
        "wall_time_s": summary["wall_time_s"],
        "failed": [f"{c['name']}: expected {c['expected']}, observed {c['observed']}"
                   for c in summary["checks"] if not c["passed"]],
    }


def _after_interrupt(s: Scenario, out: Path, since: float) -> dict[str, Any]:
    """The entry of a run the suite did not see finish before it was interrupted: finished after all
    when its folder holds a summary written since ``since`` (time.time(); the summary is a run's last
    file), else marked interrupted."""
    path = out / s.id / SUMMARY_NAME
    try:
        if path.stat().st_mtime >= since:
            return _result(s, read_summary(path))
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return {"id": s.id, "passed": False, "interrupted": True, "source": s.source,
            "description": s.description}


_worker: int | None = None  # this worker's number (in a worker process)
_compiling = Compiling()  # kernel families compiling beside the warm-up (the workers inherit it)


def _start_worker(numbers: Any, warm: bool) -> None:
    """A worker's start: its number (its runs keep to that core when the workers fill the cores, see
    `lockstep_cpu`), and the onboard fork server (this process's, if it was not forked from one that
    has it); it leaves Ctrl-C to the suite's own process."""
    global _worker
    # Ctrl-C reaches the whole process group: the suite's own process decides (no run started after it,
    # the ones flying finish and are indexed); a worker would only print a traceback from its queue
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with numbers.get_lock():
        _worker = numbers.value
        numbers.value += 1
    if warm:
        prestart()


def _results(work: list[tuple[Scenario, str, RunOptions]], workers: int, ray_address: str | None,
             warm: bool) -> Iterator[dict[str, Any]]:
    """Each run's result: from a local process pool in order (workers forked from this process where
    the platform forks, so they share what it loaded and its onboard fork server), or from Ray tasks as
    they finish."""
    if ray_address is not None:
        from hil.sweep.sweep import ray_imap, ray_session  # (Ray's imports only with a Ray address)

        with ray_session(ray_address, workers):
            for k, res in ray_imap(_run, (), [(w,) for w in work]):
                yield res if isinstance(res, dict) else {"id": work[k][0].id, "passed": False,
                                                        "error": f"its Ray task failed: {res}"}
        return
    fork = multiprocessing.get_context("fork") if "fork" in multiprocessing.get_all_start_methods() else None
    global _compiling
    if fork is not None and work:  # the workers are forked from this process: they start with what it
        if warm:  # loaded, and share its onboard fork server (which imports meanwhile)
            prestart()
        # on a cold kernel cache, the families only some runs use compile on the other cores meanwhile
        _compiling = compile_beside(families_of(w[0] for w in work), work[0][2])
        warm_up(work[0][2])
    numbers = (fork or multiprocessing).Value("i", 0)
    try:
        with ProcessPoolExecutor(
            max_workers=workers, mp_context=fork, initializer=_start_worker, initargs=(numbers, warm)
        ) as pool:
            try:
                yield from pool.map(_run, work)
            except BaseException:  # (interrupted, or closed early) no run is started after this one
                pool.shutdown(wait=True, cancel_futures=True)
                raise
    finally:
        _compiling.join()
        _compiling = Compiling()


def main(args: argparse.Namespace) -> int:
    folder = Path(args.folder)
    if not folder.is_dir():
        print(f"hil suite: {folder} is not a folder", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.jobs < 1:
        print(f"hil suite: --jobs must be >= 1, got {args.jobs}", file=sys.stderr)
        return EXIT_BAD_INPUT
    options = options_from(args)
    warm = not (options.cold_start or options.in_process)  # each worker's fork server starts at once
    if warm and args.ray_address is None:  # (it imports while the scenarios load and the kernels warm up:
        prestart()  # the first runs wait ~0.1 s less for it)
    try:
        files = [f for f in find_scenario_files(folder) if "examples" not in f.relative_to(folder).parts[:-1]]
        scenarios = [s for f in files for s in load_scenarios(f)]
    except ScenarioError as exc:
        print(f"hil suite: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    ids = [s.id for s in scenarios]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        print(f"hil suite: scenario ids used twice: {', '.join(dupes)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out = output_folder(args.out, "hil suite")
    if out is None:
        return EXIT_BAD_INPUT
    say_if_compiling("hil suite")
    if options.vehicle is not None:  # refused once, not failed in every run
        try:
            load_profile(options.vehicle)
        except ValueError as exc:
            print(f"hil suite: --vehicle {options.vehicle}: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
    skip = {s.id: s.skip for s in scenarios if s.skip}
    if options.vehicle is not None:  # scenarios that do not apply to the vehicle flown in their place
        skip.update({s.id: f"not applicable to {options.vehicle}: {why}" for s in scenarios
                     if s.id not in skip and (why := not_applicable(s, options.vehicle))})
    todo = [s for s in scenarios if s.id not in skip]
    skipped = [{"id": s.id, "skipped": skip[s.id], "source": s.source} for s in scenarios if s.id in skip]
    wall0 = time.perf_counter()
    results: list[dict[str, Any]] = []
    workers = max(1, min(args.jobs, len(todo)))
    options = replace(options, parallel_runs=workers)
    # the longest first, so that no long run starts last while the other workers sit idle; the index
    # lists them in the suite's order all the same
    work = [(s, str(out / s.id), options) for s in sorted(todo, key=lambda s: -s.duration_s)]
    started = time.time()
    try:
        for res in _results(work, workers, args.ray_address, warm):
            word = "PASSED" if res["passed"] else "FAILED"
            print(
                f"{word} {res['id']}" + (f" ({res['wall_time_s']:.1f} s)" if "wall_time_s" in res else ""),
                flush=True,
            )
            for line in res.get("failed", []) + ([res["error"]] if "error" in res else []):
                print(f"  {line}")
            results.append(res)
    except KeyboardInterrupt:  # (Ctrl-C) an index of what finished, the rest marked interrupted
        seen = {r["id"] for r in results}
        results += [_after_interrupt(s, out, started) for s in todo if s.id not in seen]
    wall = time.perf_counter() - wall0
    order = {s.id: k for k, s in enumerate(todo)}
    results.sort(key=lambda r: order.get(r["id"], len(order)))
    index = write_index(out, results, skipped, wall)
    n_pass = sum(r["passed"] for r in results)
    n_stopped = sum(bool(r.get("interrupted")) for r in results)
    if n_stopped:
        print(f"interrupted: {len(results) - n_stopped}/{len(results)} runs finished, {n_pass} passed; "
              f"index: {index}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"{n_pass}/{len(results)} passed, {len(skipped)} skipped, {wall:.1f} s wall; index: {index}")
    return EXIT_PASSED if n_pass == len(results) else EXIT_FAILED


def write_index(
    out: Path, results: list[dict[str, Any]], skipped: list[dict[str, Any]], wall_s: float
) -> Path:
    """``out/index.html`` (a table linking each report) and ``out/index.json``; returns the HTML path."""
    (out / "index.json").write_text(
        json.dumps({"wall_time_s": wall_s, "results": results, "skipped": skipped}, indent=2) + "\n",
        encoding="utf-8",
    )
    rows = []
    for r in results:
        cls, word = ("pass", "PASSED") if r["passed"] else ("fail", "FAILED")
        if r.get("interrupted"):
            cls, word = "stopped", "INTERRUPTED"
        link = f'<a href="{escape(r["report"])}">{escape(r["id"])}</a>' if "report" in r else escape(r["id"])
        why = "<br>".join(escape(x) for x in r.get("failed", []) + ([r["error"]] if "error" in r else []))
        rows.append(
            f'<tr class="{cls}"><td>{link}</td><td class="v">{word}</td>'
            f"<td>{escape(r.get('description', ''))}</td><td>{why}</td></tr>"
        )
    for r in skipped:
        rows.append(
            f'<tr><td>{escape(r["id"])}</td><td class="v">SKIPPED</td><td>{escape(r["skipped"])}</td>'
            "<td></td></tr>"
        )
    n_pass = sum(r["passed"] for r in results)
    n_stopped = sum(bool(r.get("interrupted")) for r in results)
    stopped = f" ({n_stopped} interrupted)" if n_stopped else ""
    html = (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>Scenario suite</title><style>'
        "body{font:14px system-ui,sans-serif;margin:20px;color:#1d232b}"
        "table{border-collapse:collapse;width:100%}"
        "td,th{border:1px solid #dde1e6;padding:5px 8px;text-align:left;vertical-align:top}"
        "tr.pass .v{color:#1e8a4c;font-weight:700}tr.fail .v{color:#c0392b;font-weight:700}"
        "tr.fail td{background:#fdeceb}tr.stopped .v{color:#8a6d1e;font-weight:700}</style></head><body>"
        f"<h1>Scenario suite: {n_pass}/{len(results)} passed{stopped}</h1>"
        f"<p>{len(skipped)} skipped; {wall_s:.1f} s wall.</p>"
        "<table><tr><th>Scenario</th><th>Verdict</th><th>Description</th><th>Failed checks</th></tr>"
        + "".join(rows)
        + "</table></body></html>"
    )
    path = out / "index.html"
    path.write_text(html, encoding="utf-8")
    return path
