"""The FC's server on the command link, whatever its protocol: what the emulator's loops and the harness
ask of one (`FcServer`), and the table of servers by protocol name (the names of
`hil.link.protocols.PROTOCOLS`). Adding a protocol's server: a class that has `FcServer`'s members, and
one `register_server` call (docs/extending.md)."""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass, fields
from typing import Any, Protocol

from emulator.fc.modes import FcState
from emulator.params import Parameters
from emulator.servers.dji_open_server import DjiOpenServer, DjiServerConfig
from emulator.servers.dji_open_server import setpoint_kernel as dji_setpoint_kernel
from emulator.servers.mavlink_server import MavlinkServer, ServerConfig
from emulator.servers.mavlink_server import setpoint_kernel as mavlink_setpoint_kernel
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

    #: told what the server could not tell its peer (a text, for whoever runs the FC: a rate the link's
    #: budget capped where the protocol's answer has no room for a reason); None: kept to itself
    on_untold: Callable[[str], None] | None

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
    #: the server's own settings, of the type its protocol registers (`ServerEntry.config_type`, built by
    #: `server_config`); None: its defaults
    protocol_config: object | None = None


#: (vehicle, command link, clock, options) -> the FC's server on that link
ServerFactory = Callable[[EmulatedVehicle, Transport, Clock, ServerOptions], FcServer]


@dataclass(frozen=True)
class ServerEntry:
    """One protocol's FC server: its factory, the type of its settings (None: it takes none), and what
    compiles (or loads) its servers' kernels before a wall clock starts (None: none)."""

    factory: ServerFactory
    config_type: type | None = None
    warm_up: Callable[[], object] | None = None


def _mavlink(vehicle: EmulatedVehicle, link: Transport, clock: Clock, o: ServerOptions) -> MavlinkServer:
    codec = MavlinkCodec(link, clock, o.system_id, mav.MAV_COMP_ID_AUTOPILOT1, signing_key=o.signing_key,
                         recorder=o.tlog, raw_ids=o.raw_ids, signing_epoch_unix_s=o.signing_epoch_unix_s)
    return MavlinkServer(vehicle, codec, o.protocol_config)  # type: ignore[arg-type]


def _dji_open(vehicle: EmulatedVehicle, link: Transport, clock: Clock, o: ServerOptions) -> DjiOpenServer:
    if o.signing_key is not None:
        raise ValueError("a signing key signs MAVLink: the OPEN protocol has no signing")
    return DjiOpenServer(vehicle, OpenCodec(link, clock, recorder=o.tlog), o.protocol_config)  # type: ignore[arg-type]


#: protocol name -> its FC server; `register_server` adds one
FC_SERVERS: dict[str, ServerEntry] = {}


def register_server(name: str, factory: ServerFactory, config_type: type | None = None,
                    warm_up: Callable[[], object] | None = None) -> None:
    """Serve protocol ``name`` (a name of `hil.link.protocols.PROTOCOLS`) with ``factory``'s servers, their
    settings of ``config_type`` (a dataclass; None: they take none); ``warm_up``: compiles (or loads) the
    kernels a server compiles at construction (`emulator.assembly.warm_up` calls it, so that a real-time
    run's clock does not pay for them). ValueError if a server is registered under that name already."""
    if name in FC_SERVERS:
        raise ValueError(f"an FC server for {name!r} is registered already")
    FC_SERVERS[name] = ServerEntry(factory, config_type, warm_up)


def _entry(name: str) -> ServerEntry:
    entry = FC_SERVERS.get(name)
    if entry is None:
        raise ValueError(f"command-link protocol must be one of {', '.join(FC_SERVERS)}, got {name!r}")
    return entry


def server_config(name: str, **settings: Any) -> object | None:
    """The settings of protocol ``name``'s server from those of ``settings`` its config type has a field
    for (each protocol takes what it has a use for), the rest its defaults; None for a server that takes
    none. ValueError for an unknown protocol or a value its config refuses."""
    config_type = _entry(name).config_type
    if config_type is None:
        return None
    own = {f.name for f in fields(config_type)}
    return config_type(**{k: v for k, v in settings.items() if k in own})


def make_server(name: str, vehicle: EmulatedVehicle, link: Transport, clock: Clock,
                options: ServerOptions) -> FcServer:
    """The FC server of protocol ``name``; ValueError naming the served ones otherwise, or when
    ``options.protocol_config`` is not of the type that protocol's server takes."""
    entry = _entry(name)
    config = options.protocol_config
    if config is not None and (entry.config_type is None or not isinstance(config, entry.config_type)):
        wanted = "no settings" if entry.config_type is None else f"a {entry.config_type.__name__}"
        raise ValueError(f"the {name} server takes {wanted}, got a {type(config).__name__}")
    return entry.factory(vehicle, link, clock, options)


register_server("mavlink", _mavlink, ServerConfig, mavlink_setpoint_kernel)
register_server("dji_open", _dji_open, DjiServerConfig, dji_setpoint_kernel)
