"""CAN frames over UDP multicast between processes, kept to this machine unless a network is named.

Two wire formats, each its owner's: dronecan's ``mcast`` (UDP 239.65.82.N:57732, the datagrams of
dronecan's multicast driver and of ArduPilot's simulation) and python-can's ``udp_multicast`` (its
msgpack datagrams, UDP GROUP:43113). `McastCanSocket` speaks either on two sockets of its own:

- by default on the loopback interface only: it joins its group on 127.0.0.1 (no IGMP report leaves the
  machine), sends with IP_MULTICAST_IF 127.0.0.1, time-to-live 0 (Linux never sends a multicast with
  TTL 0 beyond the host) and IP_MULTICAST_LOOP on, so every process of this machine on the group hears
  it and no other machine does;
- on a lab network when given an interface's IPv4 address (``mcast:0@192.168.1.20``): joined, and sent
  with TTL 1, on that interface.

Its own datagrams come back through the loop; they are told from another process's by their source
address (its sending socket's), never by the CAN id they carry, so another node using one of this
process's node ids is heard. A datagram that is not a frame of its format is counted, never raised.
"""

from __future__ import annotations

import binascii
import contextlib
import ipaddress
import socket
import struct
import sys
from collections.abc import Callable
from dataclasses import dataclass, fields

LOOPBACK_ADDR = "127.0.0.1"
#: Linux's SO_MEMINFO and the index of the datagrams a socket dropped for want of room in what it
#: answers (<asm-generic/socket.h>, <linux/sock_diag.h>; Python 3.11's socket module names neither)
SO_MEMINFO, SK_MEMINFO_DROPS, SK_MEMINFO_VARS = 55, 8, 9
RECV_BUFFER_BYTES = 1 << 20  # the receiving socket's buffer: about 10,000 frames of either format
MAX_DATAGRAM = 4096

Frame = tuple[int, bytes]  # (29-bit CAN id, data)


@dataclass(frozen=True)
class WireFormat:
    """One format of CAN frames in UDP datagrams: its port, its group for a bus argument, and its codec.
    ``decode`` returns None for a datagram that is not an extended frame of the format."""

    port: int
    group_of: Callable[[str], str]
    encode: Callable[[int, bytes], bytes]
    decode: Callable[[bytes], Frame | None]


def _dronecan_format() -> WireFormat:
    # (dronecan loads every DSDL type on import, about 0.7 s: only for a bus that needs it)
    from dronecan.driver.mcast import MCAST_ADDRESS_BASE, MCAST_FLAG_CANFD, MCAST_MAGIC, MCAST_PORT

    extended_flag = 1 << 31

    def crc16_from_bytes(data: bytes) -> int:
        # the datagram's CRC-16/CCITT-FALSE (polynomial 0x1021, initial 0xFFFF), as dronecan's driver
        # computes it, by the standard library in C (dronecan's is Python, a tenth of a ms a datagram)
        return binascii.crc_hqx(data, 0xFFFF)

    def encode(can_id: int, data: bytes) -> bytes:
        body = struct.pack("<HI", 0, can_id | extended_flag) + data
        return struct.pack("<HH", MCAST_MAGIC, crc16_from_bytes(body)) + body

    def decode(datagram: bytes) -> Frame | None:
        if len(datagram) < 10:
            return None
        magic, crc, flags, can_id = struct.unpack_from("<HHHI", datagram)
        if (magic != MCAST_MAGIC or crc != crc16_from_bytes(datagram[4:])
                or flags & MCAST_FLAG_CANFD or not can_id & extended_flag):
            return None
        return can_id & 0x1FFFFFFF, datagram[10:]

    def group_of(arg: str) -> str:
        bus = int(arg or 0)
        if not 0 <= bus <= 255:
            raise ValueError(f"mcast bus number must be 0..255, got {bus}")
        return f"{MCAST_ADDRESS_BASE}.{bus}"

    return WireFormat(MCAST_PORT, group_of, encode, decode)


def _python_can_format() -> WireFormat:
    # (python-can's bus modules load on first use: only for a bus that needs them)
    import can
    from can.interfaces.udp_multicast import UdpMulticastBus
    from can.interfaces.udp_multicast.utils import pack_message, unpack_message

    def encode(can_id: int, data: bytes) -> bytes:
        return pack_message(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))

    def decode(datagram: bytes) -> Frame | None:
        try:
            msg = unpack_message(datagram, check=True)
        except Exception:  # (msgpack's or python-can's complaint about a malformed datagram)
            return None
        if not msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
            return None
        return msg.arbitration_id, bytes(msg.data)

    return WireFormat(43113, lambda arg: arg or UdpMulticastBus.DEFAULT_GROUP_IPv4, encode, decode)


