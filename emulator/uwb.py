"""The UWB radio between the mocap station and the vehicle, and the UART from the vehicle's UWB module
into the onboard computer: latency with jitter, independent and bursty (Gilbert-Elliott) loss, air data
rate, packet-size and queue limits, and wire time at a baud. Seeded; all times in seconds."""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from hil.link.linktrack import MAX_NODE_DATA


@dataclass(frozen=True)
class UwbConfig:
    """Radio and UART settings (s, bit/s, bytes, probabilities per packet)."""

    latency_s: float = 0.020  # mean one-way latency after the air time (s); pings of ~40 ms are reported
    jitter_s: float = 0.005  # std of normal jitter on the latency (s), truncated so latency stays >= 0
    loss_prob: float = 0.0  # independent loss per packet
    burst_enter_prob: float = 0.0  # Gilbert-Elliott: chance per packet to go from good to bad
    burst_exit_prob: float = 0.3  # Gilbert-Elliott: chance per packet to go from bad back to good
    burst_loss_prob: float = 1.0  # loss per packet while in the bad state
    air_rate_bps: float = 6.8e6  # air data rate (bit/s)
    air_overhead_bytes: int = 24  # preamble and radio header sent with every packet (bytes)
    max_packet_bytes: int = MAX_NODE_DATA  # larger packets are refused (counted as oversize)
    queue_packets: int = 8  # packets on the air or waiting for it; more are refused (overflow)
    late_after_s: float = 0.050  # a packet delivered later than this after sending counts as late
    uart_baud: int = 921600  # UART from the vehicle's module to the onboard computer (bit/s)
    uart_bits_per_byte: int = 10  # 8N1: start + 8 data + stop

    def __post_init__(self) -> None:
        for name in ("latency_s", "jitter_s", "late_after_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"uwb {name} must be finite and >= 0, got {v}")
        for name in ("loss_prob", "burst_enter_prob", "burst_exit_prob", "burst_loss_prob"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"uwb {name} must be a probability in [0, 1], got {v}")
        if self.burst_enter_prob > 0 and self.burst_exit_prob <= 0:
            raise ValueError("uwb burst_exit_prob must be > 0 when bursts can start (or loss never ends)")
        for name in ("air_rate_bps", "uart_baud"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"uwb {name} must be > 0, got {v}")
        for name in ("air_overhead_bytes", "max_packet_bytes", "queue_packets", "uart_bits_per_byte"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < (0 if name == "air_overhead_bytes" else 1):
                raise ValueError(f"uwb {name} must be a positive integer, got {v!r}")

    @property
    def mean_loss(self) -> float:
        """Long-run fraction of packets lost (independent and burst losses combined)."""
        p_bad = 0.0
        if self.burst_enter_prob > 0:
            p_bad = self.burst_enter_prob / (self.burst_enter_prob + self.burst_exit_prob)
        return 1.0 - (1.0 - self.loss_prob) * (1.0 - p_bad * self.burst_loss_prob)

    def air_time_s(self, n_bytes: int) -> float:
        """Time one packet of ``n_bytes`` occupies the air (s)."""
        return (n_bytes + self.air_overhead_bytes) * 8.0 / self.air_rate_bps

    def uart_time_s(self, n_bytes: int) -> float:
        """Wire time of ``n_bytes`` on the UART (s)."""
        return n_bytes * self.uart_bits_per_byte / self.uart_baud


@dataclass
class UwbStats:
    """Packet counters. sent = delivered + lost + oversize + overflow + in flight."""

    sent: int = 0
    delivered: int = 0
    lost: int = 0  # dropped by the channel (independent or burst)
    late: int = 0  # delivered, but later than late_after_s
    oversize: int = 0  # refused: larger than max_packet_bytes
    overflow: int = 0  # refused: the transmit queue was full
    burst_lost: int = 0  # of ``lost``, those lost in the bad state


@dataclass(frozen=True)
class Delivery:
    """A packet out of the radio: its bytes, when it was sent and when it arrived (s)."""

    data: bytes
    sent_s: float
    arrival_s: float


class UwbRadio:
    """One-way radio: ``send(now_s, data)`` then ``update(now_s)`` returns what has arrived by then,
    in sending order. ``next_event_s()`` is the next arrival (inf when nothing is in flight).
    The radio may draw ahead from ``rng``: give it a generator of its own (``rng.spawn``)."""

    def __init__(self, config: UwbConfig, rng: np.random.Generator) -> None:
        self.config = config
        self._rng = rng
        self._air_busy_until_s = -math.inf
        self._air_ends: list[float] = []  # when the packets queued or on the air will have left
        self._last_arrival_s = -math.inf
        #: (arrival_s, sequence number, data, sent_s) of the packets on their way, a heap
        self._in_flight: list[tuple[float, int, bytes, float]] = []
        self._seq = 0
        self._bad = False
        self.stats = UwbStats()
        # with no loss the radio's generator draws only the jitter: drawn ahead in blocks, the same
        # numbers in the same order (one call per block instead of one per packet)
        self._can_lose = config.loss_prob > 0 or config.burst_enter_prob > 0
        self._jitter_block: list[float] = []
        self._jitter_next = 0

    def send(self, now_s: float, data: bytes) -> bool:
        """Hand a packet to the radio at ``now_s``; False when it is refused (size, full queue).
        A packet the channel will lose is accepted (True) and simply never arrives."""
        cfg, stats = self.config, self.stats
        stats.sent += 1
        n_bytes = len(data)
        if n_bytes > cfg.max_packet_bytes:
            stats.oversize += 1
            return False
        ends = self._air_ends  # increasing: the packets leave the air in order
        while ends and ends[0] <= now_s:
            del ends[0]
        if len(ends) >= cfg.queue_packets:
            stats.overflow += 1
            return False
        busy = self._air_busy_until_s
        busy = (now_s if now_s > busy else busy) + (n_bytes + cfg.air_overhead_bytes) * 8.0 / cfg.air_rate_bps
        self._air_busy_until_s = busy
        ends.append(busy)
        if self._can_lose and self._lost():
            return True
        latency = cfg.latency_s
        if cfg.jitter_s > 0:
            latency = max(0.0, latency + self._jitter(cfg.jitter_s))
        arrival = busy + latency
        if arrival < self._last_arrival_s:
            arrival = self._last_arrival_s  # the radio keeps order
        self._last_arrival_s = arrival
        self._seq += 1
        heapq.heappush(
            self._in_flight, (arrival, self._seq, data if data.__class__ is bytes else bytes(data), now_s)
        )
        return True

    def _jitter(self, jitter_s: float) -> float:
        """One jitter draw, N(0, jitter_s) (s)."""
        if self._can_lose:
            return self._rng.normal(0.0, jitter_s)
        k = self._jitter_next
        block = self._jitter_block
        if k >= len(block):
            block = self._jitter_block = self._rng.standard_normal(64).tolist()
            k = 0
        self._jitter_next = k + 1
        return 0.0 + jitter_s * block[k]  # what normal(0, jitter_s) makes of the same draw

    def _lost(self) -> bool:
        cfg, rng = self.config, self._rng
        if cfg.burst_enter_prob > 0:
            if self._bad:
                self._bad = rng.random() >= cfg.burst_exit_prob
            else:
                self._bad = rng.random() < cfg.burst_enter_prob
        if self._bad and rng.random() < cfg.burst_loss_prob:
            self.stats.lost += 1
            self.stats.burst_lost += 1
            return True
        if cfg.loss_prob > 0 and rng.random() < cfg.loss_prob:
            self.stats.lost += 1
            return True
        return False

    def next_event_s(self) -> float:
        return self._in_flight[0][0] if self._in_flight else math.inf

    def update(self, now_s: float) -> list[Delivery]:
        """Packets that have arrived by ``now_s``."""
        return [Delivery(data, sent_s, arrival_s) for arrival_s, data, sent_s in self._arrived(now_s)]

    def update_data(self, now_s: float) -> list[tuple[float, bytes]]:
        """`update` as (arrival_s, data) pairs, without a Delivery per packet (the mocap link's)."""
        q = self._in_flight
        if not q or q[0][0] > now_s + 1e-12:
            return []  # nothing arrived yet (most calls)
        return [(arrival_s, data) for arrival_s, data, _ in self._arrived(now_s)]

    def _arrived(self, now_s: float) -> list[tuple[float, bytes, float]]:
        """(arrival_s, data, sent_s) of the packets that have arrived by ``now_s``, counted."""
        q = self._in_flight
        if not q or q[0][0] > now_s + 1e-12:
            return []  # nothing arrived yet (most calls)
        out = []
        stats, late_after = self.stats, self.config.late_after_s
        pop = heapq.heappop
        while q and q[0][0] <= now_s + 1e-12:
            arrival_s, _, data, sent_s = pop(q)
            stats.delivered += 1
            if arrival_s - sent_s > late_after:
                stats.late += 1
            out.append((arrival_s, data, sent_s))
        return out


class UartWire:
    """A UART at ``baud``: bytes queued at a time come out whole when their last bit has been sent.

    ``write(now_s, data)`` queues a chunk; ``update(now_s)`` returns the chunks finished by then.
    """

    def __init__(self, baud: int, bits_per_byte: int = 10) -> None:
        if not baud > 0 or bits_per_byte < 1:
            raise ValueError(f"UART needs baud > 0 and bits_per_byte >= 1, got {baud}, {bits_per_byte}")
        self.baud = baud
        self.bits_per_byte = bits_per_byte
        self._busy_until_s = -math.inf
        self._queue: list[tuple[float, bytes]] = []
        self.bytes_written = 0

    def wire_time_s(self, n_bytes: int) -> float:
        return n_bytes * self.bits_per_byte / self.baud

    def write(self, now_s: float, data: bytes) -> float:
        """Queue ``data`` at ``now_s``; returns when its last byte is on the far side (s)."""
        busy = self._busy_until_s
        # max(now_s, busy) + wire_time_s(len(data)), as plain arithmetic
        done = (busy if busy > now_s else now_s) + len(data) * self.bits_per_byte / self.baud
        self._busy_until_s = done
        self._queue.append((done, data if data.__class__ is bytes else bytes(data)))
        return done

    def next_event_s(self) -> float:
        return self._queue[0][0] if self._queue else math.inf

    def update(self, now_s: float) -> list[tuple[float, bytes]]:
        """(done_s, bytes) of the chunks whose wire time has passed by ``now_s``."""
        q = self._queue
        limit = now_s + 1e-12
        if not q or q[0][0] > limit:
            return []  # nothing done yet (most calls)
        if len(q) == 1:  # one chunk, done: the queue empties
            self._queue = []
            self.bytes_written += len(q[0][1])
            return q
        n = 1
        while n < len(q) and q[n][0] <= limit:
            n += 1
        out, self._queue = q[:n], q[n:]
        self.bytes_written += sum(len(d) for _, d in out)
        return out
