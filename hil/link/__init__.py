"""The link layer: transports (serial, pty, UDP, TCP, in-memory), wire framing, the link channel model
and the lockstep convention. It imports neither `emulator` nor `policies`: both sides meet only here,
as a TX2 meets an N3 over a cable. Names are imported lazily: a transport's module (and its driver)
loads when it is first used."""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> the module that defines it
_EXPORTS = {
    "Clock": "clock",
    "SimClock": "clock",
    "WallClock": "clock",
    "EndpointSpec": "endpoint",
    "open_link": "endpoint",
    "parse_endpoint": "endpoint",
    "MemoryTransport": "memory",
    "PtyTransport": "pty",
    "SerialTransport": "serial_port",
    "TcpTransport": "tcp",
    "LinkError": "transport",
    "LinkStats": "transport",
    "Transport": "transport",
    "UartModel": "uart",
    "UartTransport": "uart",
    "UdpTransport": "udp",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'hil.link' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"hil.link.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
