"""The emulated N3's telemetry subscription (command set 0x0B): packages of topics the onboard side adds,
checked as DJI's subscription rules say, answered with their one-byte codes, and when each is due.

Codes and rules: docs/dji-open-link.md; topics and their layouts: `hil.link.dji_open.TOPICS`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from hil.link import dji_open as dj


@dataclass
class Package:
    """One subscribed package: its topics (UIDs, in order), rate asked (Hz), time stamp, next push (s),
    and the rate it is pushed at (Hz: the rate asked, or less where the line's budget cannot carry it)."""

    uids: tuple[int, ...]
    hz: int
    timestamp: bool
    next_due_s: float
    granted_hz: float

    @property
    def data_bytes(self) -> int:
        """Its topics' bytes in a push (time stamp included; the package id byte not)."""
        return topics_bytes(self.uids, self.timestamp)


def topics_bytes(uids: tuple[int, ...], timestamp: bool) -> int:
    """The bytes of topics ``uids`` (known UIDs) in a push, with the time stamp when ``timestamp``."""
    return (dj.SUB_TIMESTAMP_BYTES if timestamp else 0) + sum(dj.TOPIC_STRUCTS[u].size for u in uids)


class Subscriptions:
    """The packages (0-4) the onboard side has added; ``served``: the topic names this FC can report."""

    def __init__(self, served: frozenset[str]) -> None:
        self.served = served
        self.packages: dict[int, Package] = {}
        #: when the next package is due (s; infinite without packages): kept by every change here, so
        #: that a poll asks it with one comparison
        self.next_s = math.inf

    def add(self, payload: bytes, now_s: float) -> int:
        """Add the package a 0x0B 0x01 payload describes; its code (`dj.SUB_*`)."""
        head = dj.SUB_PACKAGE_HEAD
        if len(payload) < head.size:
            return dj.SUB_ILLEGAL_DATA_LENGTH
        pkg, hz, config, n = head.unpack_from(payload)
        if len(payload) != head.size + 4 * n:
            return dj.SUB_ILLEGAL_DATA_LENGTH
        if pkg >= dj.SUB_MAX_PACKAGES:
            return dj.SUB_PACKAGE_OUT_OF_RANGE
        if pkg in self.packages:
            return dj.SUB_PACKAGE_EXISTS
        if n == 0:
            return dj.SUB_PACKAGE_EMPTY
        uids = struct.unpack_from(f"<{n}I", payload, head.size)
        taken = {u for p in self.packages.values() for u in p.uids}
        if len(set(uids)) != n or taken.intersection(uids):
            return dj.SUB_MULTIPLE_SUBSCRIBE  # a topic is subscribed once
        code = self._check_topics(uids, hz, bool(config & 1))
        if code == dj.SUB_SUCCESS:
            self.packages[pkg] = Package(uids, hz, bool(config & 1), now_s, float(hz))
            self._reschedule()
        return code

    def _check_topics(self, uids: tuple[int, ...], hz: int, timestamp: bool) -> int:
        for uid in uids:
            if uid in dj.RTK_TOPICS:
                return dj.SUB_SOURCE_OFFLINE  # no RTK receiver on this N3
            if uid not in dj.TOPICS or dj.TOPICS[uid][0] not in self.served:
                return dj.SUB_ILLEGAL_UID
            if hz not in dj.SUB_FREQUENCIES_HZ or hz > dj.TOPICS[uid][2]:
                return dj.SUB_ILLEGAL_FREQUENCY
        too_large = topics_bytes(uids, timestamp) > dj.SUB_MAX_PACKAGE_BYTES
        return dj.SUB_PACKAGE_TOO_LARGE if too_large else dj.SUB_SUCCESS

    def remove(self, payload: bytes) -> int:
        """Remove the package a 0x0B 0x03 payload names; its code."""
        if len(payload) != 1:
            return dj.SUB_ILLEGAL_DATA_LENGTH
        if payload[0] >= dj.SUB_MAX_PACKAGES:
            return dj.SUB_PACKAGE_OUT_OF_RANGE
        if self.packages.pop(payload[0], None) is None:
            return dj.SUB_PACKAGE_MISSING
        self._reschedule()
        return dj.SUB_SUCCESS

    def reset(self) -> int:
        self.packages.clear()
        self._reschedule()
        return dj.SUB_SUCCESS

    def due(self, now_s: float) -> list[tuple[int, Package]]:
        """The packages due at ``now_s`` (s), their next push scheduled (at the rate granted)."""
        out = []
        for pkg, p in self.packages.items():
            if now_s >= p.next_due_s - 1e-9:
                nxt = p.next_due_s + 1.0 / p.granted_hz
                p.next_due_s = nxt if nxt > now_s else now_s + 1.0 / p.granted_hz
                out.append((pkg, p))
        if out:
            self._reschedule()
        return out

    def _reschedule(self) -> None:
        nxt = math.inf  # (the earliest package's next push: a loop, where min() would run a generator)
        for p in self.packages.values():
            if p.next_due_s < nxt:
                nxt = p.next_due_s
        self.next_s = nxt
