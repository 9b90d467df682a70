"""`hil bench`: speed and memory figures, measured side by side in one run.

Each module in `hil.benches` defines ``collect(quick: bool) -> Iterable[BenchRow]``; rows are printed
as a table, or with ``--json`` as one object mapping figure name -> number. Compare figures as ratios
taken in the same run: the machines are shared and noisy.
"""

from __future__ import annotations

import argparse
import json
import sys

from hil.benches import BenchRow, bench_modules, run_benches


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="print speed and memory figures (table, or --json)")
    p.add_argument("--json", action="store_true", help="print one JSON object: figure name -> number")
    p.add_argument(
        "--only",
        action="append",
        default=None,
        metavar="GROUP",
        help=f"run only this group (repeatable); groups: {', '.join(bench_modules())}",
    )
    p.add_argument("--quick", action="store_true", help="shorter measurements (noisier)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    groups = bench_modules()
    if args.only:
        unknown = sorted(set(args.only) - set(groups))
        if unknown:
            print(
                f"hil bench: unknown group(s) {', '.join(unknown)}; have: {', '.join(groups)}",
                file=sys.stderr,
            )
            return 2
        groups = [g for g in groups if g in args.only]

    def progress(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    rows: list[BenchRow] = []
    for row in run_benches(groups, args.quick, progress):
        rows.append(row)
        if not args.json:
            print(f"{row.name:<28} {row.value:>16,.3f} {row.unit:<10} {row.note}", flush=True)
    if args.json:
        print(json.dumps({r.name: r.value for r in rows}))
    return 0
