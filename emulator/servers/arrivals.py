"""Whether an FC server's command link has anything to read now: a transport that models arrival times
(the runner's command wire: ``next_arrival_s()``, s on its ``clock``) is read only when something has
arrived, so a poll that finds nothing due returns without a read."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def _always() -> bool:
    return True


def input_due(transport: Any) -> Callable[[], bool]:
    """A function (looked up once per transport) that says whether ``transport`` may be read now:
    False only when it models arrival times, is open, and its next arrival is still to come."""
    next_arrival = getattr(transport, "next_arrival_s", None)
    clock = getattr(transport, "clock", None)
    if next_arrival is None or clock is None:
        return _always
    now_s = clock.now_s

    def due() -> bool:
        return transport.closed or next_arrival() <= now_s() + 1e-12

    return due
