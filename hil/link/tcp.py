"""TCP transport: a listening end that serves one client at a time, and a connecting end.

- ``tcp:HOST:PORT`` (`TcpTransport.server`): listens on HOST:PORT. The first pending client is
  accepted on the next `send`/`recv`; a client that connects later replaces the current one (so a
  restarted peer gets in even if its old connection was never seen to die). While no client is
  connected, sends are dropped and counted and `recv` returns b"" after its timeout; when the
  client goes away the server simply waits for the next one.
- ``tcpout:HOST:PORT`` (`TcpTransport.client`): connects at construction (LinkError if nobody
  listens). When the server goes away, bytes already received are still delivered, then `recv`
  and `send` raise LinkError("peer closed"); open a new transport to reconnect.

Writes never block: what the kernel's socket buffer cannot take now is dropped and counted.
`fileno()` is the connected socket, or the listening socket while a server has no client (it
becomes readable when one is waiting), so call it again before each select.
"""

from __future__ import annotations

import errno
import select
import socket

from hil.link.transport import LinkError, Transport

LOOPBACK = "127.0.0.1"
CONNECT_TIMEOUT_S = 5.0
_PEER_GONE = (ConnectionResetError, BrokenPipeError, ConnectionAbortedError)


class TcpTransport(Transport):
    """A TCP byte stream, listening (server) or connecting (client)."""

    def __init__(
        self, host: str, port: int, *, server: bool, connect_timeout_s: float = CONNECT_TIMEOUT_S
    ) -> None:
        super().__init__()
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"TCP port must be 0..65535, got {port}")
        self.server = server
        self._listener: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._peer_gone = False
        self.connections_accepted = 0
        try:
            if server:
                self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self._listener.bind((host, int(port)))
                self._listener.listen(4)
                self._listener.setblocking(False)
                h, p = self._listener.getsockname()
            else:
                conn = socket.create_connection((host, int(port)), timeout=connect_timeout_s)
                self._adopt(conn)
                h, p = host, int(port)
        except OSError as e:
            if self._listener is not None:
                self._listener.close()
            self._closed = True
            mode = "listen on" if server else "connect to"
            raise LinkError(f"cannot {mode} TCP {host}:{port}: {e}") from e
        self.endpoint = f"{'tcp' if server else 'tcpout'}:{h}:{p}"

    @classmethod
    def server(cls, host: str = LOOPBACK, port: int = 5760) -> TcpTransport:
        """Listen on ``host:port`` (port 0: any free port, see `endpoint`)."""
        return cls(host, port, server=True)

    @classmethod
    def client(
        cls, host: str = LOOPBACK, port: int = 5760, connect_timeout_s: float = CONNECT_TIMEOUT_S
    ) -> TcpTransport:
        """Connect to ``host:port``; LinkError when nobody listens there."""
        return cls(host, port, server=False, connect_timeout_s=connect_timeout_s)

    @property
    def connected(self) -> bool:
        """True while a peer connection is open (servers: after accepting a pending client)."""
        if self.server and not self._closed:
            self._accept_pending()
        return self._conn is not None

    def fileno(self) -> int:
        if self._closed:
            raise ValueError(f"{self.endpoint}: fileno on a closed link")
        if self.server:
            self._accept_pending()
        sock = self._conn if self._conn is not None else self._listener
        if sock is None:
            raise LinkError(f"{self.endpoint}: peer closed")
        return sock.fileno()

    # --- internals -----------------------------------------------------------------------
    def _adopt(self, conn: socket.socket) -> None:
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn = conn
        self._peer_gone = False

    def _drop_conn(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if not self.server:
            self._peer_gone = True

    def _accept_pending(self) -> None:
        assert self._listener is not None
        while True:
            try:
                conn, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                if e.errno in (errno.ECONNABORTED, errno.EPROTO):
                    continue
                raise LinkError(f"{self.endpoint}: accept failed: {e}") from e
            if self._conn is not None:
                self._conn.close()
            self._adopt(conn)
            self.connections_accepted += 1

    def _send_internal(self, data: bytes) -> int:
        if self.server:
            self._accept_pending()
        if self._conn is None:
            if self._peer_gone:
                raise LinkError(f"{self.endpoint}: peer closed")
            return 0
        try:
            return self._conn.send(data)
        except (BlockingIOError, InterruptedError):
            return 0
        except _PEER_GONE as e:
            self._drop_conn()
            if self.server:
                return 0
            raise LinkError(f"{self.endpoint}: peer closed ({e})") from e
        except OSError as e:
            raise LinkError(f"{self.endpoint}: send failed: {e}") from e

    def _recv_internal(self, max_bytes: int) -> bytes:
        if self.server:
            self._accept_pending()
        if self._conn is None:
            if self._peer_gone:
                raise LinkError(f"{self.endpoint}: peer closed")
            return b""
        try:
            data = self._conn.recv(max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        except _PEER_GONE:
            data = b""
        except OSError as e:
            raise LinkError(f"{self.endpoint}: receive failed: {e}") from e
        if not data:  # orderly shutdown or reset by the peer
            self._drop_conn()
            if not self.server:
                raise LinkError(f"{self.endpoint}: peer closed")
        return data

    def _wait_readable(self, timeout_s: float | None) -> None:
        select.select([self.fileno()], [], [], timeout_s)

    def _close_internal(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._listener is not None:
            self._listener.close()
