"""In-process transport: two connected ends sharing bounded byte buffers, one per direction.

Used by fast tests and by the in-process runner. Each direction holds at most ``capacity_bytes``;
what does not fit is dropped and counted in the sender's `stats.bytes_dropped`, as a full UART
FIFO would lose it. Each end has a real file descriptor (the read end of an os.pipe carrying one
wake-up byte while data is waiting, made when `fileno` is first called), so `select` works on it like
on a socket or a pty.

When one end is closed, the other keeps reading what was already in flight; after that its
`recv` returns b"" on timeout, and its sends are dropped and counted (nobody is listening).
`peer_closed` tells the two cases apart.
"""

from __future__ import annotations

import os
import threading

from hil.link.transport import Transport

DEFAULT_CAPACITY_BYTES = 65536


class _Channel:
    """One direction: a bounded buffer plus a pipe that is readable exactly while data waits (made when
    the reading end's descriptor is first asked for: a link nobody selects on makes no system calls).

    The buffer is the list of the chunks put, in order (a read of one chunk hands that chunk itself
    over: no copy); the lock is taken with ``acquire`` and ``release`` (a ``with`` statement costs about
    twice the instructions of the two calls: its special-method lookups and ``__exit__``'s arguments)."""

    def __init__(self, capacity_bytes: int) -> None:
        self.capacity_bytes = capacity_bytes
        self.chunks: list[bytes] = []  # what waits, oldest first (none of them empty)
        self.size = 0  # bytes waiting: the chunks' lengths summed
        self.lock = threading.Lock()
        self.wake_r: int | None = None
        self.wake_w: int | None = None
        self._signalled = False
        self.fds_open = True
        self.reader_open = True  # False once the end that reads this direction is closed

    def wake_fd(self) -> int:
        """The pipe's read end (made now if it is not yet, readable if data waits)."""
        with self.lock:
            if self.wake_r is None:
                if not self.fds_open:
                    raise ValueError("fileno on a released memory channel")
                self.wake_r, self.wake_w = os.pipe()
                os.set_blocking(self.wake_r, False)
                os.set_blocking(self.wake_w, False)
                if self.chunks:
                    os.write(self.wake_w, b"\x01")
                    self._signalled = True
            return self.wake_r

    def put(self, data: bytes) -> int:
        """Buffer what fits of ``data``; returns the bytes taken (0 once the reading end is closed)."""
        lock = self.lock
        lock.acquire()
        try:
            n = len(data)
            room = self.capacity_bytes - self.size
            if n > room:
                n = room
                data = data[:n]
            if n <= 0 or not self.reader_open or not self.fds_open:
                return 0
            self.chunks.append(data)
            self.size += n
            if not self._signalled and self.wake_w is not None:
                os.write(self.wake_w, b"\x01")
                self._signalled = True
            return n
        finally:
            lock.release()

    def take(self, max_bytes: int) -> bytes:
        """Up to ``max_bytes`` of what waits, oldest first (b"" when nothing does)."""
        if not self.chunks:  # (read without the lock: a put now is as if it came after this read)
            return b""
        lock = self.lock
        lock.acquire()
        try:
            chunks = self.chunks
            if not chunks:
                return b""
            if self.size <= max_bytes:  # (all of it: the one chunk itself, or the chunks joined)
                out = chunks[0] if len(chunks) == 1 else b"".join(chunks)
                chunks.clear()
                self.size = 0
            else:
                joined = b"".join(chunks)
                out = joined[:max_bytes]
                chunks[:] = [joined[max_bytes:]]
                self.size -= max_bytes
            if not self.size and self._signalled and self.fds_open:
                os.read(self.wake_r, 1)  # type: ignore[arg-type]
                self._signalled = False
            return out
        finally:
            lock.release()

    def release(self) -> None:
        with self.lock:
            if self.fds_open:
                self.fds_open = False
                if self.wake_r is not None:
                    os.close(self.wake_r)
                    os.close(self.wake_w)


class _PairState:
    """What the two ends share: their channels and who is still open."""

    def __init__(self, capacity_bytes: int) -> None:
        self.channels = (_Channel(capacity_bytes), _Channel(capacity_bytes))
        self.open_ends = [True, True]
        self.lock = threading.Lock()


class MemoryTransport(Transport):
    """One end of an in-process byte link. Create with `MemoryTransport.pair()`."""

    #: a read that returns fewer bytes than asked took all that was waiting (readers skip a second read)
    short_read_is_all = True

    def __init__(self, state: _PairState, side: int, name: str = "memory") -> None:
        super().__init__()
        self._state = state
        self._side = side
        self._rx = state.channels[side]
        self._tx = state.channels[1 - side]
        self.endpoint = f"{name}:{'ab'[side]}"
        self.peer: MemoryTransport | None = None
        # each call goes straight to the channel (no method of this class in between)
        self._send_internal = self._tx.put
        self._recv_internal = self._rx.take

    @classmethod
    def pair(
        cls, capacity_bytes: int = DEFAULT_CAPACITY_BYTES, name: str = "memory"
    ) -> tuple[MemoryTransport, MemoryTransport]:
        """Two connected ends; each direction buffers at most ``capacity_bytes`` (bytes)."""
        if capacity_bytes <= 0:
            raise ValueError(f"capacity_bytes must be positive, got {capacity_bytes}")
        state = _PairState(int(capacity_bytes))
        a, b = cls(state, 0, name), cls(state, 1, name)
        a.peer, b.peer = b, a
        return a, b

    @property
    def peer_closed(self) -> bool:
        """True once the other end has been closed."""
        return not self._state.open_ends[1 - self._side]

    def fileno(self) -> int:
        if self._closed:
            raise ValueError(f"{self.endpoint}: fileno on a closed link")
        return self._rx.wake_fd()

    def _send_internal(self, data: bytes) -> int:
        return self._tx.put(data)  # (0 once the peer is closed: nobody reads)

    def _recv_internal(self, max_bytes: int) -> bytes:
        return self._rx.take(max_bytes)

    def _close_internal(self) -> None:
        with self._state.lock:
            self._state.open_ends[self._side] = False
            self._rx.reader_open = False
            if not any(self._state.open_ends):
                for ch in self._state.channels:
                    ch.release()
