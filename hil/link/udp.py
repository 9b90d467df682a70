"""UDP transport, presented as a byte stream (framing lives in the codecs above).

Two modes, named as MAVLink tools name them:
- ``udp:HOST:PORT`` (`UdpTransport.server`): binds HOST:PORT and replies to the last peer that sent
  to it, as an autopilot does. Until some peer has sent a datagram, sends are dropped and counted.
- ``udpout:HOST:PORT`` (`UdpTransport.client`): sends to the fixed peer HOST:PORT from an
  ephemeral local port, and receives what comes back to that port.

UDP cannot tell whether a peer is alive: datagrams to a peer that has gone are sent and lost, never
an error (ICMP "port unreachable" is ignored), and a peer that restarts is served again as soon as
it sends. Each `send` goes out as one datagram (split above 65000 bytes); a datagram larger than
`recv`'s ``max_bytes`` is handed out over several calls, nothing is cut off.
"""

from __future__ import annotations

import socket

from hil.link.transport import LinkError, Transport

MAX_DATAGRAM_BYTES = 65000
LOOPBACK = "127.0.0.1"


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
        if not self._pending:
            try:
                data, addr = self._sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError, ConnectionRefusedError):
                return b""
            except OSError as e:
                raise LinkError(f"{self.endpoint}: receive failed: {e}") from e
            if self.server:
                self._peer = addr
            self._pending = data
        out, self._pending = self._pending[:max_bytes], self._pending[max_bytes:]
        return out

    def _wait_readable(self, timeout_s: float | None) -> None:
        if not self._pending:
            super()._wait_readable(timeout_s)

    def _close_internal(self) -> None:
        self._sock.close()
