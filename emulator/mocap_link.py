"""The mocap link service: tracked poses -> mocap payloads -> UWB radio -> LinkTrack frames on the
vehicle module's UART -> a Transport (pty, serial, UDP, memory) to the onboard computer.

    server = MocapLinkServer(transport, clock, rng, MocapConfig(rate_hz=120), UwbConfig(latency_s=0.01))
    while flying:
        server.update(clock.now_s(), vehicle_state, gap_pose)   # any rate; better at next_event_s()
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numba.extending import register_jitable

from emulator.kernel_cache import entry
from emulator.mocap import MocapConfig, MocapStats, MocapSystem
from emulator.uwb import (
    OVERFLOW,
    OVERSIZE,
    SENT,
    UartWire,
    UwbConfig,
    UwbRadio,
    UwbStats,
    book_air,
    link_state_len,
)
from hil.link.channel import (
    CH_JITTER,
    CH_NEXT,
    CHANNEL_STATE_LEN,
    JITTER_BLOCK,
    UART_STATE_LEN,
    block_arrival_s,
    delivery_s,
    wire_finish_s,
)
from hil.link.clock import Clock, SimClock
from hil.link.linktrack import (
    BODY_IDS,
    ONE_NODE_EXTRA_BYTES,
    ROLE_ANCHOR,
    ROLE_TAG,
    MocapFrameEncoder,
)
from hil.link.memory import MemoryTransport
from hil.link.transport import Transport

_VEHICLE_ID, _GAP_ID = BODY_IDS["vehicle"], BODY_IDS["gap"]
_BOTH_IDS = (_VEHICLE_ID, _GAP_ID)  # (in increasing order, as the tracker takes bodies)
assert _VEHICLE_ID < _GAP_ID

#: what `_carry_kernel` says besides `emulator.uwb`'s SENT, OVERSIZE and OVERFLOW: the channel's jitter
#: draws are spent (nothing done: draw the next block, then call again)
SPENT = 3

for _plain in (delivery_s, block_arrival_s, wire_finish_s, book_air):  # (compiled into `_carry_kernel`)
    register_jitable(_plain)


@njit(cache=True)
def _carry_kernel(st: np.ndarray, ready_s: float, n_air: int, n_bytes: int) -> tuple[int, float, float]:
    """A frame of ``n_bytes`` whose radio packet is ``n_air`` bytes, ready at ``ready_s``, through the radio
    (`book_air`), its channel that cannot lose (`block_arrival_s`) and onto the UART (`wire_finish_s`), on
    their state ``st`` (`UwbRadio` ``state``: the UART's, the channel's, the radio's): (`SENT`, its arrival
    (s), when its last byte is off the UART (s)), or (the refusal, 0.0, 0.0), or (`SPENT`, 0.0, 0.0) with
    nothing done when the jitter draws are spent."""
    chan = st[UART_STATE_LEN : UART_STATE_LEN + CHANNEL_STATE_LEN]
    if chan[CH_JITTER] > 0 and chan[CH_NEXT] >= JITTER_BLOCK:
        return SPENT, 0.0, 0.0
    code, busy = book_air(st[UART_STATE_LEN + CHANNEL_STATE_LEN :], ready_s, n_air)
    if code != SENT:
        return code, 0.0, 0.0
    arrival = block_arrival_s(chan, busy)
    return SENT, arrival, wire_finish_s(st[:UART_STATE_LEN], arrival, n_bytes)


@dataclass(frozen=True)
class MocapLinkStats:
    """Snapshot of the whole chain: tracker, radio, UART and transport (frames, bytes)."""

    mocap: MocapStats
    radio: UwbStats
    frames_written: int
    bytes_written: int
    bytes_refused: int  # the transport did not take them (peer not reading, buffer full)


class MocapLinkServer:
    """Emulator-side mocap over UWB, feeding one transport. Bodies: "vehicle" (id 1), "gap" (id 2).

    ``update(now_s, vehicle_state, gap_pose)`` takes the true poses (anything with ``pos_m`` or
    ``centre_m`` and ``quat_wxyz``: a VehicleState, a world Gap; the gap may be None or move) and
    writes to the transport the frames whose exposure, latency, radio and wire time have passed.
    """

    def __init__(
        self,
        transport: Transport,
        clock: Clock,
        rng: np.random.Generator,
        mocap: MocapConfig | None = None,
        uwb: UwbConfig | None = None,
        *,
        module_id: int = 0,
        station_node_id: int = 0,
    ) -> None:
        self.transport = transport
        self.clock = clock
        mocap_rng, radio_rng = rng.spawn(2)
        # the tracker's exposures come out as the frames the vehicle's module writes for them (encoded by
        # the exposure kernel); the radio carries each, sized by its node data
        encoder = MocapFrameEncoder(ROLE_TAG, module_id, ROLE_ANCHOR, station_node_id)
        self.mocap = MocapSystem(mocap or MocapConfig(), mocap_rng, encoder)
        uwb = uwb or UwbConfig()
        # the radio, its channel and the UART behind it keep their numbers in one array: a frame goes through
        # all three in one compiled call (`_carry_kernel`) when the channel cannot lose (else through the
        # radio's own steps, which draw from the generator per packet)
        self._state = np.zeros(link_state_len(uwb.queue_packets))
        self.radio = UwbRadio(uwb, radio_rng, self._state)
        self.uart = UartWire(uwb.uart_baud, uwb.uart_bits_per_byte, self._state[:UART_STATE_LEN])
        lossless = not self.radio.channel.can_lose
        self._carry = entry(_carry_kernel, self._state, 0.0, 0, 0) if lossless else None
        self._ids = (module_id, station_node_id)
        #: LinkTrack frames handed to the transport so far
        self.frames_written = 0
        self._bytes_written = 0
        self._bytes_refused = 0
        #: the frames exposed, not yet on the radio (a heap: its head ``[0][0]`` the next ready time)
        self._pending = self.mocap.pending
        #: the frames sent on their way: (when off the UART (s), arrival (s), whether late, the frame), in
        #: order (both times increase); each counted as delivered when it leaves, or by `stats` as it is
        #: read, which counts the first ``_n_arrived`` of them ahead
        self._on_way: list[tuple[float, float, bool, bytes]] = []
        self._n_arrived = 0
        self._now_s = -math.inf  # the latest time the chain was advanced to
        #: the earlier of the next ready time and the first frame's time off the UART (inf: none), kept by
        #: `update` and `_forward`, the only ones that change the queues: when the chain next has to move
        self._next_move_s = math.inf
        self._expose_values, self._released = self.mocap.expose_values, self.mocap.released
        self._late_after_s = uwb.late_after_s

    @property
    def module_id(self) -> int:
        """The id of the vehicle's UWB module, in every frame it writes."""
        return self._ids[0]

    @property
    def station_node_id(self) -> int:
        """The node id of the mocap station's radio, in every frame."""
        return self._ids[1]

    def update(
        self,
        now_s: float | None = None,
        vehicle_state: object | None = None,
        gap_pose: object | None = None,
    ) -> int:
        """Advance the chain to ``now_s`` (default: the clock's time); returns bytes written."""
        now = self.clock.now_s() if now_s is None else float(now_s)
        if not math.isfinite(now):
            raise ValueError(f"now_s must be finite, got {now_s}")
        if (vehicle_state.__class__ is tuple and gap_pose.__class__ is tuple and len(vehicle_state) == 7
                and len(gap_pose) == 7):  # plain values (the runner's): no mapping to sort
            self._expose_values(now, _BOTH_IDS, vehicle_state + gap_pose)
        elif vehicle_state is not None and gap_pose is not None:
            self.mocap.expose(now, {_VEHICLE_ID: vehicle_state, _GAP_ID: gap_pose})
        else:
            truth: dict[int, object] = {}
            if vehicle_state is not None:
                truth[_VEHICLE_ID] = vehicle_state
            if gap_pose is not None:
                truth[_GAP_ID] = gap_pose
            self.mocap.expose(now, truth)
        self._now_s = now
        frames, nxt = self._pending, self._next_move_s
        if frames and frames[0][0] < nxt:  # (a frame just exposed)
            nxt = frames[0][0]
        if nxt <= now + 1e-12:
            return self._forward(now)
        self._next_move_s = nxt
        return 0  # nothing to move yet (most exposures: a frame is ready after its latency)

    def deliver(self, now_s: float) -> int:
        """Advance the radio and the wire to ``now_s`` without taking an exposure (none may be due
        before ``now_s``: see `next_exposure_s`); returns bytes written."""
        self._now_s = now_s
        if self._next_move_s <= now_s + 1e-12:
            return self._forward(now_s)
        return 0  # nothing leaves the tracker or the wire by then (most calls)

    def _forward(self, now: float) -> int:
        """The frames ready by ``now`` through the radio and onto the wire (each one's arrival and time off
        the wire known as it is sent), those off the wire by then to the transport (and when the chain
        next moves); returns bytes written."""
        frames, on_way = self._pending, self._on_way
        limit = now + 1e-12
        if frames and frames[0][0] <= limit:
            carry, stats, late_after = self._carry, self.radio.stats, self._late_after_s
            for ready_s, _, frame in self._released(now):
                n = len(frame)
                if carry is None:  # (a channel that can lose: the radio's steps, which count the packet)
                    arrival = self.radio.carry(ready_s, n - ONE_NODE_EXTRA_BYTES)[1]
                    if arrival is not None:
                        done = self.uart.finish_s(arrival, n)
                        on_way.append((done, arrival, arrival - ready_s > late_after, frame))
                    continue
                stats.sent += 1
                code, arrival, done = carry(self._state, ready_s, n - ONE_NODE_EXTRA_BYTES, n)
                if code == SPENT:
                    self.radio.channel.draw_block()
                    code, arrival, done = carry(self._state, ready_s, n - ONE_NODE_EXTRA_BYTES, n)
                if code == SENT:
                    on_way.append((done, arrival, arrival - ready_s > late_after, frame))
                else:
                    stats.oversize += code == OVERSIZE
                    stats.overflow += code == OVERFLOW
        written = 0
        if on_way and on_way[0][0] <= limit:
            n = 1
            while n < len(on_way) and on_way[n][0] <= limit:
                n += 1
            transport, stats, counted = self.transport, self.radio.stats, self._n_arrived
            for _, _, late, chunk in on_way[:n]:
                if counted:  # (counted by `stats` already)
                    counted -= 1
                else:
                    stats.delivered += 1
                    stats.late += late
                if transport.closed:
                    self._bytes_refused += len(chunk)
                    continue
                sent = transport.send(chunk)
                written += sent
                self._bytes_refused += len(chunk) - sent
                self.frames_written += 1
            del on_way[:n]
            self._n_arrived = counted
            self._bytes_written += written
        nxt = on_way[0][0] if on_way else math.inf
        if frames and frames[0][0] < nxt:
            nxt = frames[0][0]
        self._next_move_s = nxt
        return written

    def _count_arrivals(self, limit_s: float) -> None:
        """Count the frames on their way that have arrived by ``limit_s`` (and are not counted yet) as the
        radio's deliveries (the rest are counted as they leave the wire)."""
        on_way, k, stats = self._on_way, self._n_arrived, self.radio.stats
        while k < len(on_way) and on_way[k][1] <= limit_s:
            stats.delivered += 1
            stats.late += on_way[k][2]
            k += 1
        self._n_arrived = k

    def next_event_s(self) -> float:
        """When ``update`` next has something to do (s, on the clock)."""
        m = self.mocap.next_exposure_s()
        return m if m < self._next_move_s else self._next_move_s

    def next_exposure_s(self) -> float:
        """When the tracker next needs the true poses (s); everything between exposures can be caught
        up later by `deliver` (or `update`), each frame keeping its own times."""
        return self.mocap.next_exposure_s()

    @property
    def stats(self) -> MocapLinkStats:
        self._count_arrivals(self._now_s + 1e-12)
        return MocapLinkStats(
            mocap=MocapStats(**vars(self.mocap.stats)),
            radio=UwbStats(**vars(self.radio.stats)),
            frames_written=self.frames_written,
            bytes_written=self._bytes_written,
            bytes_refused=self._bytes_refused,
        )


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the kernels a link builds with itself (the tracker's exposure,
    the radio's step), for a caller whose wall clock starts afterwards."""
    MocapLinkServer(MemoryTransport.pair()[0], SimClock(), np.random.default_rng(0))