#: bus kind -> its wire format (made when a bus of that kind opens)
FORMATS: dict[str, Callable[[], WireFormat]] = {"mcast": _dronecan_format,
                                                "udp_multicast": _python_can_format}


def split_interface(spec: str) -> tuple[str, str]:
    """``KIND[:ARG][@ADDR]`` -> (``KIND[:ARG]``, ADDR): the interface the bus is on, the loopback one
    unless an address is named (ValueError for one that is not an IPv4 address)."""
    bus, at, addr = spec.partition("@")
    if not at:
        return bus, LOOPBACK_ADDR
    try:
        ipaddress.IPv4Address(addr)
    except ValueError:
        raise ValueError(f"{spec!r}: after @ an interface's IPv4 address, got {addr!r}") from None
    return bus, addr


@dataclass
class McastStats:
    """What a multicast CAN socket carried (counts of datagrams)."""

    sent: int = 0
    send_errors: int = 0  # refused by the socket (counted; the caller goes on)
    received: int = 0  # frames from other processes
    own: int = 0  # its own datagrams, come back through the loop
    malformed: int = 0  # not a frame of the format
    dropped: int = 0  # lost in the socket for want of room (the kernel's count)

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class McastCanSocket:
    """Extended CAN frames of ``kind`` (`FORMATS`) on the group ``arg`` names, on the interface with the
    IPv4 address ``interface`` (the loopback one by default: see the module doc)."""

    def __init__(self, kind: str, arg: str = "", interface: str = LOOPBACK_ADDR) -> None:
        if kind not in FORMATS:
            raise ValueError(f"multicast CAN bus {kind!r}: expected one of {', '.join(FORMATS)}")
        fmt = FORMATS[kind]()
        self.format, self.interface, self._stats = fmt, interface, McastStats()
        self.group = fmt.group_of(arg)
        try:
            if not ipaddress.IPv4Address(self.group).is_multicast:
                raise ValueError(f"{self.group} is not a multicast group")
        except ValueError as exc:
            raise ValueError(f"multicast CAN bus {kind}: an IPv4 multicast group, got {self.group!r} "
                             f"({exc})") from None
        self.on_loopback = ipaddress.IPv4Address(interface).is_loopback
        iface = socket.inet_aton(interface)
        self._rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            rx, tx = self._rx, self._tx
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)  # (python-can's sockets set both)
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
            rx.bind((self.group, fmt.port))  # (the group's datagrams only, not another group's on the port)
            rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(self.group) + iface)
            rx.setblocking(False)
            tx.bind((interface, 0))
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, iface)
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0 if self.on_loopback else 1)
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            tx.connect((self.group, fmt.port))
            tx.setblocking(False)
            self._own = tx.getsockname()
        except OSError:
            self.close()
            raise

    def fileno(self) -> int:
        """The receiving socket's descriptor (to wait on)."""
        return self._rx.fileno()

    def send(self, can_id: int, data: bytes) -> bool:
        """One extended frame out; False (and counted) when the socket refuses it."""
        try:
            self._tx.send(self.format.encode(can_id, bytes(data)))
        except OSError:
            self._stats.send_errors += 1
            return False
        self._stats.sent += 1
        return True

    def receive(self, max_frames: int) -> tuple[list[Frame], bool]:
        """Up to ``max_frames`` frames from other processes, and whether more may be waiting (the caller
        takes them at its next pass; the socket holds them meanwhile)."""
        out: list[Frame] = []
        st, decode = self._stats, self.format.decode
        while len(out) < max_frames:
            try:
                datagram, source = self._rx.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return out, False
            except OSError:  # (an ICMP error queued on the socket: nothing to read now)
                return out, False
            if source == self._own:
                st.own += 1
                continue
            frame = decode(datagram)
            if frame is None:
                st.malformed += 1
                continue
            st.received += 1
            out.append(frame)
        return out, True

    @property
    def stats(self) -> McastStats:
        """Its counts, the socket's drops as the kernel counts them now (Linux; elsewhere 0)."""
        if sys.platform.startswith("linux"):
            with contextlib.suppress(OSError):  # (a closed socket keeps the last count)
                info = self._rx.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * SK_MEMINFO_VARS)
                self._stats.dropped = struct.unpack_from(f"{SK_MEMINFO_VARS}I", info)[SK_MEMINFO_DROPS]
        return self._stats

    def multicast_options(self) -> dict[str, object]:
        """The sending socket's multicast settings as the kernel holds them (interface, TTL, loop) and the
        receiving socket's group: what keeps the bus where it is."""
        tx = self._tx
        return {"interface": socket.inet_ntoa(tx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4)),
                "ttl": tx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL),
                "loop": bool(tx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP)),
                "group": self.group, "port": self.format.port, "source": self._own}

    def close(self) -> None:
        for sock in (self._rx, self._tx):
            with contextlib.suppress(OSError):
                sock.close()
