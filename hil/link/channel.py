"""The link channel model: independent and Gilbert-Elliott burst loss, latency with jitter, in-order
delivery and UART wire time (10 bits a byte, 8N1). Seeded; all times in s.

One model for every link the harness simulates: the UWB radio of the mocap (`emulator.uwb`) and the
command link of a run (`hil.runner.wires`); the live UART pacing of `hil.link.uart` uses its byte
time. A link's own defaults are data of this model (`ChannelModel` field values), never a second model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

BITS_PER_BYTE = 10  # start bit, 8 data bits, stop bit
JITTER_BLOCK = 64  # jitter draws made at once by a channel that cannot lose (same numbers, in order)


@dataclass(frozen=True)
class ChannelModel:
    """Per-message behaviour of one link direction (s, probabilities per message)."""

    latency_s: float = 0.0  # mean one-way latency added to each message (s)
    jitter_s: float = 0.0  # std of normal jitter on the latency (s), truncated so latency stays >= 0
    loss_prob: float = 0.0  # independent loss per message
    burst_enter_prob: float = 0.0  # Gilbert-Elliott: chance per message to go from good to bad
    burst_exit_prob: float = 1.0  # Gilbert-Elliott: chance per message to go from bad back to good
    burst_loss_prob: float = 1.0  # loss per message while in the bad state

    def __post_init__(self) -> None:
        for name in ("latency_s", "jitter_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        for name in ("loss_prob", "burst_enter_prob", "burst_exit_prob", "burst_loss_prob"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {v}")
        if self.burst_enter_prob > 0 and self.burst_exit_prob <= 0:
            raise ValueError("burst_exit_prob must be > 0 when bursts can start (or loss never ends)")

    @property
    def can_lose(self) -> bool:
        return self.loss_prob > 0 or self.burst_enter_prob > 0

    @property
    def mean_loss(self) -> float:
        """Long-run fraction of messages lost (independent and burst losses combined)."""
        p_bad = 0.0
        if self.burst_enter_prob > 0:
            p_bad = self.burst_enter_prob / (self.burst_enter_prob + self.burst_exit_prob)
        return 1.0 - (1.0 - self.loss_prob) * (1.0 - p_bad * self.burst_loss_prob)


def next_burst_state(bad: bool, u: float, enter_prob: float, exit_prob: float) -> bool:
    """Gilbert-Elliott: whether a channel is in the bad state for the next message, from its state
    ``bad`` and a uniform draw ``u`` in [0, 1). Plain arithmetic: `Channel` runs it, and the RL
    environment compiled over its rows (`hil.rl.link_observe`)."""
    return (u >= exit_prob) if bad else (u < enter_prob)


def delivery_s(ready_s: float, latency_s: float, jitter_s: float, last_arrival_s: float) -> float:
    """When a message whose last byte is out at ``ready_s`` arrives (s): after the latency with this
    message's ``jitter_s`` (the sum not below 0), never before the one before (``last_arrival_s``)."""
    late_s = latency_s + jitter_s
    arrival_s = ready_s + (late_s if late_s > 0.0 else 0.0)
    return last_arrival_s if last_arrival_s > arrival_s else arrival_s


#: a channel's state, the numbers `Channel` keeps (a list, or a float64 array a compiled caller shares):
#: its latency and jitter (s), the last arrival (s), the next of its jitter draws drawn ahead, the draws
CH_LATENCY, CH_JITTER, CH_LAST_ARRIVAL, CH_NEXT, CH_BLOCK = 0, 1, 2, 3, 4
CHANNEL_STATE_LEN = CH_BLOCK + JITTER_BLOCK


def block_arrival_s(st: list[float] | np.ndarray, ready_s: float) -> float:
    """`Channel.arrival_s` of a channel that cannot lose, on its state ``st`` (``CH_*``): the jitter the
    next of the standard normal draws drawn ahead (none when the jitter is 0), the arrival (s) kept as the
    last; NaN, with nothing changed, when the draws are spent (draw the next block into ``st`` first).
    Plain arithmetic: `Channel` runs it, the mocap link compiled in its radio's step."""
    jitter_s = st[CH_JITTER]
    jitter = 0.0
    if jitter_s > 0:
        k = int(st[CH_NEXT])
        if k >= JITTER_BLOCK:
            return math.nan
        st[CH_NEXT] = k + 1
        jitter = 0.0 + jitter_s * st[CH_BLOCK + k]  # what normal(0, jitter_s) makes of the same draw
    arrival = delivery_s(ready_s, st[CH_LATENCY], jitter, st[CH_LAST_ARRIVAL])
    st[CH_LAST_ARRIVAL] = arrival
    return arrival


