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
