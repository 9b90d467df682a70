"""Pseudo-terminal transport: the emulator's end of a virtual serial cable.

`PtyTransport.create()` opens a pty pair in raw mode. This object reads and writes the master side;
`endpoint` is the slave path (e.g. "/dev/pts/5"), which the onboard program opens exactly as it
would the companion computer's UART: pyserial ``serial.Serial(path, 921600)``, MAVSDK
``serial:///dev/pts/5:921600``, or `SerialTransport(path, 921600)`.

Behaviour a user can rely on:
- The slave side stays open here too, so a peer may close and reopen the path at any time without
  this end ever seeing EIO.
- With no peer reading, written bytes wait in the kernel's tty buffer (about 20 KiB on Linux 6.x;
  the size is the kernel's). Once it is full, sends accept nothing more: the refused bytes are
  counted in `stats.bytes_dropped`, as a UART with nobody listening loses them. pyserial discards
  such stale bytes when it opens the port; other programs may read them first, so call
  `discard_pending()` when a fresh peer is expected.
- Writes never block (the master is non-blocking); a partial write counts the rest as dropped.
- A pty does not pace bytes at the baud rate: wrap it in `UartTransport` for wire time.
"""

from __future__ import annotations

import functools
import os
import termios
import tty

from hil.link.transport import LinkError, Transport, write_nonblocking

DEFAULT_BAUD = 921600


def set_termios_baud(fd: int, baud: int) -> None:
    """Record ``baud`` in the terminal settings of ``fd`` where the platform has that rate."""
    speed = getattr(termios, f"B{int(baud)}", None)
    if speed is None:
        return
    attrs = termios.tcgetattr(fd)
    attrs[4] = attrs[5] = speed
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


class PtyTransport(Transport):
    """The master side of a raw pseudo-terminal; peers open `endpoint` (the slave path)."""

    #: a read that returns fewer bytes than asked took all that was waiting (readers skip a second read)
    short_read_is_all = True

    def __init__(self, master_fd: int, slave_fd: int, baud: int) -> None:
        super().__init__()
        self._master = master_fd
        self._slave = slave_fd
        self.baud = baud
        self.slave_path = os.ttyname(slave_fd)
        self.endpoint = self.slave_path
        # a send goes straight to the write (no method of this class in between: two writes a tick)
        self._send_internal = functools.partial(write_nonblocking, master_fd, self.endpoint)

    @classmethod
    def create(cls, baud: int = DEFAULT_BAUD) -> PtyTransport:
        """Open a new raw pty; ``baud`` (bit/s) is recorded in its settings for peers to read."""
        if int(baud) <= 0:
            raise ValueError(f"baud must be positive, got {baud}")
        try:
            master, slave = os.openpty()
        except OSError as e:
            raise LinkError(f"cannot open a pseudo-terminal: {e}") from e
        try:
            tty.setraw(slave)
            set_termios_baud(slave, baud)
            os.set_blocking(master, False)
        except (OSError, termios.error) as e:
            os.close(master)
            os.close(slave)
            raise LinkError(f"cannot configure the pseudo-terminal: {e}") from e
        return cls(master, slave, int(baud))

    def fileno(self) -> int:
        if self._closed:
            raise ValueError(f"{self.endpoint}: fileno on a closed link")
        return self._master

    def discard_pending(self) -> None:
        """Drop bytes written here that no peer has read yet (and any unread input)."""
        if not self._closed:
            termios.tcflush(self._slave, termios.TCIFLUSH)
            termios.tcflush(self._master, termios.TCIFLUSH)

    def _send_internal(self, data: bytes) -> int:
        return write_nonblocking(self._master, self.endpoint, data)

    def _recv_internal(self, max_bytes: int) -> bytes:
        try:
            return os.read(self._master, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as e:
            raise LinkError(f"{self.endpoint}: read failed: {e}") from e

    def _close_internal(self) -> None:
        os.close(self._master)
        os.close(self._slave)
