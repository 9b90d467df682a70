"""Serial-port transport through pyserial: a real UART (/dev/ttyUSB0, /dev/ttyTHS2) or a pty slave.

pyserial opens and configures the port (raw, 8N1, baud); reads and writes then go straight to its
file descriptor without blocking, because pyserial's own zero-timeout write spins while the
kernel buffer is full. What does not fit is dropped and counted.

When the device goes away (USB unplugged, or the pty's master side closed) the next `recv` or
`send` raises LinkError naming the device.
"""

from __future__ import annotations

import contextlib
import os
import select

import serial

from hil.link.transport import LinkError, Transport, write_nonblocking

DEFAULT_BAUD = 921600


class SerialTransport(Transport):
    """A serial device opened with pyserial at ``baud`` (bit/s), 8N1, no flow control."""

    #: a read that returns fewer bytes than asked took all that was waiting (readers skip a second read)
    short_read_is_all = True

    def __init__(self, device: str, baud: int = DEFAULT_BAUD, *, exclusive: bool = False) -> None:
        super().__init__()
        if int(baud) <= 0:
            raise ValueError(f"baud must be positive, got {baud}")
        self.device = device
        self.baud = int(baud)
        self.endpoint = device
        try:
            self._port = serial.Serial(
                device, self.baud, timeout=0, write_timeout=0, exclusive=exclusive or None
            )
        except (serial.SerialException, OSError, ValueError) as e:
            self._closed = True
            raise LinkError(f"cannot open serial device {device!r} at {baud} baud: {e}") from e
        self._fd = self._port.fileno()
        os.set_blocking(self._fd, False)
        #: asks whether the device hung up, after an empty read (made once: a read per tick finds nothing)
        self._poller = select.poll()
        self._poller.register(self._fd, select.POLLIN | select.POLLHUP | select.POLLERR)

    def fileno(self) -> int:
        if self._closed:
            raise ValueError(f"{self.endpoint}: fileno on a closed link")
        return self._fd

    def _send_internal(self, data: bytes) -> int:
        return write_nonblocking(self._fd, data, f"{self.device} (device gone?)")

    def _recv_internal(self, max_bytes: int) -> bytes:
        try:
            data = os.read(self._fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as e:
            raise LinkError(f"{self.device}: read failed (device gone?): {e}") from e
        if not data and self._hung_up():
            raise LinkError(f"{self.device}: device disconnected (hang-up)")
        return data  # b"": nothing waiting (pyserial sets VMIN=0, so 0 bytes alone is not end of file)

    def _hung_up(self) -> bool:
        return any(ev & (select.POLLHUP | select.POLLERR) for _, ev in self._poller.poll(0))

    def _close_internal(self) -> None:
        with contextlib.suppress(serial.SerialException, OSError):
            self._port.close()
