"""Whether an FC server's command link has anything to read now: a transport that models arrival times
(the runner's command wire) says so itself with ``input_due()``, so a poll that finds nothing due returns
without a read; any other transport is read at every poll."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def _always() -> bool:
    return True


def input_due(transport: Any) -> Callable[[], bool]:
    """A function (looked up once per transport) that says whether ``transport`` may be read now: its
    own ``input_due`` when it models arrival times (False only while it is open and its next arrival is
    still to come), else one that always says yes."""
    return getattr(transport, "input_due", None) or _always
