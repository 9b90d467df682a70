"""ESC bus figures: frames per second through the DroneCAN bus model, the FC's CPU time per simulated
second with its motors directly, on the bus model and on the bus bridged to a real one, and the full
stack's real-time factor with the motors on the bus beside the one without it, measured in the same run."""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from emulator.esc.bus import Bridge, EscBus, EscBusConfig, attach
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.servers.mavlink_server import MavlinkServer
from emulator.vehicle import EmulatedVehicle
from hil.benches import BenchRow, time_per_call
from hil.benches.runner import RTF_SCENARIO
from hil.link import MemoryTransport, SimClock
from hil.link.mavlink import PX4_MAIN_OFFBOARD, MavlinkCodec, mav, quat_from_euler
from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios
from hil.scenario.schema import EscBusSpec

RUNS = 3  # runs of each stack; the figure is their median
#: the FC's motors: directly, behind the bus model, behind the model bridged to a real bus (a loopback
#: multicast group of this bench's own: the frames are dronecan's bytes, sent and read back)
MOTOR_PATHS = ("direct", "sim", "mcast")


def fc_cpu_s_per_sim_s(path: str, sim_s: float) -> float:
    """The FC's CPU time (s) per simulated second, hovering in OFFBOARD on 50 Hz attitude setpoints in
    lockstep (1 kHz physics, the FC's loop at 400 Hz), with its motors on ``path`` (`MOTOR_PATHS`)."""
    profile = load_profile("n3_tx2")
    clock = SimClock()
    fc_end, gcs_end = MemoryTransport.pair()
    vehicle = EmulatedVehicle(profile)
    server = MavlinkServer(vehicle, MavlinkCodec(fc_end, clock, 1, 1))
    client = MavlinkCodec(gcs_end, clock, 255, 190)
    stepper = None
    if path != "direct":
        bridge = None if path == "sim" else Bridge(f"mcast:{os.getpid() % 200 + 50}", 1_000_000)
        stepper = attach(vehicle, server, EscBusConfig(), np.random.default_rng(0), bridge)
    hover = profile.mass_kg * GRAVITY_M_S2 / profile.n3_full_thrust_n
    q = list(quat_from_euler(0.0, 0.0, 0.0))

    def fly(seconds: float) -> None:
        for _ in range(round(seconds / vehicle.dt_s)):
            now = round(clock.now_s() + vehicle.dt_s, 9)
            clock.advance_to(now)
            if round(now * 1000) % 20 == 0:
                client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, 1.05 * hover))
            server.poll(now)
            vehicle.step_to(now)
            client.receive()

    try:
        arm = mav.MAV_CMD_COMPONENT_ARM_DISARM
        client.send(client.mav.command_long_encode(1, 1, arm, 0, 1, 0, 0, 0, 0, 0, 0))
        fly(0.3)
        client.send(client.mav.command_long_encode(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 129, PX4_MAIN_OFFBOARD,
                                                   0, 0, 0, 0, 0))
        fly(0.5)  # (in the air; every kernel compiled)
        start = time.process_time()
        fly(sim_s)
        return (time.process_time() - start) / sim_s
    finally:
        if stepper is not None:
            stepper.esc.close()


def collect(quick: bool) -> Iterator[BenchRow]:
    esc = EscBus(EscBusConfig(), np.random.default_rng(0), 0.0, lambda *a: None, lambda *a: None)
    throttles = np.array([0.1, 0.2, 0.3, 0.4])
    clock = [0.0]

    def one_frame() -> None:  # the FC's node to the four ESC nodes, as in flight
        clock[0] += 1e-3
        esc.fc_node.send_command(throttles, clock[0])
        esc.bus.advance_to(clock[0] + 1e-3)

    frames0 = esc.bus.stats.frames
    per_frame = time_per_call(one_frame, 0.2 if quick else 1.0)
    if esc.bus.stats.frames == frames0 or not np.allclose(esc.throttle, throttles, atol=1e-3):
        raise RuntimeError("bench: the RawCommands did not reach the ESC nodes")
    yield BenchRow("can_frames_per_s", 1.0 / per_frame, "frames/s",
                   "RawCommand (one frame) from the FC's node to its four ESC nodes through the bus model")
    cpu: dict[str, list[float]] = {p: [] for p in MOTOR_PATHS}
    for _ in range(1 if quick else 5):  # alternated: a busy spell of the machine meets each alike
        for p in MOTOR_PATHS:
            cpu[p].append(fc_cpu_s_per_sim_s(p, 1.0 if quick else 3.0))
    cpu_med = {p: float(np.median(v)) * 1e3 for p, v in cpu.items()}
    for p in MOTOR_PATHS:
        spread = ", ".join(f"{x * 1e3:.1f}" for x in cpu[p])
        yield BenchRow(f"fc_cpu_ms_per_sim_s_{p}", cpu_med[p], "ms", f"the FC hovering in lockstep, motors "
                       f"{p}: CPU time per simulated second, median of alternated runs ({spread})")
    yield BenchRow("esc_bus_bridge_share_ms_per_sim_s", cpu_med["mcast"] - cpu_med["sim"], "ms",
                   "what bridging the bus model to a real bus (dronecan's bytes, loopback multicast) adds")
    base = loads_scenarios(RTF_SCENARIO)[0]
    on_bus = replace(base, links=replace(base.links, esc_bus=EscBusSpec()))
    runs = 1 if quick else RUNS
    rtf: dict[str, list[float]] = {"full_stack_rtf": [], "full_stack_rtf_esc_bus": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(runs):  # alternated, so that a busy spell of the machine meets both alike
            for name, s in (("full_stack_rtf", base), ("full_stack_rtf_esc_bus", on_bus)):
                r = run_scenario(s, Path(tmp) / f"{name}_{k}", RunOptions())
                if not r.passed:
                    failed = "; ".join(f"{c.name}: {c.observed}" for c in r.failed_checks)
                    raise RuntimeError(f"bench scenario failed its checks ({name}): {failed}")
                rtf[name].append(r.summary["real_time_factor"])
    med = {name: float(np.median(v)) for name, v in rtf.items()}
    for name, row in (("full_stack_rtf", "full_stack_rtf_beside_esc_bus"),
                      ("full_stack_rtf_esc_bus", "full_stack_rtf_esc_bus")):
        spread = ", ".join(f"{x:.1f}" for x in rtf[name])
        yield BenchRow(row, med[name], "x real time",
                       f"60 deg gap over ptys, lockstep, median of {runs} ({spread})")
    yield BenchRow("esc_bus_rtf_ratio", med["full_stack_rtf_esc_bus"] / med["full_stack_rtf"], "x",
                   "full stack with the motors on the DroneCAN bus / without it, same run")
