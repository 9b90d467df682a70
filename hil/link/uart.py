"""UART pacing of a live link: bytes leave at the configured baud (10 bits a byte, 8N1, as in the
channel model `hil.link.channel`) one by one, and a full transmit buffer drops bytes, as a real UART
does. (The channel model's `UartWire` hands over whole messages on simulated time; this releases
bytes as they leave, on any clock, for transports in real time.)

`UartModel` sits on the sending side: `write()` queues bytes into a transmit buffer of
``tx_buffer_bytes`` (dropping and counting the excess), and `pump()` hands out exactly the bytes
whose last bit has left the wire by ``clock.now_s()``. With a `SimClock` the timing is exact in
simulated time; with a `WallClock` it follows real time, as closely as `pump()` is called.

`UartTransport` wraps any transport with a `UartModel` on its sending side; `UartTransport.pair()`
is an in-process serial cable (two memory ends, each paced by a UART, where reading one end also
pumps the other end's UART, so nobody has to drive the pacing by hand).
"""

from __future__ import annotations

import math
import select
from collections import deque

from hil.link.channel import BITS_PER_BYTE
from hil.link.clock import Clock, WallClock
from hil.link.memory import MemoryTransport
from hil.link.transport import Transport

DEFAULT_TX_BUFFER_BYTES = 4096
_EPS_BYTES = 1e-6  # tolerance on byte counts for floating-point times


class UartModel:
    """A transmit FIFO draining at ``baud`` bit/s on ``clock`` (s)."""

    def __init__(self, baud: int, tx_buffer_bytes: int = DEFAULT_TX_BUFFER_BYTES, clock: Clock | None = None):
        if int(baud) <= 0:
            raise ValueError(f"baud must be positive, got {baud}")
        if int(tx_buffer_bytes) <= 0:
            raise ValueError(f"tx_buffer_bytes must be positive, got {tx_buffer_bytes}")
        self.baud = int(baud)
        self.tx_buffer_bytes = int(tx_buffer_bytes)
        self.clock: Clock = clock if clock is not None else WallClock()
        self.byte_time_s = BITS_PER_BYTE / self.baud
        # segments of back-to-back bytes: (time the first byte's start bit begins (s), bytes)
        self._queue: deque[tuple[float, bytes]] = deque()
        self._queued_bytes = 0
        self.bytes_dropped = 0
        self.bytes_released = 0

    def wire_time_s(self, n_bytes: int) -> float:
        """Time ``n_bytes`` take on the wire (s): n * 10 / baud."""
        return n_bytes * BITS_PER_BYTE / self.baud

    @property
    def queued_bytes(self) -> int:
        """Bytes written but not yet released (whether or not their time has come)."""
        return self._queued_bytes

    def backlog_bytes(self) -> int:
        """Bytes in the transmit buffer now (written, their last bit not yet on the wire)."""
        return self._in_buffer_bytes(self.clock.now_s())

    def free_bytes(self) -> int:
        """Room left in the transmit buffer now (bytes)."""
        return self.tx_buffer_bytes - self.backlog_bytes()

    def write(self, data: bytes) -> int:
        """Queue ``data``; return how many bytes fit in the transmit buffer (the rest is dropped).

        Bytes whose wire time has passed no longer occupy the buffer, even before `pump()`.
        """
        now = self.clock.now_s()
        free = self.tx_buffer_bytes - self._in_buffer_bytes(now)
        n = max(0, min(len(data), free))
        self.bytes_dropped += len(data) - n
        if n:
            start = max(now, self._line_free_at_s())
            self._queue.append((start, bytes(data[:n])))
            self._queued_bytes += n
        return n

    def pump(self) -> bytes:
        """Release and return the bytes whose wire time has elapsed on the clock."""
        now = self.clock.now_s()
        out = bytearray()
        while self._queue:
            start, data = self._queue[0]
            n = min(len(data), math.floor((now - start) / self.byte_time_s + _EPS_BYTES))
            if n <= 0:
                break
            out += data[:n]
            if n == len(data):
                self._queue.popleft()
            else:
                self._queue[0] = (start + n * self.byte_time_s, data[n:])
                break
        self._queued_bytes -= len(out)
        self.bytes_released += len(out)
        return bytes(out)

    def next_release_s(self) -> float | None:
        """Clock time (s) at which the next queued byte has fully left the wire; None if idle."""
        if not self._queue:
            return None
        return self._queue[0][0] + self.byte_time_s

    # --- internals -----------------------------------------------------------------------
    def _line_free_at_s(self) -> float:
        if not self._queue:
            return -math.inf
        start, data = self._queue[-1]
        return start + len(data) * self.byte_time_s

    def _in_buffer_bytes(self, now: float) -> int:
        """Bytes still occupying the transmit buffer at ``now`` (not yet fully on the wire)."""
        if not self._queue:
            return 0
        end = self._line_free_at_s()
        return min(self._queued_bytes, max(0, math.ceil((end - now) / self.byte_time_s - _EPS_BYTES)))


