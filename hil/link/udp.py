"""UDP transport, presented as a byte stream (framing lives in the codecs above).

Two modes, named as MAVLink tools name them:
- ``udp:HOST:PORT`` (`UdpTransport.server`): binds HOST:PORT and replies to the last peer that sent
  to it, as an autopilot does. Until some peer has sent a datagram, sends are dropped and counted.
- ``udpout:HOST:PORT`` (`UdpTransport.client`): sends to the fixed peer HOST:PORT from an
  ephemeral local port, and receives what comes back to that port.

UDP cannot tell whether a peer is alive: datagrams to a peer that has gone are sent and lost, never
an error (ICMP "port unreachable" is ignored), and a peer that restarts is served again as soon as
it sends. Each `send` goes out as one datagram (split above 65000 bytes); a datagram larger than
`recv`'s ``max_bytes`` is handed out over several calls, nothing is cut off. A `recv` drains every
datagram waiting, up to ``max_bytes`` (the bound on one pass's intake; the rest waits in the socket).
Datagrams the kernel drops because the socket's buffer was full are counted in
`stats.datagrams_lost_in` (Linux: SO_RXQ_OVFL tells the count with each datagram read, which misses
drops after the last one; `count_drops()` reads the count now from /proc/net/udp; elsewhere they go
uncounted).
"""

from __future__ import annotations

import os
import socket
import sys
from pathlib import Path

from hil.link.transport import LinkError, Transport

MAX_DATAGRAM_BYTES = 65000
LOOPBACK = "127.0.0.1"
#: the socket option that makes Linux hand over its count of datagrams dropped for a full receive
#: buffer with each datagram read (Python's socket module does not name it)
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
_DROP_COUNT_SPACE = socket.CMSG_SPACE(4)


class UdpTransport(Transport):
    """A UDP socket in server (bind, reply to last sender) or client (fixed peer) mode."""

    def __init__(self, host: str, port: int, *, server: bool) -> None:
        super().__init__()
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"UDP port must be 0..65535, got {port}")
        self.server = server
        self._pending = b""
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if server:
                self._sock.bind((host, int(port)))
                self._peer: tuple[str, int] | None = None
            else:
                self._peer = (socket.gethostbyname(host), int(port))
                local = LOOPBACK if self._peer[0].startswith("127.") else "0.0.0.0"
                self._sock.bind((local, 0))
        except OSError as e:
            self._sock.close()
            self._closed = True
            mode = "bind" if server else "reach"
            raise LinkError(f"cannot {mode} UDP {host}:{port}: {e}") from e
        self._sock.setblocking(False)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
            self._count_drops = True
        except OSError:  # not Linux: drops in the socket go uncounted
            self._count_drops = False
        h, p = self._sock.getsockname() if server else self._peer
        self.endpoint = f"{'udp' if server else 'udpout'}:{h}:{p}"

    @classmethod
    def server(cls, host: str = LOOPBACK, port: int = 14550) -> UdpTransport:
        """Bind ``host:port`` (port 0: any free port, see `endpoint`); reply to the last sender."""
        return cls(host, port, server=True)

    @classmethod
    def client(cls, host: str = LOOPBACK, port: int = 14550) -> UdpTransport:
        """Send to the fixed peer ``host:port`` from an ephemeral local port."""
        return cls(host, port, server=False)

    @property
    def peer(self) -> tuple[str, int] | None:
        """Where sends go: the fixed peer, or the last sender (server); None before any."""
        return self._peer

    @property
    def local_address(self) -> tuple[str, int]:
        """The (host, port) this socket is bound to."""
        return self._sock.getsockname()

    def fileno(self) -> int:
        if self._closed:
            raise ValueError(f"{self.endpoint}: fileno on a closed link")
        return self._sock.fileno()

    def _send_internal(self, data: bytes) -> int:
        if self._peer is None:
            return 0
        sent = 0
        for start in range(0, len(data), MAX_DATAGRAM_BYTES):
            chunk = data[start : start + MAX_DATAGRAM_BYTES]
            try:
                self._sock.sendto(chunk, self._peer)
            except (BlockingIOError, InterruptedError, ConnectionRefusedError):
                break
            except OSError as e:
                raise LinkError(f"{self.endpoint}: send to {self._peer} failed: {e}") from e
            sent += len(chunk)
        return sent

    def _recv_internal(self, max_bytes: int) -> bytes:
        out = bytearray()
        while True:
            if not self._pending:
                self._pending = self._next_datagram()
                if not self._pending:
                    break
            take = max_bytes - len(out)
            out += self._pending[:take]
            self._pending = self._pending[take:]
            if len(out) >= max_bytes:
                break
        return bytes(out)

    def _next_datagram(self) -> bytes:
        """The next datagram waiting (b"" if none), counting what the kernel dropped before it."""
        try:
            data, anc, _, addr = self._sock.recvmsg(65536, _DROP_COUNT_SPACE if self._count_drops else 0)
        except (BlockingIOError, InterruptedError, ConnectionRefusedError):
            return b""
        except OSError as e:
            raise LinkError(f"{self.endpoint}: receive failed: {e}") from e
        for level, kind, value in anc:
            if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= 4:
                # the kernel's running count since the socket opened
                self.stats.datagrams_lost_in = int.from_bytes(value[:4], sys.byteorder)
        if self.server:
            self._peer = addr
        return data

    def _wait_readable(self, timeout_s: float | None) -> None:
        if not self._pending:
            super()._wait_readable(timeout_s)

    def count_drops(self) -> int:
        """`stats.datagrams_lost_in` brought up to the kernel's count now (Linux; unchanged elsewhere)."""
        if self._closed:
            return self.stats.datagrams_lost_in
        inode = str(os.fstat(self._sock.fileno()).st_ino)
        try:
            lines = Path("/proc/net/udp").read_text().splitlines()[1:]
        except OSError:
            return self.stats.datagrams_lost_in
        for line in lines:  # sl local rem st queues tr retrnsmt uid timeout inode ref pointer drops
            f = line.split()
            if len(f) >= 13 and f[9] == inode:
                self.stats.datagrams_lost_in = max(self.stats.datagrams_lost_in, int(f[12]))
        return self.stats.datagrams_lost_in

    def _close_internal(self) -> None:
        self._sock.close()
