"""The transport interface: a byte stream between two endpoints, whatever carries it.

Template method after python-can: the public `recv(timeout_s)` owns waiting and statistics; each
transport implements `_send_internal` and `_recv_internal`. Datagram transports (UDP) are presented
as byte streams too: framing (MAVLink, LinkTrack) lives above, in the codecs.
"""

from __future__ import annotations

import os
import select
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType


class LinkError(OSError):
    """A transport cannot be opened or has failed (peer gone, device vanished)."""


@dataclass
class LinkStats:
    """Counters kept by every transport (bytes)."""

    bytes_sent: int = 0
    bytes_received: int = 0
    bytes_dropped: int = 0  # refused or lost because a buffer was full
    datagrams_lost_in: int = 0  # arrived, but dropped by the kernel before they were read (UDP, Linux)
    send_calls: int = 0
    recv_calls: int = 0


class Transport(ABC):
    """A bidirectional byte stream. Context manager; `close()` is idempotent."""

    #: where a peer reaches this end, e.g. "/dev/pts/5" or "udp:127.0.0.1:14550"
    endpoint: str = ""

    def __init__(self) -> None:
        self.stats = LinkStats()
        #: True once `close()` has run (read it; a plain attribute: links are asked several times a tick)
        self.closed = False

    # --- public API ----------------------------------------------------------------------
    def send(self, data: bytes) -> int:
        """Send ``data``; returns how many bytes were accepted (the rest counted as dropped)."""
        if self.closed:
            raise LinkError(f"{self.endpoint or type(self).__name__}: send on a closed link")
        if not data:
            return 0
        n = self._send_internal(data if data.__class__ is bytes else bytes(data))
        stats = self.stats
        stats.send_calls += 1
        stats.bytes_sent += n
        stats.bytes_dropped += len(data) - n
        return n

    def recv(self, timeout_s: float | None = 0.0, max_bytes: int = 65536) -> bytes:
        """Bytes available now, waiting up to ``timeout_s`` (None: forever) for the first ones.

        Returns b"" when nothing arrived in time. Raises LinkError when the link is closed.
        """
        if self.closed:
            raise LinkError(f"{self.endpoint or type(self).__name__}: recv on a closed link")
        if timeout_s is not None and timeout_s <= 0.0:  # one read, no deadline to keep
            data = self._recv_internal(max_bytes)
            if not data:
                return b""
            stats = self.stats
            stats.recv_calls += 1
            stats.bytes_received += len(data)
            return data
        deadline = None if timeout_s is None else time.monotonic() + max(0.0, timeout_s)
        while True:
            data = self._recv_internal(max_bytes)
            if data:
                self.stats.recv_calls += 1
                self.stats.bytes_received += len(data)
                return data
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                return b""
            self._wait_readable(remaining)

    def fileno(self) -> int:
        """A file descriptor that becomes readable when data may be there (for select)."""
        raise NotImplementedError(f"{type(self).__name__} has no file descriptor")

    def close(self) -> None:
        """Release the transport; calling it again does nothing."""
        if not self.closed:
            self.closed = True
            self._close_internal()

    @property
    def _closed(self) -> bool:
        """`closed`, as implementations read and set it."""
        return self.closed

    @_closed.setter
    def _closed(self, value: bool) -> None:
        self.closed = value

    def __enter__(self) -> Transport:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.endpoint!r}{' closed' if self.closed else ''}>"

    # --- for implementations -------------------------------------------------------------
    @abstractmethod
    def _send_internal(self, data: bytes) -> int:
        """Write what fits; return the number of bytes accepted. Must not block for long."""

    @abstractmethod
    def _recv_internal(self, max_bytes: int) -> bytes:
        """Return the bytes available now, or b"" without blocking."""

    @abstractmethod
    def _close_internal(self) -> None:
        """Release resources (called once)."""

    def _wait_readable(self, timeout_s: float | None) -> None:
        """Block until data may be readable or ``timeout_s`` passes; default uses select on fileno()."""
        select.select([self.fileno()], [], [], timeout_s)


class Waiter:
    """Waits until one of a few descriptors is readable: one poll object, made once, asked each wait
    (no descriptor lists built a wait, as `select.select` needs)."""

    def __init__(self, fds: list[int]) -> None:
        poll = select.poll()
        for fd in fds:
            poll.register(fd, select.POLLIN)
        self._poll = poll.poll

    def wait(self, timeout_s: float, spin_s: float = 0.0) -> bool:
        """Wait until a descriptor is readable or ``timeout_s`` (wall) has passed; True if readable.

        With ``spin_s`` > 0 it first polls for that long, yielding the CPU between polls, before it
        blocks: an answer expected within microseconds is then caught without a sleep and a wake-up (on a
        virtual machine an idle CPU halts, and waking it costs tens to hundreds of microseconds), while
        another process that needs the CPU still gets it."""
        poll = self._poll
        if spin_s > 0:
            end = time.perf_counter() + min(spin_s, timeout_s)
            while True:
                if poll(0):
                    return True
                if time.perf_counter() >= end:
                    break
                os.sched_yield()
            timeout_s -= spin_s
            if timeout_s <= 0:
                return False
        # (ms, rounded up as select rounds its seconds; a negative timeout would block for good)
        return bool(poll(timeout_s * 1e3 if timeout_s > 0 else 0))


def wait_readable(fds: list[int], timeout_s: float, spin_s: float = 0.0) -> bool:
    """Wait until one of ``fds`` is readable or ``timeout_s`` (wall) has passed; True if readable (a
    `Waiter` of them, for one wait)."""
    return Waiter(fds).wait(timeout_s, spin_s)


def write_nonblocking(fd: int, what: str, data: bytes) -> int:
    """Write what a non-blocking ``fd`` takes now; return the bytes written (the rest did not fit).

    Raises LinkError naming ``what`` when the device is gone. (``data`` last: a transport binds the
    other two with `functools.partial` positionally; a partial with a keyword builds a dict each call,
    about 1,400 instructions more a write.)
    """
    size = len(data)
    try:  # (the whole of it, almost always: a view and a loop only for the rest of a partial write)
        sent = os.write(fd, data)
    except (BlockingIOError, InterruptedError):
        return 0
    except OSError as e:
        raise LinkError(f"{what}: write failed: {e}") from e
    if sent >= size or sent <= 0:
        return max(sent, 0)
    view = memoryview(data)
    while sent < size:
        try:
            n = os.write(fd, view[sent:])
        except (BlockingIOError, InterruptedError):
            break
        except OSError as e:
            raise LinkError(f"{what}: write failed: {e}") from e
        if n <= 0:
            break
        sent += n
    return sent
