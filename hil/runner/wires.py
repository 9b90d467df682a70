"""The command link as the emulator sees it in a run: per-message latency, jitter and loss (with
Gilbert-Elliott bursts), UART wire time at the link's baud, and the link faults, in both directions,
on simulated time.

`CommandWire` is the Transport under the FC's MAVLink codec. Frames the FC sends are queued with their
arrival time and written to the real link (memory end or pty master) by `pump()`; bytes the onboard
program wrote are split into frames by the runner (`FrameSplitter`), each given an arrival time, and
read by the FC's codec once the SimClock has reached it. Lockstep ticks and their answers are the
harness's own traffic: they bypass the model, the faults and the FC (`send_sync`).
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from dataclasses import dataclass, fields

import numpy as np

from hil.link.clock import SimClock
from hil.link.transport import Transport, wait_readable
from hil.runner.faults import FaultSchedule, corrupt
from hil.scenario.schema import LinkSpec

BITS_PER_BYTE = 10  # 8N1
MAVLINK_V2_MAGIC, MAVLINK_V1_MAGIC = 0xFD, 0xFE
TIMESYNC_MSG_ID = 111


@dataclass(frozen=True)
class LinkModel:
    """Per-message behaviour of one link direction (s, bit/s, probabilities)."""

    baud: int = 921600
    latency_s: float = 0.0
    jitter_s: float = 0.0
    loss: float = 0.0
    burst_p_gb: float = 0.0
    burst_p_bg: float = 1.0

    @classmethod
    def from_spec(cls, spec: LinkSpec) -> LinkModel:
        burst = spec.burst
        return cls(
            baud=spec.baud,
            latency_s=spec.latency_ms * 1e-3,
            jitter_s=spec.jitter_ms * 1e-3,
            loss=spec.loss,
            burst_p_gb=0.0 if burst is None else burst.p_gb,
            burst_p_bg=1.0 if burst is None else burst.p_bg,
        )


@dataclass
class DirectionStats:
    """What happened to the frames of one direction (counts)."""

    frames_sent: int = 0
    frames_delivered: int = 0
    frames_lost: int = 0  # by the link model (loss, bursts)
    frames_dropped_fault: int = 0  # by command_link_down
    bytes_delivered: int = 0
    bytes_corrupted: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class _Channel:
    """Loss, latency and jitter then the UART: gives each accepted frame its arrival time (s)."""

    def __init__(self, model: LinkModel, rng: np.random.Generator) -> None:
        self.model = model
        self.rng = rng
        self.byte_time_s = BITS_PER_BYTE / model.baud
        self._bad = False
        self._line_free_s = -math.inf
        self._last_arrival_s = -math.inf

    def arrival_s(self, now_s: float, n_bytes: int) -> float | None:
        """When a frame of ``n_bytes`` handed over at ``now_s`` arrives, or None if the link loses it."""
        m, rng = self.model, self.rng
        if m.burst_p_gb > 0:
            self._bad = (rng.random() >= m.burst_p_bg) if self._bad else (rng.random() < m.burst_p_gb)
            if self._bad:
                return None
        if m.loss > 0 and rng.random() < m.loss:
            return None
        start = max(now_s, self._line_free_s)  # the UART sends one frame after the other
        self._line_free_s = start + n_bytes * self.byte_time_s
        latency = m.latency_s
        if m.jitter_s > 0:
            latency = max(0.0, latency + rng.normal(0.0, m.jitter_s))
        arrival = max(self._line_free_s + latency, self._last_arrival_s)  # a serial link keeps order
        self._last_arrival_s = arrival
        return arrival


class FrameSplitter:
    """Cuts a MAVLink byte stream into frames by their length fields (no CRC check: the FC's codec does
    that); bytes before a frame start are passed on as they are."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        buf = self._buf
        buf += data
        out: list[bytes] = []
        i = 0
        n = len(buf)
        while i < n:
            magic = buf[i]
            if magic == MAVLINK_V2_MAGIC:
                if i + 3 > n:
                    break
                size = 12 + buf[i + 1] + (13 if buf[i + 2] & 0x01 else 0)
            elif magic == MAVLINK_V1_MAGIC:
                if i + 2 > n:
                    break
                size = 8 + buf[i + 1]
            else:
                j = i + 1
                while j < n and buf[j] not in (MAVLINK_V2_MAGIC, MAVLINK_V1_MAGIC):
                    j += 1
                out.append(bytes(buf[i:j]))
                i = j
                continue
            if i + size > n:
                break
            out.append(bytes(buf[i : i + size]))
            i += size
        del buf[:i]
        return out


