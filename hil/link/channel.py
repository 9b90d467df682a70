"""The link channel model: independent and Gilbert-Elliott burst loss, latency with jitter, in-order
delivery and UART wire time (10 bits a byte, 8N1). Seeded; all times in s.

One model for every link the harness simulates: the UWB radio of the mocap (`emulator.uwb`) and the
command link of a run (`hil.runner.wires`); the live UART pacing of `hil.link.uart` uses its byte
time. A link's own defaults are data of this model (`ChannelModel` field values), never a second model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


class Channel:
    """One direction of a link on ``model``: `drop()` says whether a message is lost, `arrival_s()`
    when one ready at a time arrives (latency, jitter, order kept). Draws only from ``rng`` (and may
    draw ahead: give it a generator of its own)."""

    def __init__(self, model: ChannelModel, rng: np.random.Generator) -> None:
        self.model = model
        self.rng = rng
        self.can_lose = model.can_lose
        self._latency_s, self._jitter_s = model.latency_s, model.jitter_s  # (the model is frozen)
        self._bad = False
        self._last_arrival_s = -math.inf
        self._jitter_block: list[float] = []
        self._jitter_next = 0

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

    def arrival_s(self, ready_s: float) -> float:
        """When a message whose last byte is out at ``ready_s`` arrives: after the latency with its
        jitter, a draw of N(0, jitter_s) (in blocks when nothing else draws: the same numbers), never
        before the one before it (s)."""
        jitter_s = self._jitter_s
        if jitter_s <= 0:
            jitter = 0.0
        elif self.can_lose:
            jitter = self.rng.normal(0.0, jitter_s)
        else:
            k, block = self._jitter_next, self._jitter_block
            if k >= len(block):
                block = self._jitter_block = self.rng.standard_normal(JITTER_BLOCK).tolist()
                k = 0
            self._jitter_next = k + 1
            jitter = 0.0 + jitter_s * block[k]  # what normal(0, jitter_s) makes of the same draw
        arrival = self._last_arrival_s = delivery_s(ready_s, self._latency_s, jitter, self._last_arrival_s)
        return arrival


class UartWire:
    """A UART at ``baud``: chunks leave one after the other, each out whole when its last bit is.

    ``write(now_s, data)`` queues a chunk; ``update(now_s)`` returns the chunks finished by then;
    `finish_s` only books the line (for a caller that queues the chunks itself).
    """

    def __init__(self, baud: int, bits_per_byte: int = BITS_PER_BYTE) -> None:
        if not baud > 0 or bits_per_byte < 1:
            raise ValueError(f"UART needs baud > 0 and bits_per_byte >= 1, got {baud}, {bits_per_byte}")
        self.baud = baud
        self.bits_per_byte = bits_per_byte
        self._busy_until_s = -math.inf
        #: (done_s, bytes) of the chunks on the line, in order
        self.queue: list[tuple[float, bytes]] = []
        self.bytes_written = 0

    def wire_time_s(self, n_bytes: int) -> float:
        """Time ``n_bytes`` take on the wire (s)."""
        return n_bytes * self.bits_per_byte / self.baud

    def finish_s(self, now_s: float, n_bytes: int) -> float:
        """Book ``n_bytes`` handed over at ``now_s`` behind what is on the line; when their last bit
        is out (s)."""
        busy = self._busy_until_s
        done = (busy if busy > now_s else now_s) + n_bytes * self.bits_per_byte / self.baud
        self._busy_until_s = done
        return done

    def write(self, now_s: float, data: bytes) -> float:
        """Queue ``data`` at ``now_s``; returns when its last byte is on the far side (s)."""
        done = self.finish_s(now_s, len(data))
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
