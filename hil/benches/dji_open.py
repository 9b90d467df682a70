"""DJI OPEN-protocol figures: an Onboard SDK setpoint's latency over a pty at 230400 and 921600 baud beside
its wire time, and the full stack's real-time factor on the OPEN protocol beside MAVLink's, in one run."""

from __future__ import annotations

import statistics
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path

from emulator.loops.realtime_runner import Pollable
from emulator.servers.dji_open_server import DjiOpenServer
from emulator.vehicle import EmulatedVehicle
from hil.benches import BenchRow
from hil.benches.fc import setpoint_latency
from hil.benches.runner import RTF_RUNS, RTF_SCENARIO
from hil.link import WallClock
from hil.link import dji_open as dj
from hil.link.transport import Transport
from hil.link.uart import UartModel
from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios

BAUDS = (230400, 921600)
ACTIVATION = b"\xee\x52\x10\x00" + bytes(4) + b"\x00\x0a\x01\x03" + bytes(32)


class _OpenRig:
    """The OPEN-protocol setpoint (0x01 0x03), its number as the yaw (deg), after an activation."""

    def __init__(self) -> None:
        self._codec: dj.OpenCodec | None = None

    def serve(self, vehicle: EmulatedVehicle, link: Transport, clock: WallClock,
              applied: Callable[[int], None]) -> Pollable:
        server = DjiOpenServer(vehicle, dj.OpenCodec(link, clock))
        server.on_setpoint = lambda flag, roll, pitch, thrust, yaw, now: applied(round(yaw))
        return server

    def write(self, link: Transport, clock: WallClock, i: int, thrust_fraction: float) -> int:
        if self._codec is None or self._codec.transport is not link:
            self._codec = dj.OpenCodec(link, clock)
            self._codec.send_command(dj.SET_ACTIVATION, dj.CMD_ACTIVATE, ACTIVATION)
        codec = self._codec
        payload = dj.setpoint_payload(dj.ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, 100.0 * thrust_fraction,
                                      float(i % 360))
        frame = codec.pack_command(dj.SET_CONTROL, dj.CMD_SETPOINT, payload)
        link.send(frame)
        codec.receive(0.0)  # keep the flight data flowing
        return len(frame)


def _rtf(protocol: str, out: Path, k: int) -> dict:
    s = loads_scenarios(RTF_SCENARIO)[0]
    s = replace(s, links=replace(s.links, command=replace(s.links.command, protocol=protocol)))
    r = run_scenario(s, out / f"{protocol}_{k}", RunOptions(in_process=False))
    if not r.passed:
        failed = "; ".join(f"{c.name}: {c.observed}" for c in r.failed_checks)
        raise RuntimeError(f"bench scenario failed its checks ({protocol}): {failed}")
    return r.summary


def collect(quick: bool) -> Iterable[BenchRow]:
    for baud in BAUDS:
        median_s, frame_len = setpoint_latency(50 if quick else 300, baud, _OpenRig())
        yield BenchRow(f"osdk_setpoint_latency_us_{baud}", median_s * 1e6, "us",
                       f"OPEN-protocol setpoint (0x01 0x03) write -> FC applies it, pty {baud} baud, median")
        yield BenchRow(f"osdk_setpoint_wire_us_{baud}", UartModel(baud).wire_time_s(frame_len) * 1e6, "us",
                       f"that frame ({frame_len} bytes) on a {baud} baud UART, 10 bits a byte")
    runs: dict[str, list[float]] = {"mavlink": [], "dji_open": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(RTF_RUNS):  # the two protocols taken in turn: a busy host weighs on both alike
            for protocol in runs:
                runs[protocol].append(_rtf(protocol, Path(tmp), k)["real_time_factor"])
    med = {p: statistics.median(v) for p, v in runs.items()}
    # (full_stack_rtf itself is the runner group's; this group's MAVLink runs are paired with its own)
    for p, name in (("mavlink", "full_stack_rtf_paired"), ("dji_open", "full_stack_rtf_dji_open")):
        spread = ", ".join(f"{x:.1f}" for x in sorted(runs[p]))
        yield BenchRow(name, med[p], "x real time",
                       f"60 deg gap over ptys in lockstep, command link {p}, median of {RTF_RUNS} "
                       f"({spread}), the two protocols in turn")
    yield BenchRow("dji_open_rtf_ratio", med["dji_open"] / med["mavlink"], "x",
                   "full_stack_rtf_dji_open / full_stack_rtf_paired, one run (asked: >= 0.9)")
