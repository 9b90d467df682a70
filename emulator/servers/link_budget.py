"""The data-rate budget of the FC's command link, as PX4 keeps one per MAVLink instance: the telemetry
streams are scaled to fit a share of what the line carries (a configured rate in bytes/s, MAVLink's
``MAV_0_RATE`` or `hil fc --link-budget-bytes-s`, or with 0 half the line: baud / 20 at 10 bits a byte),
the rest left for answers (parameters, command ACKs, status text). It knows no protocol: a stream is any
key, its cost the bytes one of its frames puts on the line (``frame_bytes``, the protocol's to say), so
MAVLink's messages and the OPEN protocol's broadcast items and subscription packages share it.

On a paced line (`hil.link.uart.UartTransport`) the budget also watches the line's queue: a stream frame
that would wait behind more than `STREAM_QUEUE_S` of queued bytes is not sent (counted in
``frames_dropped``), so answers never wait long; answers and heartbeats always go while the transmit
buffer has room for the whole frame (else they are dropped whole, counted, never cut).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Hashable
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

from hil.link.channel import BITS_PER_BYTE

STREAM_QUEUE_S = 0.05  # a stream frame waits behind at most this much of the line's queue (s)
LINE_SHARE_DEFAULT = 0.5  # a configured rate of 0: the streams get this share of the line (PX4: baud / 20)
MIN_RATE_INTERVAL_S = 1.0  # no stream is scaled below 1 Hz (one asked slower keeps its rate)
CAPS_KEPT = 20  # the summary lists at most this many capped requests

K = TypeVar("K", bound=Hashable)


@dataclass
class BudgetStats:
    """What the budget did (counts, bytes)."""

    bytes_dropped: int = 0  # bytes of the frames not sent for lack of line
    frames_dropped: int = 0  # stream frames not sent: the line's queue was too deep
    answers_dropped: int = 0  # answers and heartbeats dropped whole: the transmit buffer was full
    queue_bytes_max: int = 0  # the deepest line queue seen when a frame was queued
    answer_wait_max_s: float = 0.0  # the longest an answer waited behind the line's queue (s)
    #: rate requests granted less than asked (SET_MESSAGE_INTERVAL, N3_RATE_*; OPEN: broadcast
    #: frequencies, subscription packages)
    rates_capped: int = 0
    caps: list[dict[str, Any]] = field(default_factory=list)  # the first `CAPS_KEPT` of them

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class LinkBudget:
    """The budget of one link: which stream rates fit, and whether a frame may be queued now."""

    def __init__(self, baud: int | None, uart: Any, frame_bytes: Callable[[Any], float],
                 fixed: Collection[Any] = (), rate_bytes_s: float = 0.0) -> None:
        """``baud``: the line's (bit/s; None: not a serial line); ``uart``: its `UartModel` when the
        link is paced, else None; ``frame_bytes``: a stream key -> the bytes one of its frames costs on
        the line; ``fixed``: streams kept at their rate up to once every `MIN_RATE_INTERVAL_S` (a
        ground station counts a link lost without its heartbeat; faster, they are scaled with the
        others); ``rate_bytes_s``: the configured budget (0: from the baud)."""
        self.baud, self.uart, self.frame_bytes, self.fixed = baud, uart, frame_bytes, frozenset(fixed)
        self.rate_param_bytes_s = float(rate_bytes_s)  # MAV_0_RATE's value (0: from the baud)
        self.stats = BudgetStats()

    @property
    def line_bytes_s(self) -> float | None:
        """What the line carries (bytes/s), None if not a serial line."""
        return None if self.baud is None else self.baud / BITS_PER_BYTE

    @property
    def stream_bytes_s(self) -> float | None:
        """What the streams may use (bytes/s); None: no budget (not a serial line, MAV_0_RATE 0)."""
        if self.rate_param_bytes_s > 0:
            return self.rate_param_bytes_s
        line = self.line_bytes_s
        return None if line is None else LINE_SHARE_DEFAULT * line

    def grant(self, requested_s: dict[K, float]) -> dict[K, float]:
        """The intervals (s) the streams get: ``requested_s`` (stream key -> interval) scaled alike until
        they fit the budget, none slower than once every `MIN_RATE_INTERVAL_S` (or than asked, if
        slower): the ``fixed`` streams at that rate or slower are kept as asked."""
        budget = self.stream_bytes_s
        if budget is None:
            return dict(requested_s)
        granted = dict(requested_s)
        free = [i for i, s in requested_s.items() if not (i in self.fixed and s >= MIN_RATE_INTERVAL_S)]
        while free:  # (each round pins at least one stream at its slowest, or ends)
            used = sum(self.frame_bytes(i) / s for i, s in granted.items() if i not in free)
            demand = sum(self.frame_bytes(i) / requested_s[i] for i in free)
            scale = min(1.0, max(budget - used, 0.01 * budget) / demand)
            slowest = {i: max(requested_s[i], MIN_RATE_INTERVAL_S) for i in free}
            pinned = [i for i in free if requested_s[i] / scale > slowest[i]]
            for i in free:
                granted[i] = slowest[i] if i in pinned else requested_s[i] / scale
            if not pinned:
                break
            free = [i for i in free if i not in pinned]
        return granted

    def capped(self, name: str, requested_hz: float, granted_hz: float) -> str:
        """Record a request for stream ``name`` granted less than asked; the sentence that says so
        (a MAVLink message's name keeps it within a STATUSTEXT's 50 characters)."""
        self.stats.rates_capped += 1
        if len(self.stats.caps) < CAPS_KEPT:
            self.stats.caps.append({"message": name, "requested_hz": round(requested_hz, 3),
                                    "granted_hz": round(granted_hz, 3),
                                    "stream_budget_bytes_s": round(self.stream_bytes_s or 0.0, 1)})
        return f"{name} {requested_hz:.4g}Hz capped {granted_hz:.3g}Hz: line"

    def has_room(self, n_bytes: int) -> bool:
        """Whether a frame of ``n_bytes`` sent at a stream's pace may go now (nothing counted)."""
        uart = self.uart
        if uart is None:
            return True
        queued = uart.backlog_bytes()
        return queued * BITS_PER_BYTE / uart.baud <= STREAM_QUEUE_S and \
            uart.tx_buffer_bytes - queued >= n_bytes

    def admit(self, n_bytes: int, stream: bool) -> bool:
        """Whether a frame of ``n_bytes`` may be written now (a periodic ``stream`` frame, or an answer or
        heartbeat); a frame refused is counted in ``bytes_offered`` here (one sent, by the transport)."""
        uart = self.uart
        if uart is None:
            return True
        st = self.stats
        queued = uart.backlog_bytes()
        wait_s = queued * BITS_PER_BYTE / uart.baud
        if stream and wait_s > STREAM_QUEUE_S:
            st.frames_dropped += 1
        elif uart.tx_buffer_bytes - queued < n_bytes:
            if stream:
                st.frames_dropped += 1
            else:
                st.answers_dropped += 1
        else:
            if queued > st.queue_bytes_max:
                st.queue_bytes_max = queued
            if not stream and wait_s > st.answer_wait_max_s:
                st.answer_wait_max_s = wait_s
            return True
        st.bytes_dropped += n_bytes
        return False

    def summary(self, transport: Any, elapsed_s: float) -> dict[str, Any]:
        """The budget's figures for a summary: rates (bytes/s) over ``elapsed_s`` of the paced
        ``transport`` (a `UartTransport`: what it took, and what left on the line), and the counters."""
        out: dict[str, Any] = {"baud": self.baud, "line_bytes_s": self.line_bytes_s,
                               "stream_budget_bytes_s": self.stream_bytes_s}
        stats = self.stats.as_dict()
        if self.uart is not None and elapsed_s > 0:
            taken = transport.stats.bytes_sent + transport.stats.bytes_dropped
            out["bytes_offered_per_s"] = round((taken + self.stats.bytes_dropped) / elapsed_s, 1)
            out["bytes_written_per_s"] = round(self.uart.bytes_released / elapsed_s, 1)
            out["queue_bytes_now"] = self.uart.backlog_bytes()
        return {**out, **stats}
