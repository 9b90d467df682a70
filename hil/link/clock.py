"""Clocks: simulated time for lockstep runs, wall time for real-time runs. Anything that waits or
stamps takes a Clock, so the same code runs faster than real time or against real hardware."""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    def now_s(self) -> float:
        """Current time (s)."""


class WallClock:
    """Monotonic wall time, zero at creation (s)."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now_s(self) -> float:
        return time.monotonic() - self._t0


class SimClock:
    """Simulated time, advanced only by its owner (s)."""

    def __init__(self, t0_s: float = 0.0) -> None:
        self._t = t0_s

    def now_s(self) -> float:
        return self._t

    def advance_to(self, t_s: float) -> None:
        if t_s < self._t:
            raise ValueError(f"simulated time cannot go back ({t_s} < {self._t})")
        self._t = t_s


#: lateness histogram: 0.1 ms bins up to 2 s (constant memory for a loop that runs for hours)
_LATE_BIN_S = 1e-4
_LATE_BINS = 20_000


class PacingStats:
    """How a loop paced by the wall clock kept up: each iteration's lateness (s), the time its wake-up
    came after the loop's period, and the physics steps run to catch up after a late wake-up.

    Call `wake(now_s)` once per iteration with the wall-clock time (s); `as_dict` gives the figures in
    ms: median, 99th percentile and worst lateness (with when the worst was), iterations, and how many
    iterations were later than ``late_s``. Nothing is ever skipped: a late loop steps the physics up to
    now, the steps beyond one period counted in ``caught_up_steps``.
    """

    def __init__(self, period_s: float, step_s: float = 1e-3, late_s: float = 5e-3) -> None:
        self.period_s, self.step_s, self.late_s = period_s, step_s, late_s
        self._bins = [0] * _LATE_BINS
        self._last_s: float | None = None
        self.iterations = 0
        self.late_iterations = 0
        self.caught_up_steps = 0
        self.worst_s = 0.0
        self.worst_at_s: float | None = None

    def wake(self, now_s: float) -> None:
        last, self._last_s = self._last_s, now_s
        if last is None:
            return
        late = now_s - last - self.period_s
        if late < 0.0:
            late = 0.0
        self.iterations += 1
        self._bins[min(int(late / _LATE_BIN_S), _LATE_BINS - 1)] += 1
        if late > self.late_s:
            self.late_iterations += 1
            self.caught_up_steps += int(late / self.step_s)
        if late > self.worst_s:
            self.worst_s, self.worst_at_s = late, now_s

    def quantile_s(self, q: float) -> float:
        """The ``q`` quantile (0..1) of the iterations' lateness (s), to the bin (0.1 ms)."""
        if self.iterations == 0:
            return 0.0
        rank, seen = q * self.iterations, 0
        for i, n in enumerate(self._bins):
            seen += n
            if n and seen >= rank:
                return (i + 0.5) * _LATE_BIN_S
        return self.worst_s

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            "iterations": self.iterations,
            "late_median_ms": round(self.quantile_s(0.5) * 1e3, 2),
            "late_p99_ms": round(self.quantile_s(0.99) * 1e3, 2),
            "late_worst_ms": round(self.worst_s * 1e3, 2),
            "late_worst_at_s": None if self.worst_at_s is None else round(self.worst_at_s, 3),
            f"late_over_{self.late_s * 1e3:g}ms": self.late_iterations,
            "caught_up_steps": self.caught_up_steps,
            "skipped_steps": 0,
        }


class GapStats:
    """The gaps between the times (s) a counter moved (setpoints applied, mocap frames written): its
    rate and the longest silence, as the wire saw them."""

    def __init__(self) -> None:
        self.count = 0
        self.first_count = 0  # the count when it first moved (what came before is no rate)
        self.first_s: float | None = None
        self.last_s: float | None = None
        self.max_gap_s = 0.0
        self.max_gap_end_s: float | None = None

    def update(self, now_s: float, count: int) -> None:
        """The counter reads ``count`` at ``now_s`` (s)."""
        if count == self.count:
            return
        if self.last_s is not None and now_s - self.last_s > self.max_gap_s:
            self.max_gap_s, self.max_gap_end_s = now_s - self.last_s, now_s
        if self.first_s is None:
            self.first_s, self.first_count = now_s, count
        self.count, self.last_s = count, now_s

    def as_dict(self) -> dict[str, float | int | None]:
        span = 0.0 if self.first_s is None or self.last_s is None else self.last_s - self.first_s
        return {
            "count": self.count,
            # (the moves after the first over the time they took: a first reading that finds several
            # already counted, after a late start, does not raise the rate)
            "rate_hz": round((self.count - self.first_count) / span, 2) if span > 0 else None,
            "max_gap_ms": round(self.max_gap_s * 1e3, 2),
            "max_gap_end_s": None if self.max_gap_end_s is None else round(self.max_gap_end_s, 3),
        }
