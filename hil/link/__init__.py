"""The link layer: transports (serial, pty, UDP, TCP, in-memory) and wire framing. It imports neither
`emulator` nor `policies`: both sides meet only here, as a TX2 meets an N3 over a cable."""

from hil.link.clock import Clock, SimClock, WallClock
from hil.link.endpoint import EndpointSpec, open_link, parse_endpoint
from hil.link.memory import MemoryTransport
from hil.link.pty import PtyTransport
from hil.link.serial_port import SerialTransport
from hil.link.tcp import TcpTransport
from hil.link.transport import LinkError, LinkStats, Transport
from hil.link.uart import UartModel, UartTransport
from hil.link.udp import UdpTransport

__all__ = [
    "Clock",
    "EndpointSpec",
    "LinkError",
    "LinkStats",
    "MemoryTransport",
    "PtyTransport",
    "SerialTransport",
    "SimClock",
    "TcpTransport",
    "Transport",
    "UartModel",
    "UartTransport",
    "UdpTransport",
    "WallClock",
    "open_link",
    "parse_endpoint",
]
