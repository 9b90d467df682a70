"""The command link's protocols, by name: what the link layer knows of each (its codec, its lockstep
framing, its longest frame, how a captured frame is found and read). The scenario schema, the CLIs'
choices, the .tlog reader and `hil decode` read this table; the emulator's FC servers
(`emulator.servers.registry`) and the onboard program's links (`policies.onboard.command_links`) have their
own tables under the same names. Adding a protocol: its codec module here, one `register_protocol`
call (docs/extending.md)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hil.link import dji_open, mavlink
from hil.link.lockstep import Framing, dji_framing, mavlink_framing


@dataclass(frozen=True)
class Decoded:
    """One captured frame read: protocol, type name, sender ('fc' or 'peer'), one line and the fields."""

    protocol: str
    type: str
    sender: str
    text: str
    fields: dict[str, Any]


@dataclass(frozen=True)
class LinkProtocol:
    """One command-link protocol as the link layer knows it."""

    name: str
    codec: Callable[..., Any]  # (transport, clock, ...protocol's own options) -> the protocol's codec
    framing: Callable[[int, int], Framing]  # (FC system id, FC component id) -> the lockstep's framing
    max_frame_bytes: int  # the longest frame (bytes)
    start_bytes: frozenset[int]  # the first byte of each of its frames
    frame_at: Callable[[bytes, int], bytes | None]  # the whole, CRC-good frame at data[j], or None
    describe: Callable[[bytes], tuple[str, str, str, dict[str, Any]]]  # frame -> type, sender, text, fields


#: name -> protocol; `register_protocol` adds one
PROTOCOLS: dict[str, LinkProtocol] = {}
_BY_START: dict[int, LinkProtocol] = {}  # a frame's first byte -> its protocol


def register_protocol(protocol: LinkProtocol) -> None:
    """Add ``protocol`` to the table (ValueError: its name is taken, or a start byte is another's)."""
    if protocol.name in PROTOCOLS:
        raise ValueError(f"command-link protocol {protocol.name!r} is registered already")
    for other in PROTOCOLS.values():
        if protocol.start_bytes & other.start_bytes:
            raise ValueError(f"protocol {protocol.name!r} shares a start byte with {other.name!r}")
    PROTOCOLS[protocol.name] = protocol
    _BY_START.update(dict.fromkeys(protocol.start_bytes, protocol))


def unregister_protocol(name: str) -> None:
    """Take protocol ``name`` out of the table (KeyError: not in it)."""
    protocol = PROTOCOLS.pop(name)
    for b in protocol.start_bytes:
        del _BY_START[b]


def link_protocol(name: str) -> LinkProtocol:
    """The protocol named ``name``; ValueError naming the registered ones otherwise."""
    p = PROTOCOLS.get(name)
    if p is None:
        raise ValueError(f"command-link protocol must be one of {', '.join(PROTOCOLS)}, got {name!r}")
    return p


def framing(name: str, system_id: int = 1, component_id: int = mavlink.mav.MAV_COMP_ID_AUTOPILOT1) -> Framing:
    """The lockstep framing of protocol ``name`` with the FC's ids; ValueError for an unknown name."""
    return link_protocol(name).framing(system_id, component_id)


def frame_at(data: bytes, j: int) -> bytes | None:
    """The whole, CRC-checked frame of any registered protocol that starts at ``data[j]``, or None."""
    p = _BY_START.get(data[j])
    return None if p is None else p.frame_at(data, j)


def decode(frame: bytes) -> Decoded:
    """A captured frame (CRC checked) of any registered protocol, read (ValueError: no protocol's)."""
    p = _BY_START.get(frame[0])
    if p is not None:
        return Decoded(p.name, *p.describe(frame))
    raise ValueError(f"no command-link protocol starts a frame with 0x{frame[0]:02X}")


register_protocol(LinkProtocol("mavlink", mavlink.MavlinkCodec, mavlink_framing, mavlink.MAX_FRAME_BYTES,
                               mavlink.START_BYTES, mavlink.good_frame_at, mavlink.describe_frame))
register_protocol(LinkProtocol("dji_open", dji_open.OpenCodec, dji_framing, dji_open.MAX_FRAME_BYTES,
                               frozenset({dji_open.SOF}), dji_open.good_frame_at, dji_open.describe_frame))
