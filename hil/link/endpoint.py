"""Link specs ("pty:921600", "udp:127.0.0.1:14550", ...) parsed and opened as transports.

Specs, for either side of the cable (``role`` "fc" is the flight-controller side, "onboard" the
companion computer):
    pty[:BAUD]              new pseudo-terminal, fc side only; peers open its slave path
    serial:DEVICE[:BAUD]    a serial device through pyserial (also a pty slave path); on the fc side
                            it survives the device vanishing (an adapter unplugged) and reopens it
    udp:HOST:PORT           bind and reply to the last sender (autopilot style)
    udpout:HOST:PORT        send to a fixed peer from an ephemeral port
    tcp:HOST:PORT           listen, one client at a time
    tcpout:HOST:PORT        connect
    memory[:NAME]           in-process pair: the first `open_link` of NAME creates it, the other
                            role gets the other end
BAUD defaults to 921600 (bit/s).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from hil.link.clock import Clock
from hil.link.memory import MemoryTransport
from hil.link.pty import PtyTransport
from hil.link.tcp import TcpTransport
from hil.link.transport import Transport
from hil.link.uart import DEFAULT_TX_BUFFER_BYTES, UartTransport
from hil.link.udp import UdpTransport

Role = Literal["fc", "onboard"]
ROLES: tuple[str, ...] = ("fc", "onboard")
DEFAULT_BAUD = 921600
SERIAL_RECONNECT_S = 0.25  # how often the fc side of a serial link tries a vanished device again (s)
SPEC_HELP = (
    "expected one of: 'pty', 'pty:BAUD', 'serial:DEVICE:BAUD', 'udp:HOST:PORT', 'udpout:HOST:PORT', "
    "'tcp:HOST:PORT', 'tcpout:HOST:PORT', 'memory', 'memory:NAME'"
)


@dataclass(frozen=True)
class EndpointSpec:
    """A parsed link spec."""

    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int | None = None
    name: str = ""

    def __str__(self) -> str:
        if self.kind == "pty":
            return f"pty:{self.baud}"
        if self.kind == "serial":
            return f"serial:{self.device}:{self.baud}"
        if self.kind == "memory":
            return f"memory:{self.name}"
        return f"{self.kind}:{self.host}:{self.port}"


def _parse_baud(text: str, spec: str) -> int:
    if not text.isdigit() or int(text) <= 0:
        raise ValueError(f"bad baud rate {text!r} in link spec {spec!r}: a positive integer (bit/s)")
    return int(text)


def parse_endpoint(spec: str) -> EndpointSpec:
    """Parse a link spec; ValueError naming what is expected when it is malformed."""
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"empty link spec: {SPEC_HELP}")
    spec = spec.strip()
    kind, _, rest = spec.partition(":")
    kind = kind.lower()
    if kind not in OPENERS:
        raise ValueError(f"unknown link kind {kind!r} in {spec!r}; {SPEC_HELP}")
    if kind == "pty":
        return EndpointSpec("pty", baud=_parse_baud(rest, spec) if rest else DEFAULT_BAUD)
    if kind == "memory":
        return EndpointSpec("memory", name=rest or "default")
    if kind == "serial":
        device, sep, baud = rest.rpartition(":")
        if not sep or not baud.isdigit():  # no baud given: the whole rest is the device
            device, baud = rest, ""
        if not device:
            raise ValueError(f"link spec {spec!r} names no device; expected 'serial:DEVICE:BAUD'")
        return EndpointSpec("serial", device=device, baud=_parse_baud(baud, spec) if baud else DEFAULT_BAUD)
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"bad link spec {spec!r}: expected '{kind}:HOST:PORT' with PORT 0..65535")
    return EndpointSpec(kind, host=host, port=int(port))


# in-process pairs waiting for their second end: name -> {role: transport}
_memory_pairs: dict[str, dict[str, Transport]] = {}
_memory_lock = threading.Lock()


def _open_memory(ep: EndpointSpec, role: str) -> Transport:
    name = ep.name
    with _memory_lock:
        waiting = _memory_pairs.get(name)
        if waiting is None:
            fc_end, onboard_end = MemoryTransport.pair(name=f"memory:{name}")
            waiting = _memory_pairs[name] = {"fc": fc_end, "onboard": onboard_end}
        end = waiting.pop(role, None)
        if end is None:
            raise ValueError(f"the {role} end of memory link {name!r} is already open")
        if not waiting:
            del _memory_pairs[name]
        return end


def _open_pty(ep: EndpointSpec, role: str) -> Transport:
    if role != "fc":
        raise ValueError(
            "only the fc side creates a pty; the onboard side opens its path as 'serial:/dev/pts/N:BAUD'"
        )
    return PtyTransport.create(ep.baud or DEFAULT_BAUD)


def _open_serial(ep: EndpointSpec, role: str) -> Transport:
    from hil.link.serial_port import SerialTransport  # (here: pyserial, optional, only for its users)

    # the fc side outlives its cable: a USB-serial adapter unplugged and plugged back in is silence,
    # then the link again (the FC's link-loss failsafe acts meanwhile); the onboard side is told
    return SerialTransport(ep.device, ep.baud or DEFAULT_BAUD,
                           reconnect_s=SERIAL_RECONNECT_S if role == "fc" else None)


def _open_socket(ep: EndpointSpec, role: str) -> Transport:
    cls = UdpTransport if ep.kind.startswith("udp") else TcpTransport
    return cls(ep.host, ep.port, server=ep.kind in ("udp", "tcp"))


#: link kind -> opener (the serial one imports pyserial only when used: an optional driver fails only
#: for its users)
OPENERS: dict[str, Callable[[EndpointSpec, str], Transport]] = {
    "pty": _open_pty,
    "serial": _open_serial,
    "udp": _open_socket,
    "udpout": _open_socket,
    "tcp": _open_socket,
    "tcpout": _open_socket,
    "memory": _open_memory,
}


def open_link(
    spec: str | EndpointSpec,
    role: Role = "fc",
    *,
    clock: Clock | None = None,
    uart_baud: int | None = None,
    tx_buffer_bytes: int | None = None,
) -> Transport:
    """Open the transport a spec names, for the ``role`` side.

    With ``uart_baud`` (bit/s), sends are paced as a UART at that rate on ``clock`` (default wall
    time) through a transmit buffer of ``tx_buffer_bytes``; see `hil.link.uart.UartTransport`.
    Raises ValueError for a bad spec or role, LinkError when the link cannot be opened.
    """
    if role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, got {role!r}")
    ep = spec if isinstance(spec, EndpointSpec) else parse_endpoint(spec)
    link = OPENERS[ep.kind](ep, role)
    if uart_baud is not None:
        link = UartTransport(link, uart_baud, clock, tx_buffer_bytes or DEFAULT_TX_BUFFER_BYTES)
    return link
