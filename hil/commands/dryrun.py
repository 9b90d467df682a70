"""`hil dryrun SCENARIO --runs N`: fly a scenario's dispersed runs (its ``dispersions:`` block) as Ray
tasks and write the go/no-go page; exit 0 go, 1 no-go, 2 bad input."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from hil.commands import output_folder
from hil.commands.run import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_PASSED, read_scenario_file


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dryrun", help="fly a scenario's dispersed runs on Ray and give a go/no-go")
    p.add_argument("scenario", metavar="SCENARIO", help="a *.scenario.yaml file with a dispersions: block")
    p.add_argument("--runs", type=int, default=None, help="runs (default: the block's runs)")
    p.add_argument("--seed", type=int, default=None, help="the sweep's seed (default: the block's seed)")
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default reports/dryrun/<id>)")
    p.add_argument("-j", "--jobs", type=int, default=min(2, os.cpu_count() or 1),
                   help="Ray CPUs on this machine: runs at once (2)")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="fly on this Ray cluster (e.g. ray://head:10001 or auto) instead of this machine")
    p.add_argument("--ptys", action="store_true",
                   help="each run as two processes over ptys (default: one process, memory links)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    # (here, not at the top: Ray, seconds to import, only for this command; every `hil` call imports
    # each command module to build its parser)
    from hil.sweep import plan_sweep, run_sweep, summarise
    from hil.sweep.report import verdict_line, write_sweep
    from hil.sweep.sweep import stale

    path = Path(args.scenario)
    scenarios = read_scenario_file(path, "hil dryrun")
    if scenarios is None:
        return EXIT_BAD_INPUT
    swept = [s for s in scenarios if s.dispersions is not None]
    if len(swept) != 1:
        print(f"hil dryrun: {path} needs exactly one scenario with a dispersions: block, has {len(swept)}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.jobs < 1:
        print(f"hil dryrun: --jobs must be >= 1, got {args.jobs}", file=sys.stderr)
        return EXIT_BAD_INPUT
    s = swept[0]
    out = output_folder(args.out or Path("reports") / "dryrun" / s.id, "hil dryrun")
    if out is None:
        return EXIT_BAD_INPUT
    try:
        plan = plan_sweep(s, out, runs=args.runs, seed=args.seed)
    except ValueError as exc:
        print(f"hil dryrun: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        import ray  # noqa: F401
    except ImportError:
        print("hil dryrun: needs Ray: pip install 'crossgap-hil[sweep]'", file=sys.stderr)
        return EXIT_BAD_INPUT
    where = f"Ray cluster {args.ray_address}" if args.ray_address else f"local Ray, {args.jobs} CPUs"
    print(f"dry run {s.id}: {plan.runs} runs on {where} -> {out}", flush=True)
    why = stale(plan)
    if why is not None:
        print(f"  the results already in {out} are not this plan's ({why}): all runs are flown afresh",
              flush=True)
    tty = sys.stdout.isatty()
    wall0 = time.perf_counter()
    passed = [0]

    def progress(rec, done: int, total: int) -> None:  # type: ignore[no-untyped-def]
        passed[0] += rec.passed
        rate = done / max(time.perf_counter() - wall0, 1e-9)
        bar = "#" * (30 * done // total)
        line = (f"[{bar:<30}] {done}/{total} runs, {passed[0]} passed, {rate:.2f} runs/s; run {rec.index} "
                + ("PASSED" if rec.passed else "INVALID" if rec.invalid else "FAILED"))
        if tty:
            print("\r" + line, end="" if done < total else "\n", flush=True)
        else:
            print(line, flush=True)

    records = run_sweep(plan, address=args.ray_address, jobs=args.jobs, in_process=not args.ptys,
                        progress=progress)
    result = summarise(s.id, plan.dispersions, records)
    page = write_sweep(out, result, s.description, time.perf_counter() - wall0)
    print(verdict_line(result))
    for f in result.failures[:5]:
        print(f"  {f['runs']} runs failed {f['check']} in the {f['phase']}")
    print(f"  page: {page}")
    return EXIT_PASSED if result.go else EXIT_FAILED
