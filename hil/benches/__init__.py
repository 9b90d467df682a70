"""Bench groups for `hil bench`: one module per area, each with ``collect(quick: bool) ->
Iterable[BenchRow]``, and what they share (the row, the timer, running groups by name)."""

from __future__ import annotations

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


#: the bench groups: one module of this package each, measured by its ``collect``
BENCHES = Registry("bench group", package="hil.benches", attr="collect")


def bench_modules() -> list[str]:
    """Names of the bench groups (modules of this package), in a stable order."""
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


