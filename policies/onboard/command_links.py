"""The onboard program's client of the FC on the command link, whatever its protocol: what the program asks
of one (`OnboardLink`), and the table of clients by protocol name (the names of
`hil.link.protocols.PROTOCOLS`). Adding a protocol's client: a class that has `OnboardLink`'s members
(subclassing `CommandLink` gives the lockstep's holding and answering), and one `register_command_link`
call (docs/extending.md)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from hil.link.clock import Clock
from hil.link.transport import Transport
from policies.onboard.command_link import CommandLink
from policies.onboard.dji_command_link import DjiCommandLink


class FcStatusView(Protocol):
    """The FC's status as the link last heard it."""

    @property
    def armed(self) -> bool: ...

    @property
    def offboard(self) -> bool: ...

    @property
    def holding(self) -> bool: ...


class AckView(Protocol):
    """The FC's answer to a request."""

    @property
    def accepted(self) -> bool: ...


class OnboardLink(Protocol):
    """The FC as the onboard program sees it over one protocol."""

    protocol: str  # the protocol's name
    codec: Any  # the protocol's codec (``stats.as_dict()``)
    status: FcStatusView | None  # None: the FC not heard yet
    #: the FC's latest answer to each request, by the MAVLink command it stands for (MAV_CMD_DO_SET_MODE
    #: for `request_offboard` and `request_hold`, MAV_CMD_COMPONENT_ARM_DISARM for `request_arm`)
    acks: dict[int, AckView]
    status_texts: list[str]
    foreign: dict[str, int]  # messages ignored for not coming from the FC, by kind
    mocap_announced: int | None  # lockstep: the harness's mocap byte total (mod 2^31) as last told
    lockstep: bool  # set when the program runs on lockstep ticks

    @property
    def transport(self) -> Transport: ...

    def read(self, timeout_s: float = 0.0) -> int:
        """Act on what arrived (waiting up to ``timeout_s``); how many messages."""

    #: lockstep: whether messages read are still waiting for their tick
    backlogged: bool

    def take_ticks(self) -> list[float]:
        """The lockstep tick times (s) received since the last call."""

    def read_ticks(self) -> list[float]:
        """`read`, then `take_ticks` (the lockstep's read a tick)."""

    def answer_tick(self, tick_s: float) -> None:
        """Lockstep: done with the tick at ``tick_s`` (s)."""

    def heartbeat_age_s(self, now_s: float) -> float:
        """Seconds since the FC was last heard (inf: never)."""

    def send_heartbeat(self) -> None: ...

    def send_attitude_target(self, roll_rad: float, pitch_rad: float, yaw_rad: float,
                             thrust_fraction: float) -> None: ...

    def request_heartbeat(self) -> None: ...

    def request_offboard(self) -> None: ...

    def request_arm(self) -> None: ...

    def request_hold(self) -> None: ...

    def close(self) -> None: ...


#: (command transport, the program's clock) -> the program's client of the FC
LinkFactory = Callable[[Transport, Clock], OnboardLink]

#: protocol name -> the factory of the program's client of it; `register_command_link` adds one
COMMAND_LINKS: dict[str, LinkFactory] = {}


def register_command_link(name: str, factory: LinkFactory) -> None:
    """Fly over protocol ``name`` (a name of `hil.link.protocols.PROTOCOLS`) with ``factory``'s clients;
    ValueError if one is registered under that name already."""
    if name in COMMAND_LINKS:
        raise ValueError(f"an onboard command link for {name!r} is registered already")
    COMMAND_LINKS[name] = factory


register_command_link(CommandLink.protocol, CommandLink)
register_command_link(DjiCommandLink.protocol, DjiCommandLink)
