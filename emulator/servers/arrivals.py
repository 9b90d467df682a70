"""When an FC server's command link next has something to read: a transport that models arrival times
(the runner's command wire) keeps that time in its ``next_input_s``, so a poll before it compares one
float and reads nothing; any other transport is read at every poll."""

from __future__ import annotations

import math
from typing import Any


class _Untimed:
    """A transport without arrival times as a poll sees it: something may have come at any time."""

    next_input_s = -math.inf


_UNTIMED = _Untimed()


def arrivals(transport: Any) -> Any:
    """What a poll reads ``next_input_s`` (s; looked up once per transport) from: ``transport`` itself
    when it models arrival times (inf while nothing is on the way, -inf once it is closed: its read then
    says so), else an object whose time has always come."""
    return transport if hasattr(transport, "next_input_s") else _UNTIMED
