"""The mocap link service: tracked poses -> mocap payloads -> UWB radio -> LinkTrack frames on the
vehicle module's UART -> a Transport (pty, serial, UDP, memory) to the onboard computer.

    server = MocapLinkServer(transport, clock, rng, MocapConfig(rate_hz=120), UwbConfig(latency_s=0.01))
    while flying:
        server.update(clock.now_s(), vehicle_state, gap_pose)   # any rate; better at next_event_s()
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
from numba import njit
from numba.extending import register_jitable

from emulator.kernel_cache import entry
from emulator.mocap import (
    DONE,
    DRAW_BLOCK,
    FREE,
    PENDING,
    Q_BYTES,
    Q_READY,
    Q_STATUS,
    SLOT_LEN,
    TK_K,
    TK_LEN,
    TK_ROOM,
    TK_SLOT_WORDS,
    MocapConfig,
    MocapStats,
    MocapSystem,
    queue_head,
    tracker_step,
)
from emulator.uwb import (
    OVERSIZE,
    RADIO_ENDS,
    RADIO_QUEUE,
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
    UART_BUSY_UNTIL,
    UART_STATE_LEN,
    block_arrival_s,
    delivery_s,
    wire_finish_s,
)
from hil.link.clock import Clock, SimClock
from hil.link.linktrack import (
    BODY_IDS,
    MAX_BODIES,
    ONE_NODE_EXTRA_BYTES,
    ROLE_ANCHOR,
    ROLE_TAG,
    MocapFrameEncoder,
    mocap_frame_len,
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


@register_jitable
def _first_off_s(tk: np.ndarray, line: np.ndarray) -> float:
    """The earliest time a frame still queued in the tracker's state ``tk`` can be off the UART (s; inf:
    none queued): its ready time plus its bytes' time on a free line (`wire_finish_s` on ``line``, a free
    UART's state, ``LK_LINE``). The air, the channel and the frames ahead of it on the UART only make it
    later; until then the frames ready need not be taken through the radio (they are taken in the
    tracker's order, each booked from its own ready time, whenever that is done)."""
    at = TK_LEN + DRAW_BLOCK
    first = math.inf
    for s in range(int(tk[TK_ROOM])):
        o = at + s * SLOT_LEN
        if tk[o + Q_STATUS] == PENDING:
            line[UART_BUSY_UNTIL] = -math.inf
            off = wire_finish_s(line, tk[o + Q_READY], int(tk[o + Q_BYTES]))
            if off < first:
                first = off
    return first


#: what `_link_kernel` asks for besides the tracker's ``NEED_*`` (answered by `MocapSystem.answer`), having
#: done what it could (call again once answered): the channel's jitter draws spent, no room for another
#: frame on its way
NEED_JITTER, NEED_WAY_ROOM = -5, -6
#: the link's own numbers in its state, after the radio's: the radio's late limit (s), the frames its room
#: holds on their way, how many are on their way, then the radio's counts (frames sent, delivered, late,
#: refused as oversize, as overflow), then a free line of the UART (its state, ``UART_*``, as at its start:
#: `_first_off_s` books a frame on it)
LK_LATE_AFTER, LK_ROOM, LK_N_WAY, LK_SENT, LK_DELIVERED, LK_LATE, LK_OVERSIZE, LK_OVERFLOW, LK_LINE = range(9)
LK_LEN = LK_LINE + UART_STATE_LEN
#: a frame on its way: when its last byte is off the UART (s), its arrival (s), whether late (1.0), its
#: length (bytes)
W_DONE, W_ARRIVAL, W_LATE, W_BYTES = range(4)
WAY_LEN = 4
#: a frame's bytes in the state (float64 words: a frame of the most bodies)
WAY_WORDS = -(-mocap_frame_len(MAX_BODIES) // 8)
_FIRST_WAY_ROOM = 16  # frames the state has room for on their way at first (doubled when more are)
_RADIO_AT = UART_STATE_LEN + CHANNEL_STATE_LEN


def link_kernel_state_len(queue_packets: int, room: int) -> int:
    """The length of the state `_link_kernel` runs on: the UART's, the channel's and the radio's (as
    `link_state_len`), the link's numbers (``LK_*``), ``room`` frames on their way (``W_*``) and their bytes,
    as many frames' bytes to hand over and their lengths."""
    return link_state_len(queue_packets) + LK_LEN + room * (WAY_LEN + 2 * WAY_WORDS + 1)


@register_jitable
def _way_rows(st: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The link's part of its state ``st`` (`link_kernel_state_len`), as views: its numbers (``LK_*``), the
    frames on their way (``W_*``), their bytes, the bytes to hand over and their lengths."""
    la = _RADIO_AT + RADIO_ENDS + int(st[_RADIO_AT + RADIO_QUEUE])
    lk = st[la : la + LK_LEN]
    room = int(lk[LK_ROOM])
    ways = st[la + LK_LEN : la + LK_LEN + room * WAY_LEN]
    bytes_at = la + LK_LEN + room * WAY_LEN
    way_bytes = st[bytes_at : bytes_at + room * WAY_WORDS].view(np.uint8)
    out_at = bytes_at + room * WAY_WORDS
    out = st[out_at : out_at + room * WAY_WORDS].view(np.uint8)
    out_lens = st[out_at + room * WAY_WORDS : out_at + room * WAY_WORDS + room]
    return lk, ways, way_bytes, out, out_lens


@register_jitable
def _push_rows(lk: np.ndarray, ways: np.ndarray, way_bytes: np.ndarray, ready_s: float, arrival: float,
               done: float, frame: np.ndarray) -> bool:
    """A frame (its bytes ``frame``) ready at ``ready_s`` that arrives at ``arrival`` and is off the UART at
    ``done`` (s) after the frames on their way (the link's numbers ``lk``, the rows ``ways`` and their
    bytes, `_way_rows`; late when it arrives more than the radio's late limit after it was ready); False
    with nothing done when there is no room."""
    n_way = int(lk[LK_N_WAY])
    if n_way >= int(lk[LK_ROOM]):
        return False
    n_bytes = len(frame)
    w = n_way * WAY_LEN
    ways[w + W_DONE], ways[w + W_ARRIVAL], ways[w + W_BYTES] = done, arrival, n_bytes
    ways[w + W_LATE] = 1.0 if arrival - ready_s > lk[LK_LATE_AFTER] else 0.0
    b = n_way * 8 * WAY_WORDS
    way_bytes[b : b + n_bytes] = frame
    lk[LK_N_WAY] = n_way + 1
    return True


@register_jitable
def _hand_rows(lk: np.ndarray, ways: np.ndarray, way_bytes: np.ndarray, out: np.ndarray, out_lens: np.ndarray,
               limit_s: float) -> tuple[int, int, float]:
    """The frames on their way (`_way_rows`) that are off the UART by ``limit_s`` (s), in order, into the
    frames to hand over (``out``, their lengths ``out_lens``), counted as delivered (and late); the rest to
    the front. Returns (how many to hand over, their bytes, when the first left is off the UART (s; inf:
    none))."""
    n_way = int(lk[LK_N_WAY])
    n_out = n_bytes_out = 0
    while n_out < n_way and ways[n_out * WAY_LEN + W_DONE] <= limit_s:  # off the UART by now, in order
        w = n_out * WAY_LEN
        n_bytes, b = int(ways[w + W_BYTES]), n_out * 8 * WAY_WORDS
        out[n_bytes_out : n_bytes_out + n_bytes] = way_bytes[b : b + n_bytes]
        out_lens[n_out] = n_bytes
        n_bytes_out += n_bytes
        lk[LK_DELIVERED] += 1
        lk[LK_LATE] += ways[w + W_LATE]
        n_out += 1
    if n_out:  # (the rest to the front, in order)
        for i in range(n_out, n_way):
            j = i - n_out
            ways[j * WAY_LEN : (j + 1) * WAY_LEN] = ways[i * WAY_LEN : (i + 1) * WAY_LEN]
            way_bytes[j * 8 * WAY_WORDS : (j + 1) * 8 * WAY_WORDS] = way_bytes[
                i * 8 * WAY_WORDS : (i + 1) * 8 * WAY_WORDS]
        n_way -= n_out
        lk[LK_N_WAY] = n_way
    return n_out, n_bytes_out, ways[W_DONE] if n_way else math.inf


@njit(cache=True)
def _push_way(st: np.ndarray, ready_s: float, arrival: float, done: float, frame: np.ndarray) -> bool:
    """`_push_rows` on the link's state ``st`` (`link_kernel_state_len`)."""
    lk, ways, way_bytes, _, _ = _way_rows(st)
    return _push_rows(lk, ways, way_bytes, ready_s, arrival, done, frame)


@njit(cache=True)
def _hand_way(st: np.ndarray, limit_s: float) -> tuple[int, int, float]:
    """`_hand_rows` on the link's state ``st`` (`link_kernel_state_len`)."""
    lk, ways, way_bytes, out, out_lens = _way_rows(st)
    return _hand_rows(lk, ways, way_bytes, out, out_lens, limit_s)


@njit(cache=True)
def _link_kernel(mem: np.ndarray, tk: np.ndarray, st: np.ndarray, now_s: float, n: int, expose: int
                 ) -> tuple[int, int, int, float]:
    """The tracker, the radio, its channel that cannot lose and the UART to ``now_s`` (s) in one call: the
    tracker's step (`tracker_step` on its buffer ``mem`` with the true poses of ``n`` bodies and its state
    ``tk``) when ``expose`` is 1, then the frames it releases by then (`queue_head`: the earliest ready
    first) through the radio, its channel and onto the UART (`_carry_kernel`) onto the frames on their way
    (`_push_rows`, in the link's state ``st``, `link_kernel_state_len`), then those off the UART by then
    handed over (`_hand_rows`). Returns (how many frames to hand over, or one of the tracker's ``NEED_*``,
    `NEED_JITTER` or `NEED_WAY_ROOM` with what was done kept, the next exposure's number, the bytes to hand
    over or the normal draws needed, the earliest a frame can next be handed over (s; inf: never): the
    first on its way off the UART, or a frame still queued off it at the earliest, `_first_off_s`)."""
    if expose:
        code, k, aux = tracker_step(mem, tk, now_s, n)
        if code != DONE:
            return code, k, aux, math.inf
    else:
        k = int(tk[TK_K])
    lk, ways, way_bytes, out, out_lens = _way_rows(st)
    t_words, t_at = int(tk[TK_SLOT_WORDS]), TK_LEN + DRAW_BLOCK
    t_room = int(tk[TK_ROOM])
    frames = tk[t_at + t_room * SLOT_LEN : t_at + t_room * (SLOT_LEN + t_words)].view(np.uint8)
    limit = now_s + 1e-12
    while True:  # the frames released by now onto the radio, in the tracker's order
        s = queue_head(tk, limit)
        if s < 0:
            break
        if lk[LK_N_WAY] >= lk[LK_ROOM]:
            return NEED_WAY_ROOM, k, 0, math.inf
        o = t_at + s * SLOT_LEN
        ready_s, n_bytes = tk[o + Q_READY], int(tk[o + Q_BYTES])
        code, arrival, done = _carry_kernel(st, ready_s, n_bytes - ONE_NODE_EXTRA_BYTES, n_bytes)
        if code == SPENT:
            return NEED_JITTER, k, 0, math.inf
        tk[o + Q_STATUS] = FREE
        lk[LK_SENT] += 1
        if code == SENT:
            f = s * 8 * t_words
            _push_rows(lk, ways, way_bytes, ready_s, arrival, done, frames[f : f + n_bytes])
        elif code == OVERSIZE:
            lk[LK_OVERSIZE] += 1
        else:
            lk[LK_OVERFLOW] += 1
    n_out, n_bytes_out, first = _hand_rows(lk, ways, way_bytes, out, out_lens, limit)
    nxt = _first_off_s(tk, lk[LK_LINE:])
    return n_out, k, n_bytes_out, first if first < nxt else nxt


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

    Where the channel cannot lose, the tracker's step, the radio, its channel and the UART run in one
    compiled call (`_link_kernel`), which keeps the frames on their way and the radio's counts in the
    link's state: the radio's ``stats`` are brought up to date by `stats`. Where it can lose, the
    tracker's and the radio's own steps carry each frame onto the same frames on their way (`_push_way`),
    handed over as the kernel hands them (`_hand_way`).
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
        mocap = mocap or MocapConfig()
        self.mocap = MocapSystem(mocap, mocap_rng, encoder)
        uwb = uwb or UwbConfig()
        # the radio, its channel and the UART behind it keep their numbers in one array: when the channel
        # cannot lose, the tracker's step and a frame's way through all three are one compiled call
        # (`_link_kernel`), the array holding the frames on their way (else the radio's own steps, which
        # draw from the generator per packet, carry them onto the same frames on their way)
        lossless = not uwb.can_lose
        self._room = _FIRST_WAY_ROOM
        self._state = np.zeros(link_kernel_state_len(uwb.queue_packets, self._room))
        self.radio = UwbRadio(uwb, radio_rng, self._state)
        self.uart = UartWire(uwb.uart_baud, uwb.uart_bits_per_byte, self._state[:UART_STATE_LEN])
        self._ids = (module_id, station_node_id)
        #: LinkTrack frames handed to the transport so far
        self.frames_written = 0
        self._bytes_written = 0
        self._bytes_refused = 0
        self._now_s = -math.inf  # the latest time the chain was advanced to
        #: when the chain next has to move (inf: never), kept by `update` and `deliver`, the only ones that
        #: change the queues: the first frame's time off the UART or, of the frames not yet taken through
        #: the radio, the earliest off it (the link's kernel, `_first_off_s`) or the next ready time (a
        #: channel that can lose)
        self._next_move_s = math.inf
        self._period_s = mocap.period_s
        self._link_at = link_state_len(uwb.queue_packets)  # (where the link's numbers start: ``LK_*``)
        self._kernel = None
        self._mem = self.mocap.lay_out(_BOTH_IDS, (0.0,) * 14)
        lk = self._link_numbers()
        lk[LK_LATE_AFTER], lk[LK_ROOM] = uwb.late_after_s, self._room
        lk[LK_LINE:] = self._state[:UART_STATE_LEN]  # (the UART as it starts: free)
        self._views()
        # compiled (or loaded from numba's cache) now, called without numba's type dispatch
        self._hand = entry(_hand_way, self._state, 0.0)
        if lossless:
            self._kernel = entry(_link_kernel, self._mem, self.mocap.state, self._state, 0.0, 0, 0)
        else:  # (the frames the radio's own steps carry, read-only bytes)
            self._push = entry(_push_way, self._state, 0.0, 0.0, 0.0, np.frombuffer(b"\0", np.uint8))

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
        self._now_s = now
        mocap = self.mocap
        if mocap.exposure_k * self._period_s > now + 1e-12:  # (no exposure due)
            if self._next_move_s <= now + 1e-12:
                return self.deliver(now)
            return 0
        if (vehicle_state.__class__ is tuple and gap_pose.__class__ is tuple and len(vehicle_state) == 7
                and len(gap_pose) == 7):  # plain values (the runner's): no mapping to sort
            body_ids, poses = _BOTH_IDS, vehicle_state + gap_pose
        else:
            truth: dict[int, object] = {}
            if vehicle_state is not None:
                truth[_VEHICLE_ID] = vehicle_state
            if gap_pose is not None:
                truth[_GAP_ID] = gap_pose
            body_ids, poses = mocap.values_of(truth)
        kernel = self._kernel
        if kernel is None:  # (a channel that can lose: the tracker's own step, then the radio's)
            mocap.expose_values(now, body_ids, poses)
            r = mocap.next_release_s()
            nxt = r if r < self._next_move_s else self._next_move_s
            if nxt <= now + 1e-12:
                return self._forward(now)
            self._next_move_s = nxt
            return 0  # nothing to move yet (most exposures: a frame is ready after its latency)
        mem = self._mem = mocap.lay_out(body_ids, poses)
        n = len(body_ids)
        n_out, mocap.exposure_k, n_bytes, self._next_move_s = kernel(mem, mocap.state, self._state, now, n, 1)
        if n_out == 1:  # (one frame off the wire)
            return self._hand_over((self._out[:n_bytes].tobytes(),))
        return self._settle(now, n_out, n_bytes, n, 1, body_ids, poses) if n_out else 0

    def deliver(self, now_s: float) -> int:
        """Advance the radio and the wire to ``now_s`` without taking an exposure (none may be due
        before ``now_s``: see `next_exposure_s`); returns bytes written."""
        self._now_s = now_s
        if self._next_move_s <= now_s + 1e-12:
            kernel = self._kernel
            if kernel is None:
                return self._forward(now_s)
            mocap = self.mocap
            n_out, _, n_bytes, self._next_move_s = kernel(self._mem, mocap.state, self._state, now_s, 0, 0)
            if n_out == 1:  # (one frame off the wire: most moves)
                return self._hand_over((self._out[:n_bytes].tobytes(),))
            return self._settle(now_s, n_out, n_bytes, 0, 0, (), ()) if n_out else 0
        return 0  # nothing leaves the tracker or the wire by then (most calls)

    def _settle(self, now: float, n_out: int, aux: int, n: int, expose: int, body_ids: Sequence[int],
                poses: Sequence[float]) -> int:
        """What the link's kernel asked for (the tracker's draws or room: `MocapSystem.answer`; the
        channel's jitter draws; room on the way), then the kernel again until it is done; the frames it
        handed over to the transport. Returns bytes written."""
        mocap = self.mocap
        while n_out < 0:
            if n_out == NEED_JITTER:
                self.radio.channel.draw_block()
            elif n_out == NEED_WAY_ROOM:
                self._grow()
            else:
                mocap.answer(n_out, mocap.exposure_k, aux, body_ids, poses)
            n_out, mocap.exposure_k, aux, self._next_move_s = self._kernel(
                self._mem, mocap.state, self._state, now, n, expose)
        return self._hand_out(n_out)

    def _hand_out(self, n_out: int) -> int:
        """The ``n_out`` frames the link's state holds to hand over, to the transport; returns bytes
        written."""
        if not n_out:
            return 0
        out = self._out
        chunks, at = [], 0
        for size in self._out_lens[:n_out].astype(int).tolist():
            chunks.append(out[at : at + size].tobytes())
            at += size
        return self._hand_over(chunks)

    def _hand_over(self, chunks: Sequence[bytes]) -> int:
        """Frames off the UART to the transport (what it refuses counted); returns bytes written."""
        transport, written = self.transport, 0
        for chunk in chunks:
            if transport.closed:
                self._bytes_refused += len(chunk)
                continue
            sent = transport.send(chunk)
            written += sent
            self._bytes_refused += len(chunk) - sent
            self.frames_written += 1
        self._bytes_written += written
        return written

    def _link_numbers(self) -> np.ndarray:
        """The link's numbers (``LK_*``), a view of its state."""
        at = self._link_at
        return self._state[at : at + LK_LEN]

    def _grow(self) -> None:
        """Room for twice as many frames on their way (the radio's, the channel's and the UART's state
        moved with the rest)."""
        old, old_room = self._state, self._room
        room = 2 * old_room
        new = np.zeros(link_kernel_state_len(self.radio.config.queue_packets, room))
        ways_at = self._link_at + LK_LEN
        new[: ways_at + old_room * WAY_LEN] = old[: ways_at + old_room * WAY_LEN]
        at, old_at = ways_at + room * WAY_LEN, ways_at + old_room * WAY_LEN  # (their bytes)
        new[at : at + old_room * WAY_WORDS] = old[old_at : old_at + old_room * WAY_WORDS]
        self._state, self._room = new, room
        self._link_numbers()[LK_ROOM] = room
        self.uart.state = new[:UART_STATE_LEN]
        self.uart.finish_s = partial(wire_finish_s, self.uart.state)
        self.radio.channel.state, self.radio.state = new[UART_STATE_LEN:_RADIO_AT], new[_RADIO_AT:]
        self._views()

    def _views(self) -> None:
        """The frames the link's kernel hands over, in its state: their bytes and their lengths."""
        out_at = self._link_at + LK_LEN + self._room * (WAY_LEN + WAY_WORDS)
        self._out = memoryview(self._state[out_at : out_at + self._room * WAY_WORDS].view(np.uint8))
        self._out_lens = self._state[out_at + self._room * WAY_WORDS : out_at + self._room * (WAY_WORDS + 1)]

    def _forward(self, now: float) -> int:
        """(A channel that can lose.) The frames ready by ``now`` through the radio and onto the wire (each
        one's arrival and time off the wire known as it is sent) onto the frames on their way
        (`_push_way`), those off the wire by then to the transport (`_hand_way`; and when the chain next
        moves); returns bytes written."""
        mocap = self.mocap
        limit = now + 1e-12
        if mocap.next_release_s() <= limit:
            for ready_s, _, frame in mocap.released(now):
                n = len(frame)
                arrival = self.radio.carry(ready_s, n - ONE_NODE_EXTRA_BYTES)[1]
                if arrival is not None:
                    done = self.uart.finish_s(arrival, n)
                    data = np.frombuffer(frame, np.uint8)
                    while not self._push(self._state, ready_s, arrival, done, data):
                        self._grow()
        n_out, _, first = self._hand(self._state, limit)
        r = mocap.next_release_s()
        self._next_move_s = r if r < first else first
        return self._hand_out(n_out)

    def _count_arrivals(self, limit_s: float) -> None:
        """The radio's counts from the link's: the frames delivered (those on their way that have arrived
        by ``limit_s`` among them, the rest counted as they leave the wire) and late; where the channel
        cannot lose, those sent and refused too (else the radio's own steps count them)."""
        lk, r = self._link_numbers(), self.radio.stats
        n_way, ways_at = int(lk[LK_N_WAY]), self._link_at + LK_LEN
        ways = self._state[ways_at : ways_at + n_way * WAY_LEN].reshape(n_way, WAY_LEN)
        arrived = ways[ways[:, W_ARRIVAL] <= limit_s]
        if self._kernel is not None:
            r.sent, r.oversize, r.overflow = int(lk[LK_SENT]), int(lk[LK_OVERSIZE]), int(lk[LK_OVERFLOW])
        r.delivered = int(lk[LK_DELIVERED]) + len(arrived)
        r.late = int(lk[LK_LATE] + arrived[:, W_LATE].sum())

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
        if self._kernel is not None and self._now_s > -math.inf:
            # (the frames ready by then that the kernel has not taken through the radio yet, as none of
            # them could be off the UART: taken now, counted as sent, as they would be at any later move)
            self._next_move_s = -math.inf
            self.deliver(self._now_s)
        self._count_arrivals(self._now_s + 1e-12)
        return MocapLinkStats(
            mocap=self.mocap.stats,
            radio=UwbStats(**vars(self.radio.stats)),
            frames_written=self.frames_written,
            bytes_written=self._bytes_written,
            bytes_refused=self._bytes_refused,
        )


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the kernels a link builds with itself (the tracker's step, its
    queue's, and with the radio's step the link's), for a caller whose wall clock starts afterwards."""
    MocapLinkServer(MemoryTransport.pair()[0], SimClock(), np.random.default_rng(0))
