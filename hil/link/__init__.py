"""The link layer: transports (serial, pty, UDP, TCP, in-memory), wire framing, the link channel model
and the lockstep convention. It imports neither `emulator` nor `policies`: both sides meet only here,
as a TX2 meets an N3 over a cable. Names are imported lazily: a transport's module (and its driver)
loads when it is first used."""

from __future__ import annotations

import importlib
from typing import Any

#: module -> the public names it defines
_MODULES = {
    "clock": ("Clock", "SimClock", "WallClock"),
    "endpoint": ("EndpointSpec", "open_link", "parse_endpoint"),
    "memory": ("MemoryTransport",),
    "pty": ("PtyTransport",),
    "serial_port": ("SerialTransport",),
    "tcp": ("TcpTransport",),
    "transport": ("LinkError", "LinkStats", "Transport"),
    "uart": ("UartModel", "UartTransport"),
    "udp": ("UdpTransport",),
}
_EXPORTS = {name: module for module, names in _MODULES.items() for name in names}
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
