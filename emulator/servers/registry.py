"""The FC's server on the command link, whatever its protocol: what the emulator's loops and the harness
ask of one (`FcServer`), and the table of servers by protocol name (the names of
`hil.link.protocols.PROTOCOLS`). Adding a protocol's server: a class that has `FcServer`'s members, and
one `register_server` call (docs/extending.md)."""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any, Protocol

from emulator.fc.modes import FcState
from emulator.params import Parameters
from emulator.servers.dji_open_server import DjiOpenServer, DjiServerConfig
from emulator.servers.mavlink_server import MavlinkServer, ServerConfig
from emulator.vehicle import EmulatedVehicle
from hil.link.clock import Clock
from hil.link.dji_open import OpenCodec
from hil.link.mavlink import SIGNING_EPOCH_UNIX_S, MavlinkCodec, mav
from hil.link.tlog import TlogWriter
from hil.link.transport import Transport


class ServerCounts(Protocol):
    """A server's counters: the setpoints it applied, and all of them by name."""

    setpoints_applied: int

    def as_dict(self) -> dict[str, int]: ...


class FcServer(Protocol):
    """One vehicle's FC served over one codec: polled by the loop, its parameters set by the harness."""

    vehicle: EmulatedVehicle
    codec: Any  # the protocol's codec (``stats.as_dict()``, ``transport``)
    params: Parameters
    stats: ServerCounts

    @property
    def state(self) -> FcState: ...

    def poll(self, now_s: float) -> None:
        """Parse and act on what arrived, then send what is due at ``now_s`` (s)."""

    def statustext(self, severity: int, text: str, now_s: float, key: str | None = None) -> bool:
        """Tell the peer a text (MAVLink severity), as the protocol can; True if told."""


@dataclass(frozen=True)
class ServerOptions:
    """What a server factory may use besides the vehicle, the link and the clock (each protocol takes what
    it has a use for)."""

    system_id: int = 1  # MAVLink: the FC's system id
    raw_ids: Collection[int] = ()  # MAVLink: message ids handed to the server as frames
    tlog: TlogWriter | None = None  # every good frame, both directions
    signing_key: bytes | None = None  # MAVLink signing
    signing_epoch_unix_s: float = SIGNING_EPOCH_UNIX_S
    server_config: ServerConfig | None = None  # the MAVLink server's
    dji_config: DjiServerConfig | None = None  # the OPEN-protocol server's


#: (vehicle, command link, clock, options) -> the FC's server on that link
ServerFactory = Callable[[EmulatedVehicle, Transport, Clock, ServerOptions], FcServer]


def _mavlink(vehicle: EmulatedVehicle, link: Transport, clock: Clock, o: ServerOptions) -> MavlinkServer:
    codec = MavlinkCodec(link, clock, o.system_id, mav.MAV_COMP_ID_AUTOPILOT1, signing_key=o.signing_key,
                         recorder=o.tlog, raw_ids=o.raw_ids, signing_epoch_unix_s=o.signing_epoch_unix_s)
    return MavlinkServer(vehicle, codec, o.server_config)


def _dji_open(vehicle: EmulatedVehicle, link: Transport, clock: Clock, o: ServerOptions) -> DjiOpenServer:
    return DjiOpenServer(vehicle, OpenCodec(link, clock, recorder=o.tlog), o.dji_config)


#: protocol name -> the factory of its FC server; `register_server` adds one
FC_SERVERS: dict[str, ServerFactory] = {}


def register_server(name: str, factory: ServerFactory) -> None:
    """Serve protocol ``name`` (a name of `hil.link.protocols.PROTOCOLS`) with ``factory``'s servers;
    ValueError if a server is registered under that name already."""
    if name in FC_SERVERS:
        raise ValueError(f"an FC server for {name!r} is registered already")
    FC_SERVERS[name] = factory


def make_server(name: str, vehicle: EmulatedVehicle, link: Transport, clock: Clock,
                options: ServerOptions) -> FcServer:
    """The FC server of protocol ``name``; ValueError naming the served ones otherwise."""
    factory = FC_SERVERS.get(name)
    if factory is None:
        raise ValueError(f"command-link protocol must be one of {', '.join(FC_SERVERS)}, got {name!r}")
    return factory(vehicle, link, clock, options)


register_server("mavlink", _mavlink)
register_server("dji_open", _dji_open)
