"""The UWB radio between the mocap station and the vehicle: air data rate, packet-size and queue
limits on the link channel model (`hil.link.channel`: latency with jitter, independent and bursty
loss), and the UART from the vehicle's UWB module into the onboard computer. Seeded; times in s."""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from hil.link.channel import BITS_PER_BYTE, Channel, ChannelModel, UartWire
from hil.link.linktrack import MAX_NODE_DATA

_heappush, _heappop = heapq.heappush, heapq.heappop

__all__ = ["Delivery", "UartWire", "UwbConfig", "UwbRadio", "UwbStats"]


@dataclass(frozen=True)
class UwbConfig(ChannelModel):
    """Radio and UART settings (s, bit/s, bytes, probabilities per packet): the link channel model
    with the radio's defaults, air time, packet and queue limits, and the UART into the computer."""

    latency_s: float = 0.020  # mean one-way latency after the air time (s); pings of ~40 ms are reported
    jitter_s: float = 0.005
    burst_exit_prob: float = 0.3
    air_rate_bps: float = 6.8e6  # air data rate (bit/s)
    air_overhead_bytes: int = 24  # preamble and radio header sent with every packet (bytes)
    max_packet_bytes: int = MAX_NODE_DATA  # larger packets are refused (counted as oversize)
    queue_packets: int = 8  # packets on the air or waiting for it; more are refused (overflow)
    late_after_s: float = 0.050  # a packet delivered later than this after sending counts as late
    uart_baud: int = 921600  # UART from the vehicle's module to the onboard computer (bit/s)
    uart_bits_per_byte: int = BITS_PER_BYTE

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (math.isfinite(self.late_after_s) and self.late_after_s >= 0):
            raise ValueError(f"uwb late_after_s must be finite and >= 0, got {self.late_after_s}")
        for name in ("air_rate_bps", "uart_baud"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"uwb {name} must be > 0, got {v}")
        for name in ("air_overhead_bytes", "max_packet_bytes", "queue_packets", "uart_bits_per_byte"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < (0 if name == "air_overhead_bytes" else 1):
                raise ValueError(f"uwb {name} must be a positive integer, got {v!r}")

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
        self.channel = Channel(config, rng)
        self._air_busy_until_s = -math.inf
        self._air_ends: list[float] = []  # when the packets queued or on the air will have left
        #: (arrival_s, sequence number, data, sent_s) of the packets on their way, a heap (its head the
        #: next arrival; read, never changed, by the mocap link)
        self.in_flight: list[tuple[float, int, bytes, float]] = []
        self._seq = 0
        self.stats = UwbStats()
        # the settings a packet reads, looked up once (the config is frozen)
        self._max_packet_bytes, self._queue_packets = config.max_packet_bytes, config.queue_packets
        self._air_overhead_bytes, self._air_rate_bps = config.air_overhead_bytes, config.air_rate_bps
        self._late_after_s = config.late_after_s
        self._arrival_s, self._can_lose = self.channel.arrival_s, self.channel.can_lose

    def send(self, now_s: float, data: bytes, n_bytes: int | None = None) -> bool:
        """Hand a packet to the radio at ``now_s``; False when it is refused (size, full queue).
        A packet the channel will lose is accepted (True) and simply never arrives. ``n_bytes``: the
        packet's size on the air when ``data`` is what the far side makes of it rather than the packet
        (the mocap link hands over the frame the vehicle's module writes for it)."""
        stats = self.stats
        stats.sent += 1
        if n_bytes is None:
            n_bytes = len(data)
        if n_bytes > self._max_packet_bytes:
            stats.oversize += 1
            return False
        ends = self._air_ends  # increasing: the packets leave the air in order
        while ends and ends[0] <= now_s:
            del ends[0]
        if len(ends) >= self._queue_packets:
            stats.overflow += 1
            return False
        busy = self._air_busy_until_s
        air_s = (n_bytes + self._air_overhead_bytes) * 8.0 / self._air_rate_bps
        busy = (now_s if now_s > busy else busy) + air_s
        self._air_busy_until_s = busy
        ends.append(busy)
        if self._can_lose:
            lost = self.channel.drop()
            if lost is not None:
                stats.lost += 1
                stats.burst_lost += lost == "burst"
                return True
        self._seq += 1
        _heappush(self.in_flight, (self._arrival_s(busy), self._seq,
                                   data if data.__class__ is bytes else bytes(data), now_s))
        return True

    def next_event_s(self) -> float:
        return self.in_flight[0][0] if self.in_flight else math.inf

    def update(self, now_s: float) -> list[Delivery]:
        """Packets that have arrived by ``now_s``."""
        return [Delivery(data, sent_s, arrival_s) for arrival_s, data, sent_s in self.arrived(now_s)]

    def update_data(self, now_s: float) -> list[tuple[float, bytes]]:
        """`update` as (arrival_s, data) pairs, without a Delivery per packet."""
        return [(arrival_s, data) for arrival_s, data, _ in self.arrived(now_s)]

    def arrived(self, now_s: float) -> list[tuple[float, bytes, float]]:
        """`update` as (arrival_s, data, sent_s) of the packets that have arrived by ``now_s``, counted
        (the mocap link's: no object per packet)."""
        q = self.in_flight
        limit = now_s + 1e-12
        if not q or q[0][0] > limit:
            return []  # nothing arrived yet (most calls)
        out = []
        stats, late_after = self.stats, self._late_after_s
        while q and q[0][0] <= limit:
            arrival_s, _, data, sent_s = _heappop(q)
            stats.delivered += 1
            if arrival_s - sent_s > late_after:
                stats.late += 1
            out.append((arrival_s, data, sent_s))
        return out
