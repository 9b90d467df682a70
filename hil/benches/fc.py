"""FC figures: setpoint latency over a pty at 921600 baud beside the frame's wire time, and the
emulator's real-time factor (1 kHz physics + FC + telemetry, as fast as it runs)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterable
from typing import Protocol

from emulator.loops.realtime_runner import Pollable, RealtimeRunner
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.servers.mavlink_server import MavlinkServer
from emulator.vehicle import EmulatedVehicle
from hil.benches import BenchRow
from hil.link import MemoryTransport, PtyTransport, SerialTransport, SimClock, WallClock
from hil.link.mavlink import MavlinkCodec, quat_from_euler
from hil.link.transport import Transport
from hil.link.uart import UartModel

BAUD = 921600


class LatencyRig(Protocol):
    """One protocol's side of `setpoint_latency`: its FC server and its onboard writer."""

    def serve(self, vehicle: EmulatedVehicle, link: Transport, clock: WallClock,
              applied: Callable[[int], None]) -> Pollable:
        """The FC's server on ``link``, calling ``applied(i)`` when it applies setpoint number ``i``."""
        ...

    def write(self, link: Transport, clock: WallClock, i: int, thrust_fraction: float) -> int:
        """Write setpoint number ``i`` (1..n) on the onboard end and read what came; the frame's bytes."""
        ...


def setpoint_latency(n: int, baud: int, rig: LatencyRig) -> tuple[float, int]:
    """Median seconds from the onboard side's write of a setpoint to the FC applying it over a pty at
    ``baud``, and the frame's length (bytes). The FC runs its real-time loop in a thread, the writer in
    this one."""
    profile = load_profile("n3_tx2")
    clock = WallClock()
    fc_link = PtyTransport.create(baud)
    onboard_link = SerialTransport(fc_link.endpoint, baud)
    vehicle = EmulatedVehicle(profile)
    applied: dict[int, float] = {}
    server = rig.serve(vehicle, fc_link, clock, lambda i: applied.setdefault(i, time.perf_counter()))
    runner = RealtimeRunner(vehicle, [server], clock=clock, wait_fds=[fc_link.fileno()]).start()
    thrust = 0.3 * profile.mass_kg * GRAVITY_M_S2 / profile.n3_full_thrust_n
    sent: dict[int, float] = {}
    frame_len = 0
    try:
        for i in range(1, n + 1):
            sent[i] = time.perf_counter()
            frame_len = rig.write(onboard_link, clock, i, thrust)
            time.sleep(0.01)
        time.sleep(0.05)
    finally:
        runner.stop()
        onboard_link.close()
        fc_link.close()
    lat = [applied[i] - sent[i] for i in sent if i in applied]
    if len(lat) < n // 2:
        raise RuntimeError(f"only {len(lat)} of {n} setpoints reached the FC")
    return statistics.median(lat), frame_len


class _MavlinkRig:
    """SET_ATTITUDE_TARGET, its number in time_boot_ms."""

    def __init__(self) -> None:
        self._codec: MavlinkCodec | None = None

    def serve(self, vehicle: EmulatedVehicle, link: Transport, clock: WallClock,
              applied: Callable[[int], None]) -> Pollable:
        server = MavlinkServer(vehicle, MavlinkCodec(link, clock, 1, 1))
        server.on_setpoint = lambda msg, now: applied(msg.time_boot_ms)
        return server

    def write(self, link: Transport, clock: WallClock, i: int, thrust_fraction: float) -> int:
        if self._codec is None or self._codec.transport is not link:
            self._codec = MavlinkCodec(link, clock, 255, 190)
        codec = self._codec
        q = list(quat_from_euler(0.0, 0.0, 0.0))
        msg = codec.mav.set_attitude_target_encode(i, 1, 1, 7, q, 0.0, 0.0, 0.0, thrust_fraction)
        n = len(codec.send(msg))
        codec.receive(0.0)  # keep the telemetry flowing
        return n


def _realtime_factor(sim_s: float) -> float:
    """Simulated seconds per wall second of the FC alone: 1 kHz physics, inner loop, telemetry."""
    profile = load_profile("n3_tx2")
    clock = SimClock()
    fc_end, gcs_end = MemoryTransport.pair()
    vehicle = EmulatedVehicle(profile)
    server = MavlinkServer(vehicle, MavlinkCodec(fc_end, clock, 1, 1))
    vehicle.fc.arm(0.0)
    server.poll(0.0)
    vehicle.step(10)  # compile before timing
    start = time.perf_counter()
    t0 = clock.now_s()
    steps = round(sim_s / vehicle.dt_s)
    for k in range(1, steps + 1):
        now = round(t0 + k * vehicle.dt_s, 9)
        clock.advance_to(now)
        server.poll(now)
        vehicle.step(1)
        if k % 100 == 0:
            gcs_end.recv(0.0)  # drain the telemetry as a client would
    return sim_s / (time.perf_counter() - start)


def collect(quick: bool) -> Iterable[BenchRow]:
    median_s, frame_len = setpoint_latency(50 if quick else 300, BAUD, _MavlinkRig())
    yield BenchRow(
        "setpoint_latency_us",
        median_s * 1e6,
        "us",
        f"SET_ATTITUDE_TARGET write -> FC applies it, pty {BAUD} baud, median",
    )
    yield BenchRow(
        "setpoint_wire_us",
        UartModel(BAUD).wire_time_s(frame_len) * 1e6,
        "us",
        f"that frame ({frame_len} bytes) on a {BAUD} baud UART, 10 bits a byte",
    )
    yield BenchRow(
        "fc_realtime_factor",
        _realtime_factor(1.0 if quick else 5.0),
        "x",
        "sim s / wall s: 1 kHz physics + FC + telemetry, no pacing",
    )