class UartTransport(Transport):
    """Any transport with UART pacing on its sending side; `recv` passes straight through.

    `send` queues into the UART (excess dropped and counted in `stats.bytes_dropped`); queued bytes
    reach ``inner`` on `pump()`, which also runs on every `send` and `recv`. Closing drops
    whatever is still queued (as powering a UART off does) and closes ``inner``.
    """

    def __init__(
        self,
        inner: Transport,
        baud: int,
        clock: Clock | None = None,
        tx_buffer_bytes: int = DEFAULT_TX_BUFFER_BYTES,
    ) -> None:
        super().__init__()
        self.inner = inner
        self.uart = UartModel(baud, tx_buffer_bytes, clock)
        self.endpoint = inner.endpoint
        self._peer: UartTransport | None = None

    @classmethod
    def pair(
        cls,
        baud: int,
        clock: Clock | None = None,
        tx_buffer_bytes: int = DEFAULT_TX_BUFFER_BYTES,
        capacity_bytes: int = 65536,
    ) -> tuple[UartTransport, UartTransport]:
        """An in-process serial cable: two memory ends, each paced at ``baud`` on one ``clock``."""
        clock = clock if clock is not None else WallClock()
        a_mem, b_mem = MemoryTransport.pair(capacity_bytes, name="uart")
        a, b = cls(a_mem, baud, clock, tx_buffer_bytes), cls(b_mem, baud, clock, tx_buffer_bytes)
        a._peer, b._peer = b, a
        return a, b

    @property
    def baud(self) -> int:
        return self.uart.baud

    def pump(self) -> int:
        """Hand the bytes whose wire time has elapsed to ``inner``; returns how many were released."""
        if self._closed:
            return 0
        released = self.uart.pump()
        if released:
            self.inner.send(released)
        return len(released)

    def next_release_s(self) -> float | None:
        """Clock time (s) when `pump()` next has a byte to release; None while idle."""
        return self.uart.next_release_s()

    def fileno(self) -> int:
        return self.inner.fileno()

    def _send_internal(self, data: bytes) -> int:
        self.pump()
        n = self.uart.write(data)
        self.pump()
        return n

    def _recv_internal(self, max_bytes: int) -> bytes:
        self.pump()
        if self._peer is not None:
            self._peer.pump()
        return self.inner.recv(0.0, max_bytes)

    def _wait_readable(self, timeout_s: float | None) -> None:
        if isinstance(self.uart.clock, WallClock):
            now = self.uart.clock.now_s()
            for model in (self.uart, None if self._peer is None else self._peer.uart):
                nxt = None if model is None else model.next_release_s()
                if nxt is not None:
                    wait = max(0.0, nxt - now)
                    timeout_s = wait if timeout_s is None else min(timeout_s, wait)
        select.select([self.inner.fileno()], [], [], timeout_s)

    def _close_internal(self) -> None:
        self.inner.close()
