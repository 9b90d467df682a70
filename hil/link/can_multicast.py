"""python-can's UDP multicast bus kept to its own group: a bus of its own for each bench on one host."""

from __future__ import annotations

import socket
import sys
from typing import Any

#: Linux's IP_MULTICAST_ALL and IPV6_MULTICAST_ALL (<linux/in.h>, <linux/in6.h>; Python 3.11's socket
#: module names neither)
IP_MULTICAST_ALL = 49
IPV6_MULTICAST_ALL = 29


def own_group_only(bus: Any) -> Any:
    """``bus`` (python-can's udp_multicast) made to hear its own group only, returned. python-can binds
    its socket to the port on every address, and Linux then hands it every group's datagrams to that
    port that any socket on the host has joined: two benches on two groups would drive each other's
    motors. Clearing IP(V6)_MULTICAST_ALL restricts the socket to the groups it joined itself. (Elsewhere
    the option does not exist and the bus is returned as it is.)"""
    if sys.platform.startswith("linux"):
        sock = bus._multicast._socket
        if sock.family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, IPV6_MULTICAST_ALL, 0)
        else:
            sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
    return bus
