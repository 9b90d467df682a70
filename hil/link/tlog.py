"""Recording a command link's frames to a .tlog (pymavlink's format: 8-byte big-endian microseconds, raw
frame): MAVLink 2 and 1 frames, or DJI OPEN-protocol frames, both directions."""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from hil.link.protocols import frame_at

FLUSH_INTERVAL_S = 0.1  # a killed process loses at most this much wall time of recording
_STAMP = struct.Struct(">Q").pack  # a record's stamp: microseconds, big-endian


class TlogWriter:
    """Appends frames stamped ``(epoch_unix_s + time_s)`` in microseconds; flushes every 100 ms of wall time.

    With a simulated clock and a fixed ``epoch_unix_s`` the file is byte-for-byte deterministic.
    """

    def __init__(
        self, path: str | Path, epoch_unix_s: float = 0.0, flush_interval_s: float = FLUSH_INTERVAL_S
    ):
        self.path = Path(path)
        self.epoch_unix_s = epoch_unix_s
        self.flush_interval_s = flush_interval_s
        try:
            self._file: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise OSError(f"cannot write tlog {self.path}: {exc.strerror}") from exc
        self._flush_at = time.monotonic() + flush_interval_s  # (monotonic s) the next flush due
        self.frames = 0

    def record(self, frame: bytes, time_s: float) -> None:
        """Append one frame received or sent at ``time_s`` (clock seconds)."""
        file = self._file
        if file is None:
            return
        stamp_us = round((self.epoch_unix_s + time_s) * 1e6)
        file.write(_STAMP(stamp_us if stamp_us > 0 else 0) + frame)
        self.frames += 1
        if time.monotonic() >= self._flush_at:
            self.flush()

    def tick(self) -> None:
        """Flush if the last flush is older than the flush interval (call it from the main loop too)."""
        if self._file is not None and time.monotonic() >= self._flush_at:
            self.flush()

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()
            self._flush_at = time.monotonic() + self.flush_interval_s

    def close(self) -> None:
        """Flush and close; idempotent."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


@dataclass(frozen=True)
class TlogScan:
    """What a .tlog holds: its good records, and the damaged spots skipped between them."""

    records: list[tuple[int, bytes]]  # (timestamp_us, frame), in file order
    skipped: list[tuple[int, int]]  # (byte offset, bytes skipped) of each damaged spot

    @property
    def skipped_bytes(self) -> int:
        return sum(n for _, n in self.skipped)


def scan_tlog(data: bytes) -> TlogScan:
    """The records of a .tlog's bytes, resynchronising past damage (a cut tail, a flipped byte): a record
    is taken where a timestamp is followed by a whole frame, its CRC good, of a registered protocol
    (`hil.link.protocols`); bytes that start no such record are skipped a byte at a time and reported,
    as mavlogdump does."""
    records: list[tuple[int, bytes]] = []
    skipped: list[tuple[int, int]] = []
    i, n, bad_from = 0, len(data), -1
    while i + 8 < n:
        j = i + 8
        frame = frame_at(data, j)
        if frame is None:
            if bad_from < 0:
                bad_from = i
            i += 1
            continue
        if bad_from >= 0:
            skipped.append((bad_from, i - bad_from))
            bad_from = -1
        records.append((struct.unpack_from(">Q", data, i)[0], frame))
        i = j + len(frame)
    start = bad_from if bad_from >= 0 else i
    if start < n:
        skipped.append((start, n - start))
    return TlogScan(records, skipped)


def read_tlog(path: str | Path) -> list[tuple[int, bytes]]:
    """(timestamp_us, frame) pairs of a .tlog written by TlogWriter (MAVLink 2 and 1 frames, DJI OPEN
    frames); ValueError naming the first damaged spot (`scan_tlog` reads past them)."""
    scan = scan_tlog(Path(path).read_bytes())
    if scan.skipped:
        offset, size = scan.skipped[0]
        raise ValueError(f"{path}: {size} bytes at byte {offset} are no MAVLink or DJI OPEN record")
    return scan.records
