"""Serial-port transport through pyserial: a real UART (/dev/ttyUSB0, /dev/ttyTHS2) or a pty slave.

pyserial opens and configures the port (raw, 8N1, baud); reads and writes then go straight to its
file descriptor without blocking, because pyserial's own zero-timeout write spins while the
kernel buffer is full. What does not fit is dropped and counted.

When the device goes away (USB unplugged, or the pty's master side closed) the next `recv` or
`send` raises LinkError naming the device, unless the transport reconnects (``reconnect_s``, what the
emulator's side of a USB-serial cable does): then the link goes silent (sends dropped and counted,
reads empty), the device path is tried again every ``reconnect_s`` and the link carries on once the
adapter is back. ``fileno()`` stays the same number throughout, so a loop waiting on it need not know.
"""

from __future__ import annotations

import contextlib
import os
import select
import time

import serial

from hil.link.transport import LinkError, Transport, write_nonblocking

DEFAULT_BAUD = 921600


class SerialTransport(Transport):
    """A serial device opened with pyserial at ``baud`` (bit/s), 8N1, no flow control."""

    #: a read that returns fewer bytes than asked took all that was waiting (readers skip a second read)
    short_read_is_all = True

    def __init__(self, device: str, baud: int = DEFAULT_BAUD, *, exclusive: bool = False,
                 reconnect_s: float | None = None) -> None:
        super().__init__()
        if int(baud) <= 0:
            raise ValueError(f"baud must be positive, got {baud}")
        if reconnect_s is not None and not reconnect_s > 0:
            raise ValueError(f"reconnect_s must be positive (s), got {reconnect_s}")
        self.device = device
        self.baud = int(baud)
        self.endpoint = device
        self.exclusive = exclusive
        self.reconnect_s = reconnect_s
        self.connected = True
        self.disconnects = 0  # times the device went away (reconnecting transports only)
        self.reconnects = 0  # times it came back
        self._retry_at = 0.0
        try:
            self._fd = self._open_fd()
        except LinkError:
            self._closed = True
            raise
        os.set_blocking(self._fd, False)
        #: asks whether the device hung up, after an empty read (made once: a read per tick finds nothing)
        self._poller = select.poll()
        self._poller.register(self._fd, select.POLLIN | select.POLLHUP | select.POLLERR)
        #: while disconnected ``_fd`` is the read end of this pipe, which never becomes readable
        self._idle: tuple[int, int] | None = None

    def _open_fd(self) -> int:
        """Open and configure the device (raw, 8N1, baud); returns a file descriptor of our own."""
        try:
            port = serial.Serial(self.device, self.baud, timeout=0, write_timeout=0,
                                 exclusive=self.exclusive or None)
        except (serial.SerialException, OSError, ValueError) as e:
            raise LinkError(f"cannot open serial device {self.device!r} at {self.baud} baud: {e}") from e
        fd = os.dup(port.fileno())  # the settings belong to the device; pyserial's object can go
        with contextlib.suppress(serial.SerialException, OSError):
            port.close()
        return fd

    def fileno(self) -> int:
        if self._closed:
            raise ValueError(f"{self.endpoint}: fileno on a closed link")
        return self._fd

    def _send_internal(self, data: bytes) -> int:
        if not self.connected and not self._try_reconnect():
            return 0  # unplugged: dropped, as a UART with no cable drops it
        try:
            return write_nonblocking(self._fd, f"{self.device} (device gone?)", data)
        except LinkError:
            if self.reconnect_s is None:
                raise
            self._disconnect()
            return 0

    def _recv_internal(self, max_bytes: int) -> bytes:
        if not self.connected and not self._try_reconnect():
            return b""
        try:
            data = os.read(self._fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as e:
            if self.reconnect_s is None:
                raise LinkError(f"{self.device}: read failed (device gone?): {e}") from e
            self._disconnect()
            return b""
        if not data and self._hung_up():
            if self.reconnect_s is None:
                raise LinkError(f"{self.device}: device disconnected (hang-up)")
            self._disconnect()
        return data  # b"": nothing waiting (pyserial sets VMIN=0, so 0 bytes alone is not end of file)

    def _disconnect(self) -> None:
        """The device went away: keep the descriptor's number on a pipe that never reads, retry later."""
        if self._idle is None:
            self._idle = os.pipe()
        os.dup2(self._idle[0], self._fd)
        self.connected = False
        self.disconnects += 1
        self._retry_at = time.monotonic() + (self.reconnect_s or 0.0)

    def _try_reconnect(self) -> bool:
        """Open the device again if it is time to try; True once it is back."""
        now = time.monotonic()
        if now < self._retry_at:
            return False
        self._retry_at = now + (self.reconnect_s or 0.0)
        try:
            fd = self._open_fd()
        except LinkError:
            return False
        os.dup2(fd, self._fd)  # the same number as before, now the device again
        os.close(fd)
        os.set_blocking(self._fd, False)
        self.connected = True
        self.reconnects += 1
        return True

    def _hung_up(self) -> bool:
        return any(ev & (select.POLLHUP | select.POLLERR) for _, ev in self._poller.poll(0))

    def _close_internal(self) -> None:
        for fd in (self._fd, *(self._idle or ())):
            with contextlib.suppress(OSError):
                os.close(fd)
