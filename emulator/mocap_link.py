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

from emulator.mocap import MocapConfig, MocapStats, MocapSystem
from emulator.uwb import UartWire, UwbConfig, UwbRadio, UwbStats
from hil.link.clock import Clock
from hil.link.linktrack import (
    BODY_IDS,
    ONE_NODE_EXTRA_BYTES,
    ROLE_ANCHOR,
    ROLE_TAG,
    MocapFrameEncoder,
)
from hil.link.transport import Transport

_VEHICLE_ID, _GAP_ID = BODY_IDS["vehicle"], BODY_IDS["gap"]
_BOTH_IDS = (_VEHICLE_ID, _GAP_ID)  # (in increasing order, as the tracker takes bodies)
assert _VEHICLE_ID < _GAP_ID


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
        self.radio = UwbRadio(uwb or UwbConfig(), radio_rng)
        self.uart = UartWire(self.radio.config.uart_baud, self.radio.config.uart_bits_per_byte)
        self._ids = (module_id, station_node_id)
        #: LinkTrack frames handed to the transport so far
        self.frames_written = 0
        self._bytes_written = 0
        self._bytes_refused = 0
        #: what the tracker, the radio and the wire hold, each ordered by time at its head (``[0][0]``):
        #: frames exposed (ready time), packets in flight (arrival), chunks on the line (done)
        self._queues = (self.mocap.pending, self.radio.in_flight, self.uart.queue)
        #: the earliest of those heads (inf: all empty), kept by `update` and `_forward`, the only ones that
        #: change the queues: when the chain next has something to move
        self._next_move_s = math.inf
        self._expose_values, self._released = self.mocap.expose_values, self.mocap.released
        self._radio_send, self._radio_arrived = self.radio.send, self.radio.arrived
        self._uart_write, self._uart_update = self.uart.write, self.uart.update

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
        frames, nxt = self._queues[0], self._next_move_s
        if frames and frames[0][0] < nxt:  # (a frame just exposed)
            nxt = frames[0][0]
        if nxt <= now + 1e-12:
            return self._forward(now)
        self._next_move_s = nxt
        return 0  # nothing to move yet (most exposures: a frame is ready after its latency)

    def deliver(self, now_s: float) -> int:
        """Advance the radio and the wire to ``now_s`` without taking an exposure (none may be due
        before ``now_s``: see `next_exposure_s`); returns bytes written."""
        if self._next_move_s <= now_s + 1e-12:
            return self._forward(now_s)
        return 0  # nothing leaves the tracker, the radio or the wire by then (most calls)

    def _forward(self, now: float) -> int:
        """The frames ready by ``now`` through the radio, those arrived onto the wire, those off the
        wire to the transport (and when the chain next moves); returns bytes written."""
        frames, packets, chunks = self._queues
        limit = now + 1e-12
        if frames and frames[0][0] <= limit:
            send = self._radio_send
            for ready_s, _, frame in self._released(now):
                send(ready_s, frame, len(frame) - ONE_NODE_EXTRA_BYTES)
        if packets and packets[0][0] <= limit:  # onto the wire as they arrive
            write = self._uart_write
            for arrival_s, frame, _ in self._radio_arrived(now):
                write(arrival_s, frame)
        written = 0
        if chunks and chunks[0][0] <= limit:
            transport = self.transport
            for _, chunk in self._uart_update(now):
                if transport.closed:
                    self._bytes_refused += len(chunk)
                    continue
                n = transport.send(chunk)
                written += n
                self._bytes_refused += len(chunk) - n
                self.frames_written += 1
            self._bytes_written += written
        nxt = chunks[0][0] if chunks else math.inf
        if packets and packets[0][0] < nxt:
            nxt = packets[0][0]
        if frames and frames[0][0] < nxt:
            nxt = frames[0][0]
        self._next_move_s = nxt
        return written

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
        return MocapLinkStats(
            mocap=MocapStats(**vars(self.mocap.stats)),
            radio=UwbStats(**vars(self.radio.stats)),
            frames_written=self.frames_written,
            bytes_written=self._bytes_written,
            bytes_refused=self._bytes_refused,
        )
