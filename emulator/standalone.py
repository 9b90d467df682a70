"""The standalone FC (`hil fc`) assembled: its links opened from their specs, the emulator behind them, its
built-in gaps, and what its real-time loop polls besides the vehicle: the FC's server, a watch of the gap
(crossings and collisions told as status texts), the mocap-over-UWB link fed with the true poses and the
streams' watch; its exit summary. `hil fc` only parses its options and prints."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from emulator.assembly import Emulator, assemble, warm_up
from emulator.esc.bus import Bridge, EscBusConfig, EscBusStepper, attach, parse_bus_spec
from emulator.loops.realtime_runner import RealtimeRunner, WireWatch
from emulator.mocap import MocapConfig
from emulator.mocap_link import MocapLinkServer
from emulator.profile import VehicleProfile
from emulator.servers.registry import FcServer, server_config
from emulator.uwb import UwbConfig
from emulator.vehicle import EmulatedVehicle, resting_state
from emulator.world import CrossingTracker, Gap, World
from hil.link.clock import WallClock
from hil.link.endpoint import open_link, parse_endpoint
from hil.link.mavlink import mav
from hil.link.tlog import TlogWriter

#: built-in gaps and where the vehicle starts (x, y on the ground, m): the paper's test case (centre
#: (0, 0.5, 2.1) m, rolled -60 deg, start (-2, -1)), or a level gap at (0, 0, 1.5) m
GAPS: dict[str, tuple[Gap, tuple[float, float]]] = {
    "paper": (Gap(centre_m=(0.0, 0.5, 2.1), roll_rad=math.radians(-60.0)), (-2.0, -1.0)),
    "level": (Gap(), (-2.0, 0.0)),
}
GAP_SAMPLE_S = 0.01  # collision and crossing checks at 100 Hz


class MocapPoll:
    """Feeds the true vehicle and gap poses to the mocap-over-UWB link when it has something due."""

    def __init__(self, vehicle: EmulatedVehicle, server: MocapLinkServer, gap: Gap | None) -> None:
        self.vehicle, self.server, self.gap = vehicle, server, gap

    def poll(self, now_s: float) -> None:
        if now_s >= self.server.next_event_s():
            self.server.update(now_s, self.vehicle.state, self.gap)


class GapWatch:
    """Samples the vehicle against the gap world and reports crossings and collisions as status texts."""

    def __init__(self, vehicle: EmulatedVehicle, world: World, server: FcServer) -> None:
        self.vehicle, self.server = vehicle, server
        self.tracker = CrossingTracker(world)
        self._next_s = 0.0
        self._reported_collision = False

    def poll(self, now_s: float) -> None:
        if now_s < self._next_s:
            return
        self._next_s = now_s + GAP_SAMPLE_S
        if self.vehicle.fc.landed:  # resting on the ground is no collision
            return
        s = self.vehicle.state
        crossing = self.tracker.update(s.time_s + 1e-9 * self.tracker.samples, s.pos_m, s.quat_wxyz)
        if crossing is not None:
            where = "through the gap" if crossing.through_opening else "outside the gap"
            self.server.statustext(mav.MAV_SEVERITY_INFO, f"Crossed the wall {where}", now_s, key="crossing")
        hit = self.tracker.first_collision
        if hit is not None and not self._reported_collision:
            self._reported_collision = True
            self.server.statustext(mav.MAV_SEVERITY_CRITICAL, f"Collision: {hit.obstacle}", now_s)


def loop_links(emu: Emulator, gap: Gap | None) -> list:
    """What the standalone FC's real-time loop polls: the FC's server, the gap's watch (with a world), the
    mocap link (with one)."""
    links: list = [emu.server]
    if emu.world is not None:
        links.append(GapWatch(emu.vehicle, emu.world, emu.server))
    if emu.mocap is not None:
        links.append(MocapPoll(emu.vehicle, emu.mocap, gap))
    return links


class SetupError(ValueError):
    """The standalone FC could not be set up: ``part`` names what refused (``command_link``,
    ``mocap_link``, ``tlog``, ``server``, ``params``, ``esc_bus``), the message says why."""

    def __init__(self, part: str, reason: str) -> None:
        super().__init__(reason)
        self.part = part


@dataclass(frozen=True)
class StandaloneConfig:
    """What the standalone FC is asked to be (`hil fc`'s options, checked there)."""

    profile: VehicleProfile
    command_link: str = "pty"  # an endpoint spec (`hil.link.endpoint`)
    mocap_link: str | None = "pty"  # an endpoint spec; None: no mocap link
    backend: str = "native"
    gap: str | None = "paper"  # a name of `GAPS`; None: no gap to watch
    protocol: str = "mavlink"  # a name of `emulator.servers.registry.FC_SERVERS`
    #: settings of the protocol's server by field name (`server_config`: each protocol takes its own)
    protocol_settings: Mapping[str, Any] = field(default_factory=dict)
    #: FC parameters set before the loop starts (their file's values with the options over them)
    params: Mapping[str, float | int] = field(default_factory=dict)
    param_file: str | None = None  # where MAV_CMD_PREFLIGHT_STORAGE reads and writes the parameters
    #: the telemetry's data-rate budget on the command link (bytes/s; 0: half a serial line): the
    #: parameter MAV_0_RATE where the server has MAVLink telemetry, else its own setting; None: its default
    link_budget_bytes_s: float | None = None
    signing_key: bytes | None = None
    system_id: int = 1
    seed: int = 0  # of the mocap noise, the radio and the ESC bus
    duration_s: float | None = None  # None: until stopped
    tlog_path: str | None = None  # every frame of the command link, both ways
    mocap: MocapConfig = field(default_factory=MocapConfig)
    uwb: UwbConfig = field(default_factory=UwbConfig)
    esc_bus: str | None = None  # a bus spec (`emulator.esc.bus.parse_bus_spec`); None: no bus
    external_esc: tuple[int, ...] = ()  # ESC nodes served by other nodes on the bus


class StandaloneFc:
    """The standalone FC set up: its links open, the emulator assembled behind them, its real-time loop
    ready (`run`); `close` closes what it opened. SetupError (nothing left open) if a part refuses."""

    def __init__(self, config: StandaloneConfig) -> None:
        self.config = config
        self.esc: EscBusStepper | None = None
        with ExitStack() as undo:
            self._setup(config, undo)
            self._close = undo.pop_all()

    def _setup(self, c: StandaloneConfig, undo: ExitStack) -> None:
        try:
            spec = parse_endpoint(c.command_link)
            # a serial line carries baud / 10 bytes a second: the FC writes at that pace, within its budget
            link_baud = spec.baud if spec.kind == "serial" else None
            self.link = open_link(spec, "fc", uart_baud=link_baud)
        except (ValueError, OSError) as exc:
            raise SetupError("command_link", str(exc)) from None
        undo.callback(self.link.close)
        self.mocap_link = None
        if c.mocap_link is not None:
            try:
                self.mocap_link = open_link(c.mocap_link, "fc")
            except (ValueError, OSError) as exc:
                raise SetupError("mocap_link", str(exc)) from None
            undo.callback(self.mocap_link.close)
        tlog = None
        if c.tlog_path is not None:
            try:
                tlog = TlogWriter(c.tlog_path)
            except OSError as exc:
                raise SetupError("tlog", str(exc)) from None
            undo.callback(tlog.close)
        gap, start_xy = GAPS.get(c.gap or "", (None, (0.0, 0.0)))
        self.gap = gap
        start = resting_state(c.profile, *start_xy, yaw_rad=0.0)  # facing world +x, the paper's reference yaw
        warm_up(c.profile)  # before the clock starts
        if c.esc_bus is not None:
            import dronecan  # noqa: F401 (its message types load here, not on the clock)
        self.clock, epoch_unix_s = WallClock(), time.time()  # clock zero in Unix time, for tlog and signing
        if tlog is not None:
            tlog.epoch_unix_s = epoch_unix_s
        settings = {"param_file": c.param_file, "link_baud": link_baud, **c.protocol_settings}
        if c.link_budget_bytes_s is not None:
            settings["budget_bytes_s"] = c.link_budget_bytes_s
        try:
            emu = assemble(
                c.profile, self.link, self.clock, initial_state=start, backend=c.backend, gap=gap,
                mocap_link=self.mocap_link, mocap_rng=np.random.default_rng(c.seed), mocap_config=c.mocap,
                uwb_config=c.uwb, system_id=c.system_id, tlog=tlog, signing_key=c.signing_key,
                signing_epoch_unix_s=epoch_unix_s, protocol=c.protocol,
                protocol_config=server_config(c.protocol, **settings),
            )
        except ValueError as exc:
            raise SetupError("server", str(exc)) from None
        self.emulator = emu
        params = dict(c.params)
        if c.link_budget_bytes_s is not None and emu.server.params.streams is not None:
            params["MAV_0_RATE"] = c.link_budget_bytes_s  # (the servers with MAVLink telemetry keep it there)
        try:
            emu.server.params.set_many(params)
        except ValueError as exc:
            raise SetupError("params", str(exc)) from None
        if c.esc_bus is not None:
            try:
                self.esc = self._esc_bus(c)
            except (ValueError, OSError) as exc:
                raise SetupError("esc_bus", str(exc)) from None
            undo.callback(self.esc.esc.close)
        self.wire = WireWatch(emu.server, emu.mocap)
        fds = [self.link.fileno()] if _has_fileno(self.link) else []
        self.runner = RealtimeRunner(emu.vehicle, [*loop_links(emu, gap), self.wire], clock=self.clock,
                                     duration_s=c.duration_s, wait_fds=fds)

    def _esc_bus(self, c: StandaloneConfig) -> EscBusStepper:
        """The ESC bus ``c.esc_bus`` names, with the FC's ESC parameters; ValueError or OSError say
        why not."""
        spec = parse_bus_spec(c.esc_bus or "")
        if spec == "sim" and c.external_esc:
            raise ValueError("--external-esc needs a bus other processes reach (mcast, udp_multicast, "
                             "socketcan)")
        emu = self.emulator
        config = EscBusConfig(external=tuple(c.external_esc), **emu.server.params.esc_settings())
        bridge = None if spec == "sim" else Bridge(spec, config.bitrate_bps)
        return attach(emu.vehicle, emu.server, config, np.random.default_rng(c.seed), bridge)

    def endpoints(self) -> dict[str, str]:
        """Where to reach it: the command link (and its protocol), the mocap link (with one)."""
        out = {"command_link": self.link.endpoint, "protocol": self.config.protocol}
        if self.emulator.mocap is not None and self.mocap_link is not None:
            out["mocap_link"] = self.mocap_link.endpoint
        return out

    def run(self) -> None:
        """The real-time loop, until its duration has passed or `RealtimeRunner.stop` is called."""
        self.runner.run()

    def summary(self) -> dict[str, Any]:
        """What the FC did and what its links carried, for the exit line."""
        emu, link, now_s = self.emulator, self.link, self.clock.now_s()
        count_drops = getattr(link, "count_drops", None)  # (UDP: the kernel's drops until now)
        if count_drops is not None:
            count_drops()
        vehicle, server = emu.vehicle, emu.server
        out: dict[str, Any] = {
            "sim_time_s": round(vehicle.time_s, 3),
            "state": vehicle.fc.state.value,
            "events": [
                {"time_s": round(e.time_s, 4), "to": e.to_state.value, "reason": e.reason}
                for e in vehicle.fc.events
            ],
            "link": emu.codec.stats.as_dict(),
            "transport": asdict(link.stats),
            "server": server.stats.as_dict(),
            "realtime": {"loop": self.runner.pacing.as_dict(), **self.wire.as_dict(),
                         "serial": _serial_stats(link)},
        }
        budget = getattr(server, "budget", None)
        if budget is not None:
            out["link_budget"] = budget.summary(link, now_s)
        if self.esc is not None:
            out["esc_bus"] = self.esc.summary(now_s)
        if emu.mocap is not None:
            st = emu.mocap.stats
            out["mocap"] = {
                "frames_written": st.frames_written,
                "radio_sent": st.radio.sent,
                "radio_delivered": st.radio.delivered,
                "radio_lost": st.radio.lost,
            }
        return out

    def close(self) -> None:
        """Close the ESC bus, the capture and the links (in that order)."""
        self._close.close()


def _serial_stats(link: object) -> dict[str, int] | None:
    """A serial link's unplugs and replugs (None for other links)."""
    link = getattr(link, "inner", link)  # (under its UART pacing)
    if not hasattr(link, "disconnects"):
        return None
    return {"disconnects": link.disconnects, "reconnects": link.reconnects}  # type: ignore[attr-defined]


def _has_fileno(link: object) -> bool:
    try:
        link.fileno()  # type: ignore[attr-defined]
    except (NotImplementedError, ValueError, OSError):
        return False
    return True
