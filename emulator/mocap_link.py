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

from emulator.mocap import FrameRows, MocapConfig, MocapStats, MocapSystem
from emulator.uwb import UartWire, UwbConfig, UwbRadio, UwbStats
from hil.link.clock import Clock
from hil.link.linktrack import (
    BODY_IDS,
    MAX_BODIES,
    ROLE_ANCHOR,
    ROLE_TAG,
    encode_mocap_rows,
    encode_node_frame,
)
from hil.link.transport import Transport

_VEHICLE_ID, _GAP_ID = BODY_IDS["vehicle"], BODY_IDS["gap"]


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
        self.mocap = MocapSystem(mocap or MocapConfig(), mocap_rng)
        self.radio = UwbRadio(uwb or UwbConfig(), radio_rng)
        self.uart = UartWire(self.radio.config.uart_baud, self.radio.config.uart_bits_per_byte)
        self.module_id = module_id
        self.station_node_id = station_node_id
        self._frames_written = 0
        self._bytes_written = 0
        self._bytes_refused = 0
        #: when the tracker, the radio and the wire next have something: asked at every `deliver`
        self._next_events = (self.mocap.next_release_s, self.radio.next_event_s, self.uart.next_event_s)

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
        truth: dict[int, object] = {}
        if vehicle_state is not None:
            truth[_VEHICLE_ID] = vehicle_state
        if gap_pose is not None:
            truth[_GAP_ID] = gap_pose
        return self._forward(now, self.mocap.update_rows(now, truth))

    def deliver(self, now_s: float) -> int:
        """Advance the radio and the wire to ``now_s`` without taking an exposure (none may be due
        before ``now_s``: see `next_exposure_s`); returns bytes written."""
        limit = now_s + 1e-12
        next_release, next_arrival, next_off_wire = self._next_events
        if next_release() > limit and next_arrival() > limit and next_off_wire() > limit:
            return 0  # nothing leaves the tracker, the radio or the wire by then (most calls)
        return self._forward(now_s, self.mocap.release_rows(now_s))

    def _forward(self, now: float, frames: list[FrameRows]) -> int:
        radio, uart = self.radio, self.uart
        for frame_no, _, ready_s, rows in frames:
            radio.send(ready_s, encode_mocap_rows(frame_no & 0xFFFFFFFF, rows[:MAX_BODIES]))
        for arrival_s, data in radio.update_data(now):
            uart.write(arrival_s, encode_node_frame(
                data, ROLE_TAG, self.module_id, ROLE_ANCHOR, self.station_node_id))
        chunks = uart.update(now)
        if not chunks:
            return 0  # nothing off the wire yet (most calls)
        written = 0
        transport = self.transport
        for _, chunk in chunks:
            if transport.closed:
                self._bytes_refused += len(chunk)
                continue
            n = transport.send(chunk)
            written += n
            self._bytes_refused += len(chunk) - n
            self._frames_written += 1
        self._bytes_written += written
        return written

    def next_event_s(self) -> float:
        """When ``update`` next has something to do (s, on the clock)."""
        return min(self.mocap.next_event_s(), self.radio.next_event_s(), self.uart.next_event_s())

    def next_exposure_s(self) -> float:
        """When the tracker next needs the true poses (s); everything between exposures can be caught
        up later by `deliver` (or `update`), each frame keeping its own times."""
        return self.mocap.next_exposure_s()

    @property
    def frames_written(self) -> int:
        """LinkTrack frames handed to the transport so far."""
        return self._frames_written

    @property
    def stats(self) -> MocapLinkStats:
        return MocapLinkStats(
            mocap=MocapStats(**vars(self.mocap.stats)),
            radio=UwbStats(**vars(self.radio.stats)),
            frames_written=self._frames_written,
            bytes_written=self._bytes_written,
            bytes_refused=self._bytes_refused,
        )