def timesync_answer_ns(frame: bytes) -> int | None:
    """The tick time (ns) of a lockstep answer (TIMESYNC with tc1 == ts1 != 0), else None."""
    if len(frame) < 12 or frame[0] != MAVLINK_V2_MAGIC:
        return None
    if frame[7] | frame[8] << 8 | frame[9] << 16 != TIMESYNC_MSG_ID:
        return None
    payload = bytes(frame[10 : 10 + frame[1]]).ljust(16, b"\x00")  # MAVLink 2 trims trailing zeros
    tc1 = int.from_bytes(payload[0:8], "little", signed=True)
    ts1 = int.from_bytes(payload[8:16], "little", signed=True)
    return tc1 if tc1 == ts1 and tc1 != 0 else None


class CommandWire(Transport):
    """The FC's end of the command link in a run (see the module docstring)."""

    def __init__(
        self,
        raw: Transport,
        clock: SimClock,
        model: LinkModel,
        rng: np.random.Generator,
        faults: FaultSchedule,
    ) -> None:
        super().__init__()
        self.raw = raw
        self.clock = clock
        self.faults = faults
        self.endpoint = raw.endpoint
        out_rng, in_rng, self._corrupt_rng = rng.spawn(3)
        self._out = _Channel(model, out_rng)
        self._in = _Channel(model, in_rng)
        self._out_queue: list[tuple[float, int, bytes]] = []
        self._in_queue: list[tuple[float, int, bytes]] = []
        self._seq = 0
        self.splitter = FrameSplitter()
        self.to_onboard = DirectionStats()
        self.to_fc = DirectionStats()
        self.setpoints_sent = 0  # SET_ATTITUDE_TARGET frames the onboard program wrote
        self._backlog: deque[bytes] = deque()  # onboard frames read, not yet handed to the link
        #: wall time `read_raw` polls before it sleeps (lockstep: the answer is expected within it)
        self.spin_s = 0.0
        self._unanswered: list[bytes] = []  # frames taken from the backlog whose answer has not come
        self._answered_later: dict[int, list[bytes]] = {}  # tick ns -> its frames, answered out of turn
        #: hold pumped FC frames until the next `send_sync` / `flush` (lockstep: one write per tick)
        self.hold_output = False
        self._held = bytearray()
        try:
            self._fd: int | None = raw.fileno()
        except (NotImplementedError, OSError, ValueError):
            self._fd = None

    # --- FC -> onboard --------------------------------------------------------------------------
    def _send_internal(self, data: bytes) -> int:
        self.to_onboard.frames_sent += 1
        arrival = self._out.arrival_s(self.clock.now_s(), len(data))
        if arrival is None:
            self.to_onboard.frames_lost += 1
        else:
            self._seq += 1
            heapq.heappush(self._out_queue, (arrival, self._seq, data))
        return len(data)

    def pump(self) -> int:
        """Write to the real link the FC frames that have arrived by now; returns bytes written (or
        held: with ``hold_output`` set they wait for the next `send_sync` or `flush`)."""
        data = self._drain(self._out_queue, self.to_onboard)
        if not data:
            return 0
        if self.hold_output:
            self._held += data
            return len(data)
        return self.raw.send(data) if not self.raw.closed else 0

    def send_sync(self, frame: bytes) -> None:
        """Write a lockstep tick straight to the real link (no model, no faults, not seen by the FC),
        after the held FC frames, in one write."""
        if self._held:
            frame = bytes(self._held) + frame
            self._held.clear()
        if not self.raw.closed:
            self.raw.send(frame)

    def flush(self) -> None:
        """Write the held FC frames now."""
        if self._held:
            data = bytes(self._held)
            self._held.clear()
            if not self.raw.closed:
                self.raw.send(data)

    # --- onboard -> FC --------------------------------------------------------------------------
    def read_raw(self, timeout_s: float = 0.0) -> bool:
        """Read what the onboard program wrote into the backlog of frames not yet handed to the link;
        False when nothing came within ``timeout_s`` (wall s)."""
        fd = self._fd
        data = b""
        if timeout_s > 0 and fd is not None and not self.raw.closed:
            # one read first (the bytes are often there already: no poll for them), else wait for
            # them and read once
            data = self.raw.recv(0.0)
            if not data:
                if not wait_readable([fd], timeout_s, self.spin_s):
                    return False
                timeout_s = 0.0
        if not data:
            data = self.raw.recv(timeout_s)
        if not data:
            return False
        self._backlog.extend(self.splitter.feed(data))
        return True

    def read_onboard(self, timeout_s: float = 0.0) -> bool:
        """Read what the onboard program wrote and queue all of it for the FC, handed to the link now
        (real time; a lockstep answer is the harness's, not the FC's: dropped). False when nothing
        came in time."""
        got = self.read_raw(timeout_s)
        now = self.clock.now_s()
        backlog = self._backlog
        while backlog:
            frame = backlog.popleft()
            if timesync_answer_ns(frame) is None:
                self._queue_for_fc(frame, now)
        return got

    def take_until_answer(self, tick_ns: int, stamp_s: float) -> bool:
        """Queue for the FC, handed to the link at ``stamp_s`` (s), what the onboard program wrote for
        the tick at ``tick_ns`` (the frames before its answer); True once that answer has come. Frames
        answered for a later tick (this one's TIMESYNC was lost to corrupt bytes and sent again) wait
        for their own tick; what follows the last answer (the next tick's outputs) stays."""
        stashed = self._answered_later.pop(tick_ns, None)
        if stashed is not None:
            for frame in stashed:
                self._queue_for_fc(frame, stamp_s)
            return True
        backlog, frames = self._backlog, self._unanswered
        while backlog:
            frame = backlog.popleft()
            answered = timesync_answer_ns(frame)
            if answered is None:
                frames.append(frame)
                continue
            self._unanswered = []
            if answered > tick_ns:
                self._answered_later[answered] = frames
            else:  # this tick's answer, or one to a tick sent twice (nothing new in front of it)
                for f in frames:
                    self._queue_for_fc(f, stamp_s)
                if answered == tick_ns:
                    return True
            frames = self._unanswered
        return False

    def answered_later_than(self, tick_ns: int) -> bool:
        """Whether the onboard program has answered a tick after ``tick_ns`` (so it never saw that one)."""
        return any(k > tick_ns for k in self._answered_later)

    def _queue_for_fc(self, frame: bytes, handed_s: float) -> None:
        if len(frame) > 9 and frame[0] == MAVLINK_V2_MAGIC and frame[7] == 82 and frame[8] == frame[9] == 0:
            self.setpoints_sent += 1
        self.to_fc.frames_sent += 1
        arrival = self._in.arrival_s(handed_s, len(frame))
        if arrival is None:
            self.to_fc.frames_lost += 1
            return
        self._seq += 1
        heapq.heappush(self._in_queue, (arrival, self._seq, frame))

    def next_arrival_s(self) -> float:
        """When the next onboard frame reaches the FC (s; inf when none is on the way)."""
        return self._in_queue[0][0] if self._in_queue else math.inf

    def _recv_internal(self, max_bytes: int) -> bytes:
        return self._drain(self._in_queue, self.to_fc)

    def _drain(self, q: list, st: DirectionStats) -> bytes:
        """The frames of queue ``q`` that have arrived by now, with the link's faults applied."""
        now = self.clock.now_s()
        chunks = []
        while q and q[0][0] <= now + 1e-12:
            t, _, frame = heapq.heappop(q)
            frame = self._apply_faults(frame, t, st)
            if frame is not None:
                chunks.append(frame)
        return b"".join(chunks)

    def _apply_faults(self, frame: bytes, time_s: float, st: DirectionStats) -> bytes | None:
        if not self.faults.has_command_faults:
            st.frames_delivered += 1
            st.bytes_delivered += len(frame)
            return frame
        if self.faults.any_active("command_link_down", time_s):
            st.frames_dropped_fault += 1
            return None
        frac = self.faults.corrupt_fraction("command", time_s)
        if frac > 0:
            frame, flipped = corrupt(frame, frac, self._corrupt_rng)
            st.bytes_corrupted += flipped
        st.frames_delivered += 1
        st.bytes_delivered += len(frame)
        return frame

    def fileno(self) -> int:
        return self.raw.fileno()

    def _wait_readable(self, timeout_s: float | None) -> None:
        return  # the FC's codec only ever polls (timeout 0)

    def _close_internal(self) -> None:
        self.raw.close()
