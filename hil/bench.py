"""`hil bench`: speed and memory figures, measured side by side in one run.

Each module in `hil.benches` defines ``collect(quick: bool) -> Iterable[BenchRow]``; rows are printed
as a table, or with ``--json`` as one object mapping figure name -> number. Compare figures as ratios
taken in the same run: the machines are shared and noisy.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from hil.link.registry import Registry


@dataclass(frozen=True)
class BenchRow:
    """One figure: its name, value, unit and a short note on how it was measured."""

    name: str
    value: float
    unit: str
    note: str = ""


#: the bench groups: one module of `hil.benches` each, measured by its ``collect``
BENCHES = Registry("bench group", package="hil.benches", attr="collect")


def bench_modules() -> list[str]:
    """Names of the bench groups (modules of hil.benches), in a stable order."""
    return BENCHES.names()


def run_benches(groups: Iterable[str], quick: bool, progress: Callable[[str], None]) -> Iterator[BenchRow]:
    """Run the named groups, yielding rows as they are measured."""
    for group in groups:
        collect = BENCHES.load(group)
        progress(f"bench {group} ...")
        start = time.perf_counter()
        yield from collect(quick)  # type: ignore[operator]
        progress(f"bench {group} done in {time.perf_counter() - start:.1f} s")


def time_per_call(fn: Callable[[], object], min_time_s: float = 0.5, max_calls: int = 10_000_000) -> float:
    """Seconds per call of ``fn``, after one warm-up call, over at least ``min_time_s``."""
    fn()
    calls, start = 0, time.perf_counter()
    batch = 1
    while True:
        for _ in range(batch):
            fn()
        calls += batch
        elapsed = time.perf_counter() - start
        if elapsed >= min_time_s or calls >= max_calls:
            return elapsed / calls
        batch = min(batch * 2, max_calls - calls) or 1


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