class Channel:
    """One direction of a link on ``model``: `drop()` says whether a message is lost, `arrival_s()`
    when one ready at a time arrives (latency, jitter, order kept). Draws only from ``rng`` (and may
    draw ahead: give it a generator of its own). ``state``: where it keeps its numbers (``CH_*``; a
    float64 array of `CHANNEL_STATE_LEN` that a compiled caller shares), else a list of its own."""

    def __init__(self, model: ChannelModel, rng: np.random.Generator,
                 state: np.ndarray | None = None) -> None:
        self.model = model
        self.rng = rng
        self.can_lose = model.can_lose
        self._latency_s, self._jitter_s = model.latency_s, model.jitter_s  # (the model is frozen)
        self._bad = False
        st = [0.0] * CHANNEL_STATE_LEN if state is None else state
        st[CH_LATENCY], st[CH_JITTER], st[CH_LAST_ARRIVAL] = model.latency_s, model.jitter_s, -math.inf
        st[CH_NEXT] = JITTER_BLOCK  # (none drawn yet)
        self.state = st

    def drop(self) -> str | None:
        """Whether the next message is lost: "burst" (in the bad state), "loss" (independent) or None.
        Draws: the state change (bursts on), the burst loss (bad state), then the independent loss."""
        m, rng = self.model, self.rng
        if m.burst_enter_prob > 0:
            self._bad = next_burst_state(self._bad, rng.random(), m.burst_enter_prob, m.burst_exit_prob)
        if self._bad and rng.random() < m.burst_loss_prob:
            return "burst"
        if m.loss_prob > 0 and rng.random() < m.loss_prob:
            return "loss"
        return None

    def draw_block(self) -> None:
        """The next `JITTER_BLOCK` standard normal draws into the state (`block_arrival_s` spent them)."""
        st = self.state
        st[CH_BLOCK:] = self.rng.standard_normal(JITTER_BLOCK).tolist()
        st[CH_NEXT] = 0

    def arrival_s(self, ready_s: float) -> float:
        """When a message whose last byte is out at ``ready_s`` arrives: after the latency with its
        jitter, a draw of N(0, jitter_s) (in blocks when nothing else draws: the same numbers), never
        before the one before it (s)."""
        st = self.state
        if self.can_lose and self._jitter_s > 0:
            arrival = delivery_s(ready_s, self._latency_s, self.rng.normal(0.0, self._jitter_s),
                                 st[CH_LAST_ARRIVAL])
            st[CH_LAST_ARRIVAL] = arrival
            return float(arrival)
        arrival = block_arrival_s(st, ready_s)
        if arrival != arrival:  # (NaN: the draws are spent)
            self.draw_block()
            arrival = block_arrival_s(st, ready_s)
        return float(arrival)


#: a UART's state, the numbers `UartWire` keeps: bits a byte, the baud (bit/s), when the line is free (s)
UART_BITS, UART_BAUD, UART_BUSY_UNTIL = 0, 1, 2
UART_STATE_LEN = 3


def wire_finish_s(st: list[float] | np.ndarray, now_s: float, n_bytes: int) -> float:
    """`UartWire.finish_s` on its state ``st`` (``UART_*``): ``n_bytes`` handed over at ``now_s`` booked
    behind what is on the line; when their last bit is out (s). Plain arithmetic: `UartWire` runs it, the
    mocap link compiled in its radio's step."""
    busy = st[UART_BUSY_UNTIL]
    done = (busy if busy > now_s else now_s) + n_bytes * st[UART_BITS] / st[UART_BAUD]
    st[UART_BUSY_UNTIL] = done
    return done


class UartWire:
    """A UART at ``baud``: chunks leave one after the other, each out whole when its last bit is.

    ``write(now_s, data)`` queues a chunk; ``update(now_s)`` returns the chunks finished by then;
    `finish_s` only books the line (for a caller that queues the chunks itself).
    """

    def __init__(self, baud: int, bits_per_byte: int = BITS_PER_BYTE,
                 state: np.ndarray | None = None) -> None:
        """``state``: where the wire keeps its numbers (``UART_*``; a float64 array of `UART_STATE_LEN` that
        a compiled caller shares), else a list of its own."""
        if not baud > 0 or bits_per_byte < 1:
            raise ValueError(f"UART needs baud > 0 and bits_per_byte >= 1, got {baud}, {bits_per_byte}")
        self.baud = baud
        self.bits_per_byte = bits_per_byte
        st = [0.0] * UART_STATE_LEN if state is None else state
        st[UART_BITS], st[UART_BAUD], st[UART_BUSY_UNTIL] = bits_per_byte, baud, -math.inf
        self.state = st
        #: ``finish_s(now_s, n_bytes)``: book ``n_bytes`` handed over at ``now_s`` behind what is on the
        #: line; when their last bit is out (s). `wire_finish_s` bound to the state (no call of its own)
        self.finish_s: Callable[[float, int], float] = partial(wire_finish_s, st)
        #: (done_s, bytes) of the chunks on the line, in order
        self.queue: list[tuple[float, bytes]] = []
        self.bytes_written = 0

    def wire_time_s(self, n_bytes: int) -> float:
        """Time ``n_bytes`` take on the wire (s)."""
        return n_bytes * self.bits_per_byte / self.baud

    def write(self, now_s: float, data: bytes) -> float:
        """Queue ``data`` at ``now_s``; returns when its last byte is on the far side (s)."""
        done = wire_finish_s(self.state, now_s, len(data))
        self.queue.append((done, data if data.__class__ is bytes else bytes(data)))
        return done

    def next_event_s(self) -> float:
        return self.queue[0][0] if self.queue else math.inf

    def update(self, now_s: float) -> list[tuple[float, bytes]]:
        """(done_s, bytes) of the chunks whose wire time has passed by ``now_s``."""
        q = self.queue  # (the same list for the wire's life: a reader may look at its head)
        limit = now_s + 1e-12
        if not q or q[0][0] > limit:
            return []  # nothing done yet (most calls)
        n = 1
        while n < len(q) and q[n][0] <= limit:
            n += 1
        out = q[:n]
        del q[:n]
        self.bytes_written += len(out[0][1]) if n == 1 else sum(len(d) for _, d in out)
        return out
