"""The UWB radio between the mocap station and the vehicle: air data rate, packet-size and queue
limits on the link channel model (`hil.link.channel`: latency with jitter, independent and bursty
loss), and the UART from the vehicle's UWB module into the onboard computer. Seeded; times in s."""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from hil.link.channel import (
    BITS_PER_BYTE,
    CHANNEL_STATE_LEN,
    UART_STATE_LEN,
    Channel,
    ChannelModel,
    UartWire,
)
from hil.link.linktrack import MAX_NODE_DATA

_heappush, _heappop = heapq.heappush, heapq.heappop

#: a radio's state, the numbers `UwbRadio` keeps for the air (a list, or a float64 array a compiled caller
#: shares): its packet and queue limits (bytes, packets), overhead (bytes) and rate (bit/s), when the air is
#: free (s), then how many packets are queued or on the air and, from ``RADIO_ENDS``, when each leaves it
#: (s, increasing)
RADIO_MAX_PACKET, RADIO_QUEUE, RADIO_OVERHEAD, RADIO_RATE = 0, 1, 2, 3
RADIO_BUSY_UNTIL, RADIO_N_ENDS, RADIO_ENDS = 4, 5, 6
#: what `book_air` says of a packet: booked, or refused (larger than the limit, the queue full)
SENT, OVERSIZE, OVERFLOW = 0, 1, 2

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


def radio_state_len(queue_packets: int) -> int:
    """The length of a radio's state (``RADIO_*``) for a queue of ``queue_packets``."""
    return RADIO_ENDS + queue_packets


def link_state_len(queue_packets: int) -> int:
    """The length of the state of the radio, its channel and the UART behind it as one float64 array
    (`UwbRadio` ``state``: the UART's, the channel's, the radio's, in that order)."""
    return UART_STATE_LEN + CHANNEL_STATE_LEN + radio_state_len(queue_packets)


def book_air(st: list[float] | np.ndarray, now_s: float, n_bytes: int) -> tuple[int, float]:
    """A packet of ``n_bytes`` handed to the radio at ``now_s``, on its state ``st`` (``RADIO_*``):
    (`SENT`, when it has left the air (s)), or (`OVERSIZE` or `OVERFLOW`, 0.0) with the air not booked.
    Plain arithmetic: `UwbRadio` runs it, the mocap link compiled in its radio's step."""
    if n_bytes > st[RADIO_MAX_PACKET]:
        return OVERSIZE, 0.0
    n = int(st[RADIO_N_ENDS])  # the packets leave the air in order: those gone by now are the first ones
    gone = 0
    while gone < n and st[RADIO_ENDS + gone] <= now_s:
        gone += 1
    if gone:
        for i in range(gone, n):
            st[RADIO_ENDS + i - gone] = st[RADIO_ENDS + i]
        n -= gone
        st[RADIO_N_ENDS] = n
    if n >= st[RADIO_QUEUE]:
        return OVERFLOW, 0.0
    busy = st[RADIO_BUSY_UNTIL]
    air_s = (n_bytes + st[RADIO_OVERHEAD]) * 8.0 / st[RADIO_RATE]
    busy = (now_s if now_s > busy else busy) + air_s
    st[RADIO_BUSY_UNTIL] = busy
    st[RADIO_ENDS + n] = busy
    st[RADIO_N_ENDS] = n + 1
    return SENT, busy


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
    The radio may draw ahead from ``rng``: give it a generator of its own (``rng.spawn``).
    ``state``: a float64 array of `link_state_len` where the radio, its channel and a UART behind it keep
    their numbers (the UART's first: `UartWire` ``state``), for a compiled caller that carries packets
    through all three; else each keeps its own."""

    def __init__(self, config: UwbConfig, rng: np.random.Generator, state: np.ndarray | None = None) -> None:
        self.config = config
        at = UART_STATE_LEN + CHANNEL_STATE_LEN
        self.channel = Channel(config, rng, None if state is None else state[UART_STATE_LEN:at])
        st = [0.0] * radio_state_len(config.queue_packets) if state is None else state[at:]
        st[RADIO_MAX_PACKET], st[RADIO_QUEUE] = config.max_packet_bytes, config.queue_packets
        st[RADIO_OVERHEAD], st[RADIO_RATE] = config.air_overhead_bytes, config.air_rate_bps
        st[RADIO_BUSY_UNTIL], st[RADIO_N_ENDS] = -math.inf, 0
        self.state = st
        #: (arrival_s, sequence number, data, sent_s) of the packets on their way, a heap (its head the
        #: next arrival; read, never changed, by the mocap link)
        self.in_flight: list[tuple[float, int, bytes, float]] = []
        self._seq = 0
        self.stats = UwbStats()
        self._late_after_s = config.late_after_s  # (the config is frozen)
        self._arrival_s, self._can_lose = self.channel.arrival_s, self.channel.can_lose

    def send(self, now_s: float, data: bytes, n_bytes: int | None = None) -> bool:
        """Hand a packet to the radio at ``now_s``; False when it is refused (size, full queue).
        A packet the channel will lose is accepted (True) and simply never arrives. ``n_bytes``: the
        packet's size on the air when ``data`` is what the far side makes of it rather than the packet
        (the mocap link hands over the frame the vehicle's module writes for it)."""
        if n_bytes is None:
            n_bytes = len(data)
        accepted, arrival_s = self.carry(now_s, n_bytes)
        if arrival_s is None:
            return accepted
        self._seq += 1
        data = data if data.__class__ is bytes else bytes(data)
        _heappush(self.in_flight, (arrival_s, self._seq, data, now_s))
        return True

    def carry(self, now_s: float, n_bytes: int) -> tuple[bool, float | None]:
        """`send` of a packet of ``n_bytes`` without keeping it: (whether the radio took it, its arrival
        (s) or None when it is refused or lost), counted as `send` counts it."""
        stats = self.stats
        stats.sent += 1
        code, busy = book_air(self.state, now_s, n_bytes)
        if code != SENT:
            if code == OVERSIZE:
                stats.oversize += 1
            else:
                stats.overflow += 1
            return False, None
        if self._can_lose:
            lost = self.channel.drop()
            if lost is not None:
                stats.lost += 1
                stats.burst_lost += lost == "burst"
                return True, None
        return True, self._arrival_s(busy)

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
