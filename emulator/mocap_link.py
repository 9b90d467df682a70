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
from emulator.mocap import DRAW_BLOCK, MAX_CATCH_UP_S, MocapConfig, MocapStats, MocapSystem, expose_kernel
from emulator.uwb import (
    OVERFLOW,
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

#: what `_link_kernel` asks for before it can go on (it returns one of these in place of a count of frames,
#: having done what it could, and is called again): the tracker's normal draws or its exponential draws
#: spent, the channel's jitter draws spent, no room for another frame
NEED_NORMALS, NEED_EXPONENTIALS, NEED_JITTER, NEED_ROOM = -1, -2, -3, -4
#: the link's own numbers in its state, after the radio's (`_link_kernel`): the next exposure's number,
#: whether its frame is measured but not queued (its processing latency not drawn yet), the tracker's
#: normal draws (how many, the next) and exponential ones (how many, the next), the tracker's period,
#: camera latency, mean processing latency (s), noises (m, rad), the radio's late limit (s), where the
#: frame starts in the tracker's buffer, the next frame sent's order, how many frames there is room for,
#: then the counts (frames exposed, bodies invalid, exposures skipped, frames sent, delivered, late,
#: refused as oversize, as overflow)
LK_K, LK_STAGE, LK_NOISE_LEN, LK_NOISE_NEXT, LK_EXP_LEN, LK_EXP_NEXT = 0, 1, 2, 3, 4, 5
LK_PERIOD, LK_LATENCY, LK_PROCESSING, LK_POS_SD, LK_ATT_SD, LK_LATE_AFTER = 6, 7, 8, 9, 10, 11
LK_FRAME_AT, LK_SEQ, LK_ROOM = 12, 13, 14
LK_FRAMES, LK_INVALID, LK_SKIPPED, LK_SENT, LK_DELIVERED, LK_LATE, LK_OVERSIZE, LK_OVERFLOW = range(15, 23)
LK_LEN = 23
#: a frame's place (one of ``LK_ROOM``): its status (`FREE`, `PENDING` on the tracker, `ON_WAY` through the
#: radio and the UART), when it is ready (s), its number, when it is off the UART (s), its arrival (s),
#: whether late (1.0), its order sent, its length (bytes)
S_STATUS, S_READY, S_K, S_DONE, S_ARRIVAL, S_LATE, S_SEQ, S_LEN = range(8)
SLOT_LEN = 8
FREE, PENDING, ON_WAY = 0.0, 1.0, 2.0
#: a frame's bytes in the state (float64 words: a frame of the most bodies)
SLOT_WORDS = -(-mocap_frame_len(MAX_BODIES) // 8)
_FIRST_ROOM = 16  # frames the state has room for at first (doubled when more are on their way)
_RADIO_AT = UART_STATE_LEN + CHANNEL_STATE_LEN


def fused_state_len(queue_packets: int, room: int) -> int:
    """The length of the state `_link_kernel` runs on: the radio's, its channel's and the UART's (as
    `link_state_len`), the link's numbers (``LK_*``), the tracker's exponential draws, ``room`` frames' places
    and bytes, and as many frames' lengths and bytes to hand over."""
    return (link_state_len(queue_packets) + LK_LEN + DRAW_BLOCK
            + room * (SLOT_LEN + SLOT_WORDS) + room * (1 + SLOT_WORDS))


@njit(cache=True)
def _link_kernel(mem: np.ndarray, st: np.ndarray, now_s: float, n: int, expose: int
                 ) -> tuple[int, int, int, float]:
    """The tracker, the radio, its channel that cannot lose and the UART to ``now_s`` in one call, on the
    tracker's buffer ``mem`` (`ExposureBuffer`, the true poses of ``n`` bodies there when ``expose`` is 1)
    and the link's state ``st`` (`fused_state_len`): the exposures due by then (`expose_kernel`, as
    `MocapSystem.expose_values` takes them: catching up at most `MAX_CATCH_UP_S`, each frame ready after
    the camera latency and a processing latency drawn per frame), the frames ready by then through the radio,
    its channel and onto the UART (`_carry_kernel`: the earliest ready first), and those off the UART by
    then (in order) into the frames to hand over, counted as delivered. Returns (how many frames to hand
    over, or one of ``NEED_*`` with what was done kept, the next exposure's number, their bytes or the
    normal draws needed, when the chain next moves (s; inf: never))."""
    la = _RADIO_AT + RADIO_ENDS + int(st[_RADIO_AT + RADIO_QUEUE])
    lk = st[la : la + LK_LEN]
    room = int(lk[LK_ROOM])
    exps = st[la + LK_LEN : la + LK_LEN + DRAW_BLOCK]
    slots_at = la + LK_LEN + DRAW_BLOCK
    slots = st[slots_at : slots_at + room * SLOT_LEN]
    bytes_at = slots_at + room * SLOT_LEN
    frames = st[bytes_at : bytes_at + room * SLOT_WORDS].view(np.uint8)
    lens_at = bytes_at + room * SLOT_WORDS
    out_lens = st[lens_at : lens_at + room]
    out = st[lens_at + room : lens_at + room + room * SLOT_WORDS].view(np.uint8)
    limit = now_s + 1e-12
    k = int(lk[LK_K])
    if expose:
        period = lk[LK_PERIOD]
        if now_s - k * period > MAX_CATCH_UP_S:  # (exposures nobody could see are not replayed)
            skip_to = math.floor(now_s / period)
            lk[LK_SKIPPED] += skip_to - k
            k = skip_to
            lk[LK_K] = k
        frame_at = int(lk[LK_FRAME_AT])
        n_bytes = mem.size - frame_at
        while k * period <= limit:
            t_s = k * period
            free = -1
            for s in range(room):
                if slots[s * SLOT_LEN + S_STATUS] == FREE:
                    free = s
                    break
            if free < 0:
                return NEED_ROOM, k, 0, math.inf
            if lk[LK_STAGE] == 0.0:
                invalid, nxt = expose_kernel(mem, n, lk[LK_POS_SD], lk[LK_ATT_SD], 0, int(lk[LK_NOISE_LEN]),
                                             int(lk[LK_NOISE_NEXT]), k & 0xFFFFFFFF, round(t_s * 1e6))
                if invalid < 0:
                    return NEED_NORMALS, k, nxt, math.inf
                lk[LK_NOISE_NEXT] = nxt
                lk[LK_INVALID] += invalid
                lk[LK_FRAMES] += 1
                lk[LK_STAGE] = 1.0
            extra = 0.0
            processing_s = lk[LK_PROCESSING]
            if processing_s > 0:  # (an exponential draw from the block drawn ahead)
                j = int(lk[LK_EXP_NEXT])
                if j >= lk[LK_EXP_LEN]:
                    return NEED_EXPONENTIALS, k, 0, math.inf
                lk[LK_EXP_NEXT] = j + 1
                extra = processing_s * exps[j]
            lk[LK_STAGE] = 0.0
            o = free * SLOT_LEN
            slots[o + S_STATUS], slots[o + S_READY] = PENDING, t_s + lk[LK_LATENCY] + extra
            slots[o + S_K], slots[o + S_LEN] = k, n_bytes
            frames[free * 8 * SLOT_WORDS : free * 8 * SLOT_WORDS + n_bytes] = mem[frame_at:]
            k += 1
            lk[LK_K] = k
    while True:  # the frames ready by now onto the radio, the earliest first (the tracker's order)
        best, ready_s, best_k = -1, 0.0, 0.0
        for s in range(room):
            o = s * SLOT_LEN
            if slots[o + S_STATUS] == PENDING and slots[o + S_READY] <= limit and (
                    best < 0 or slots[o + S_READY] < ready_s
                    or (slots[o + S_READY] == ready_s and slots[o + S_K] < best_k)):
                best, ready_s, best_k = s, slots[o + S_READY], slots[o + S_K]
        if best < 0:
            break
        o = best * SLOT_LEN
        n_bytes = int(slots[o + S_LEN])
        code, arrival, done = _carry_kernel(st, ready_s, n_bytes - ONE_NODE_EXTRA_BYTES, n_bytes)
        if code == SPENT:
            return NEED_JITTER, k, 0, math.inf
        lk[LK_SENT] += 1
        if code == SENT:
            slots[o + S_STATUS], slots[o + S_DONE], slots[o + S_ARRIVAL] = ON_WAY, done, arrival
            slots[o + S_LATE] = 1.0 if arrival - ready_s > lk[LK_LATE_AFTER] else 0.0
            slots[o + S_SEQ] = lk[LK_SEQ]
            lk[LK_SEQ] += 1
        else:
            slots[o + S_STATUS] = FREE
            lk[LK_OVERSIZE if code == OVERSIZE else LK_OVERFLOW] += 1
    n_out = n_bytes_out = 0
    while True:  # the frames off the UART by now, in the order sent
        best, seq = -1, 0.0
        for s in range(room):
            o = s * SLOT_LEN
            if slots[o + S_STATUS] == ON_WAY and slots[o + S_DONE] <= limit and (
                    best < 0 or slots[o + S_SEQ] < seq):
                best, seq = s, slots[o + S_SEQ]
        if best < 0:
            break
        o = best * SLOT_LEN
        n_bytes, at = int(slots[o + S_LEN]), best * 8 * SLOT_WORDS
        out[n_bytes_out : n_bytes_out + n_bytes] = frames[at : at + n_bytes]
        out_lens[n_out] = n_bytes
        n_out += 1
        n_bytes_out += n_bytes
        lk[LK_DELIVERED] += 1
        lk[LK_LATE] += slots[o + S_LATE]
        slots[o + S_STATUS] = FREE
    nxt_s = math.inf
    for s in range(room):
        o = s * SLOT_LEN
        status = slots[o + S_STATUS]
        if status == PENDING and slots[o + S_READY] < nxt_s:
            nxt_s = slots[o + S_READY]
        elif status == ON_WAY and slots[o + S_DONE] < nxt_s:
            nxt_s = slots[o + S_DONE]
    return n_out, k, n_bytes_out, nxt_s


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

    Where the channel cannot lose and nothing is occluded, the tracker's exposures, the radio, its channel
    and the UART run in one compiled call (`_link_kernel`), which keeps the frames on their way and the
    counts in the link's state: the tracker's and the radio's ``stats`` are brought up to date by `stats`.
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
        # the radio, its channel and the UART behind it keep their numbers in one array: a frame goes through
        # all three in one compiled call (`_carry_kernel`) when the channel cannot lose (else through the
        # radio's own steps, which draw from the generator per packet); with no occlusion either (whose
        # draws are the tracker's, per body) the tracker's exposures too (`_link_kernel`), the array holding
        # the frames on their way
        lossless = not uwb.can_lose
        fused = lossless and mocap.occlusion_prob == 0
        self._room = _FIRST_ROOM if fused else 0
        self._state = np.zeros(fused_state_len(uwb.queue_packets, self._room) if fused
                               else link_state_len(uwb.queue_packets))
        self.radio = UwbRadio(uwb, radio_rng, self._state)
        self.uart = UartWire(uwb.uart_baud, uwb.uart_bits_per_byte, self._state[:UART_STATE_LEN])
        self._carry = entry(_carry_kernel, self._state, 0.0, 0, 0) if lossless and not fused else None
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
        #: `update` and `_forward` (or the link's kernel), the only ones that change the queues: when the
        #: chain next has to move
        self._next_move_s = math.inf
        self._expose_values, self._released = self.mocap.expose_values, self.mocap.released
        self._late_after_s = uwb.late_after_s
        self._period_s = mocap.period_s
        self._kernel = None
        self._link_at = link_state_len(uwb.queue_packets)  # (where the link's numbers start: ``LK_*``)
        if fused:
            lk = self._link_numbers()
            lk[LK_PERIOD], lk[LK_LATENCY], lk[LK_PROCESSING] = (
                self._period_s, mocap.camera_latency_s, mocap.processing_s)
            lk[LK_POS_SD], lk[LK_ATT_SD], lk[LK_LATE_AFTER] = (
                mocap.pos_noise_m, mocap.att_noise_rad, uwb.late_after_s)
            lk[LK_ROOM] = self._room
            self._views()
            self._lay_out(_BOTH_IDS)
            # compiled (or loaded from numba's cache) now, called without numba's type dispatch
            self._kernel = entry(_link_kernel, self._mem, self._state, 0.0, 0, 0)

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
        plain = (vehicle_state.__class__ is tuple and gap_pose.__class__ is tuple and len(vehicle_state) == 7
                 and len(gap_pose) == 7)  # plain values (the runner's): no mapping to sort
        kernel = self._kernel
        if kernel is not None:
            self._now_s = now
            mocap = self.mocap
            if mocap.exposure_k * self._period_s <= now + 1e-12:  # (an exposure due)
                if plain:
                    body_ids, poses = _BOTH_IDS, vehicle_state + gap_pose
                else:
                    body_ids, poses = mocap.values_of(self._truth(vehicle_state, gap_pose))
                if body_ids is not self._laid_ids:
                    self._lay_out(body_ids)
                self._put_poses(self._io_buf, 0, *poses)
                n_out, mocap.exposure_k, n_bytes, self._next_move_s = kernel(
                    self._mem, self._state, now, self._n_bodies, 1)
                if n_out == 1:
                    return self._hand_over((self._out[:n_bytes].tobytes(),))
                return self._settle(now, n_out, n_bytes, 1) if n_out else 0
            if self._next_move_s <= now + 1e-12:
                return self.deliver(now)
            return 0
        if plain:
            self._expose_values(now, _BOTH_IDS, vehicle_state + gap_pose)
        else:
            self.mocap.expose(now, self._truth(vehicle_state, gap_pose))
        self._now_s = now
        frames, nxt = self._pending, self._next_move_s
        if frames and frames[0][0] < nxt:  # (a frame just exposed)
            nxt = frames[0][0]
        if nxt <= now + 1e-12:
            return self._forward(now)
        self._next_move_s = nxt
        return 0  # nothing to move yet (most exposures: a frame is ready after its latency)

    @staticmethod
    def _truth(vehicle_state: object | None, gap_pose: object | None) -> dict[int, object]:
        """The true poses given (by body id; a body not given is not seen)."""
        truth: dict[int, object] = {}
        if vehicle_state is not None:
            truth[_VEHICLE_ID] = vehicle_state
        if gap_pose is not None:
            truth[_GAP_ID] = gap_pose
        return truth

    def deliver(self, now_s: float) -> int:
        """Advance the radio and the wire to ``now_s`` without taking an exposure (none may be due
        before ``now_s``: see `next_exposure_s`); returns bytes written."""
        self._now_s = now_s
        if self._next_move_s <= now_s + 1e-12:
            kernel = self._kernel
            if kernel is None:
                return self._forward(now_s)
            n_out, _, n_bytes, self._next_move_s = kernel(self._mem, self._state, now_s, self._n_bodies, 0)
            if n_out == 1:  # (one frame off the wire: most moves)
                return self._hand_over((self._out[:n_bytes].tobytes(),))
            return self._settle(now_s, n_out, n_bytes, 0) if n_out else 0
        return 0  # nothing leaves the tracker or the wire by then (most calls)

    def _settle(self, now: float, n_out: int, n_bytes: int, expose: int) -> int:
        """What the link's kernel asked for (draws, room), then the kernel again until it is done; the
        frames it handed over to the transport. Returns bytes written."""
        while n_out < 0:
            lk = self._link_numbers()
            if n_out == NEED_NORMALS:
                lk[LK_NOISE_LEN], lk[LK_NOISE_NEXT] = self.mocap.draw_normals(n_bytes), 0
            elif n_out == NEED_EXPONENTIALS:
                at = self._link_at + LK_LEN
                self._state[at : at + DRAW_BLOCK] = self.mocap.draw_exponentials()
                lk[LK_EXP_LEN], lk[LK_EXP_NEXT] = DRAW_BLOCK, 0
            elif n_out == NEED_JITTER:
                self.radio.channel.draw_block()
            else:
                self._grow()
            n_out, self.mocap.exposure_k, n_bytes, self._next_move_s = self._kernel(
                self._mem, self._state, now, self._n_bodies, expose)
        if not n_out:
            return 0
        out = self._out
        chunks, at = [], 0
        for n in self._out_lens[:n_out].astype(int).tolist():
            chunks.append(out[at : at + n].tobytes())
            at += n
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

    def _lay_out(self, body_ids: tuple[int, ...] | list[int]) -> None:
        """The tracker's buffer for ``body_ids`` (`MocapSystem.lay_out`), as the link's kernel takes it."""
        buf = self.mocap.lay_out(body_ids)
        self._mem, self._io_buf, self._put_poses = buf.mem, buf.io_buf, buf.put_poses
        self._n_bodies = len(body_ids)
        # (the same tuple again is known by identity; a list, sorted anew each time, is laid out each time)
        self._laid_ids = buf.body_ids if body_ids.__class__ is tuple else None
        self._link_numbers()[LK_FRAME_AT] = buf.frame_at

    def _grow(self) -> None:
        """Room for twice as many frames on their way (the radio's, the channel's and the UART's state
        moved with the rest)."""
        old, old_room = self._state, self._room
        room = 2 * old_room
        new = np.zeros(fused_state_len(self.radio.config.queue_packets, room))
        slots_at = self._link_at + LK_LEN + DRAW_BLOCK
        new[:slots_at] = old[:slots_at]
        new[slots_at : slots_at + old_room * SLOT_LEN] = old[slots_at : slots_at + old_room * SLOT_LEN]
        at, old_at = slots_at + room * SLOT_LEN, slots_at + old_room * SLOT_LEN  # (the frames' bytes)
        new[at : at + old_room * SLOT_WORDS] = old[old_at : old_at + old_room * SLOT_WORDS]
        self._state, self._room = new, room
        self._link_numbers()[LK_ROOM] = room
        self.uart.state = new[:UART_STATE_LEN]
        self.uart.finish_s = partial(wire_finish_s, self.uart.state)
        self.radio.channel.state, self.radio.state = new[UART_STATE_LEN:_RADIO_AT], new[_RADIO_AT:]
        self._views()

    def _views(self) -> None:
        """The frames the link's kernel hands over, in its state: their lengths and their bytes."""
        out_at = self._link_at + LK_LEN + DRAW_BLOCK + self._room * (SLOT_LEN + SLOT_WORDS)
        self._out_lens = self._state[out_at : out_at + self._room]
        self._out = memoryview(self._state[out_at + self._room :].view(np.uint8))

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
            stats, counted = self.radio.stats, self._n_arrived
            for _, _, late, _ in on_way[:n]:
                if counted:  # (counted by `stats` already)
                    counted -= 1
                else:
                    stats.delivered += 1
                    stats.late += late
            written = self._hand_over([chunk for _, _, _, chunk in on_way[:n]])
            del on_way[:n]
            self._n_arrived = counted
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

    def _sync_counts(self, limit_s: float) -> None:
        """The tracker's and the radio's counts from the link's kernel's, the frames on their way that
        have arrived by ``limit_s`` counted as delivered (the kernel counts them as they leave the wire)."""
        lk = self._link_numbers()
        slots_at = self._link_at + LK_LEN + DRAW_BLOCK
        slots = self._state[slots_at : slots_at + self._room * SLOT_LEN].reshape(self._room, SLOT_LEN)
        arrived = slots[(slots[:, S_STATUS] == ON_WAY) & (slots[:, S_ARRIVAL] <= limit_s)]
        m, r = self.mocap.stats, self.radio.stats
        m.frames, m.bodies_occluded, m.frames_skipped = (
            int(lk[LK_FRAMES]), int(lk[LK_INVALID]), int(lk[LK_SKIPPED]))
        r.sent, r.oversize, r.overflow = int(lk[LK_SENT]), int(lk[LK_OVERSIZE]), int(lk[LK_OVERFLOW])
        r.delivered = int(lk[LK_DELIVERED]) + len(arrived)
        r.late = int(lk[LK_LATE] + arrived[:, S_LATE].sum())

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
        if self._kernel is None:
            self._count_arrivals(self._now_s + 1e-12)
        else:
            self._sync_counts(self._now_s + 1e-12)
        return MocapLinkStats(
            mocap=MocapStats(**vars(self.mocap.stats)),
            radio=UwbStats(**vars(self.radio.stats)),
            frames_written=self.frames_written,
            bytes_written=self._bytes_written,
            bytes_refused=self._bytes_refused,
        )


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the kernels a link builds with itself (the exposure and the
    radio's step in one kernel; each alone, for a link whose bodies can be occluded), for a caller whose
    wall clock starts afterwards."""
    for mocap in (MocapConfig(), MocapConfig(occlusion_prob=0.5)):
        MocapLinkServer(MemoryTransport.pair()[0], SimClock(), np.random.default_rng(0), mocap)
