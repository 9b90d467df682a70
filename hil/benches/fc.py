"""FC figures: setpoint latency over a pty at 921600 baud beside the frame's wire time, and the
emulator's real-time factor (1 kHz physics + FC + telemetry, as fast as it runs)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterable

from emulator.fc import EmulatedVehicle, MavlinkServer, RealtimeRunner
from emulator.profile import GRAVITY_M_S2, load_profile
from hil.benches import BenchRow
from hil.link import MemoryTransport, PtyTransport, SerialTransport, SimClock, WallClock
from hil.link.mavlink import MavlinkCodec, quat_from_euler
from hil.link.uart import UartModel

BAUD = 921600


def _setpoint_latency(n: int) -> tuple[float, int]:
    """Median seconds from the onboard side's write of SET_ATTITUDE_TARGET to the FC applying it, and the
    frame's length (bytes). The FC runs its real-time loop in a thread, the writer in this one."""
    profile = load_profile("n3_tx2")
    clock = WallClock()
    fc_link = PtyTransport.create(BAUD)
    onboard_link = SerialTransport(fc_link.endpoint, BAUD)
    vehicle = EmulatedVehicle(profile)
    server = MavlinkServer(vehicle, MavlinkCodec(fc_link, clock, 1, 1))
    applied: dict[int, float] = {}
    server.on_setpoint = lambda msg, now: applied.setdefault(msg.time_boot_ms, time.perf_counter())
    runner = RealtimeRunner(vehicle, [server], clock=clock, wait_fds=[fc_link.fileno()]).start()
    onboard = MavlinkCodec(onboard_link, clock, 255, 190)
    q = list(quat_from_euler(0.0, 0.0, 0.0))
    thrust = 0.3 * profile.mass_kg * GRAVITY_M_S2 / profile.n3_full_thrust_n
    sent: dict[int, float] = {}
    frame_len = 0
    try:
        for i in range(1, n + 1):
            msg = onboard.mav.set_attitude_target_encode(i, 1, 1, 7, q, 0.0, 0.0, 0.0, thrust)
            sent[i] = time.perf_counter()
            frame_len = len(onboard.send(msg))
            onboard.receive(0.0)  # keep the telemetry flowing
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
    median_s, frame_len = _setpoint_latency(50 if quick else 300)
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
