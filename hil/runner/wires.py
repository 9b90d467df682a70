"""The command link as the emulator sees it in a run: the link channel model (`hil.link.channel`: loss
with bursts, latency, jitter, UART wire time at the link's baud) and the link faults, in both
directions, on simulated time.

`CommandWire` is the Transport under the FC's MAVLink codec. Frames the FC sends are queued with their
arrival time and written to the real link (memory end or pty master) by `pump()`; bytes the onboard
program wrote are split into frames (the protocol's splitter, `hil.link.lockstep.framing`), each given
an arrival time, and read by the FC's codec once the SimClock has reached it. Lockstep ticks and their
answers are the harness's own traffic: they bypass the model, the faults and the FC (`send_sync`).
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from dataclasses import dataclass, fields

import numpy as np
from numba import njit
from numba.extending import register_jitable

from emulator.kernel_cache import entry
from hil.link.channel import (
    CH_JITTER,
    CH_NEXT,
    CHANNEL_STATE_LEN,
    JITTER_BLOCK,
    UART_STATE_LEN,
    Channel,
    ChannelModel,
    UartWire,
    block_arrival_s,
    delivery_s,
    wire_finish_s,
)
from hil.link.clock import SimClock
from hil.link.lockstep import Framing
from hil.link.protocols import framing
from hil.link.transport import Transport, Waiter
from hil.runner.faults import FaultSchedule
from hil.scenario.schema import LinkSpec


def channel_model(spec: LinkSpec) -> ChannelModel:
    """The channel model of a scenario's link (the file's names and units mapped here, once)."""
    burst = spec.burst
    return ChannelModel(
        latency_s=spec.latency_ms * 1e-3,
        jitter_s=spec.jitter_ms * 1e-3,
        loss_prob=spec.loss,
        burst_enter_prob=0.0 if burst is None else burst.p_gb,
        burst_exit_prob=1.0 if burst is None else burst.p_bg,
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


for _plain in (delivery_s, block_arrival_s, wire_finish_s):  # (compiled into `_arrival_kernel`)
    register_jitable(_plain)


@njit(cache=True)
def _arrival_kernel(st: np.ndarray, now_s: float, n_bytes: int) -> float:
    """`_Direction.arrival_s` of a channel that cannot lose, on the direction's state ``st`` (its UART's
    numbers, then its channel's): the frame booked on the UART (`wire_finish_s`), then carried by the
    channel (`block_arrival_s`); its arrival (s), or NaN with nothing done when the channel's jitter draws
    are spent (draw the next block, then call again)."""
    chan = st[UART_STATE_LEN:]
    if chan[CH_JITTER] > 0 and chan[CH_NEXT] >= JITTER_BLOCK:
        return math.nan
    return block_arrival_s(chan, wire_finish_s(st[:UART_STATE_LEN], now_s, n_bytes))


class _Direction:
    """One direction: the channel (loss, latency, jitter, order) behind the UART at the link's baud. A
    channel that cannot lose keeps its and its UART's numbers in one array, and a frame goes through both
    in one compiled call (`_arrival_kernel`); one that can draws per frame from its generator."""

    def __init__(self, model: ChannelModel, baud: int, rng: np.random.Generator) -> None:
        self.state: np.ndarray | None = None
        self._kernel = None
        if not model.can_lose:
            self.state = np.zeros(UART_STATE_LEN + CHANNEL_STATE_LEN)
            self.channel = Channel(model, rng, self.state[UART_STATE_LEN:])
            self.uart = UartWire(baud, state=self.state[:UART_STATE_LEN])
            self._kernel = entry(_arrival_kernel, self.state, 0.0, 0)
        else:
            self.channel = Channel(model, rng)
            self.uart = UartWire(baud)
        self._drop, self._arrival_s, self._finish_s = self.channel.drop, self.channel.arrival_s, \
            self.uart.finish_s

    def arrival_s(self, now_s: float, n_bytes: int) -> float | None:
        """When a frame of ``n_bytes`` handed over at ``now_s`` arrives, or None if the link loses it."""
        kernel = self._kernel
        if kernel is not None:
            arrival = kernel(self.state, now_s, n_bytes)
            if arrival == arrival:
                return arrival
            self.channel.draw_block()  # (NaN: the jitter draws are spent)
            return kernel(self.state, now_s, n_bytes)
        if self._drop() is not None:
            return None
        return self._arrival_s(self._finish_s(now_s, n_bytes))


class CommandWire(Transport):
    """The FC's end of the command link in a run (see the module docstring)."""

    def __init__(
        self,
        raw: Transport,
        clock: SimClock,
        spec: LinkSpec,
        rng: np.random.Generator,
        faults: FaultSchedule,
        wire_framing: Framing | None = None,
    ) -> None:
        """``wire_framing``: the command link's protocol as the harness cuts and reads it (default
        MAVLink with the FC's ids 1, 1)."""
        super().__init__()
        self.framing = wire_framing or framing("mavlink")
        self.raw = raw
        self.clock = clock
        self.faults = faults
        self.endpoint = raw.endpoint
        out_rng, in_rng, self._corrupt_rng = rng.spawn(3)
        model = channel_model(spec)
        self._out = _Direction(model, spec.baud, out_rng)
        self._in = _Direction(model, spec.baud, in_rng)
        self._out_queue: list[tuple[float, int, bytes]] = []
        self._in_queue: list[tuple[float, int, bytes]] = []
        #: when the FC's codec next has something to read (s): the first arrival in the queue to the FC
        #: (inf: none on the way), -inf once this end is closed (its read then says so); an FC server's
        #: poll compares it with its time (`emulator.servers.arrivals`)
        self.next_input_s = math.inf
        self._seq = 0
        self.splitter = self.framing.splitter()
        self._answered_ns = self.framing.answered_ns
        self._is_setpoint = self.framing.is_setpoint
        self.to_onboard = DirectionStats()
        self.to_fc = DirectionStats()
        self.setpoints_sent = 0  # setpoint frames the onboard program wrote
        #: real time: the onboard computer's modelled compute time (s); what the program writes is handed
        #: to the link this long after it is read, as lockstep hands a tick's outputs over (`read_onboard`)
        self.compute_s = 0.0
        self._backlog: deque[bytes] = deque()  # onboard frames read, not yet handed to the link
        #: wall time `read_raw` polls before it sleeps (lockstep: the answer is expected within it)
        self.spin_s = 0.0
        self._unanswered: list[bytes] = []  # frames taken from the backlog whose answer has not come
        self._answered_later: dict[int, list[bytes]] = {}  # tick ns -> its frames, answered out of turn
        #: hold pumped FC frames until the next `send_sync` / `flush` (lockstep: one write per tick)
        self.hold_output = False
        self._held = bytearray()
        #: the wait on the real link's descriptor (`_waiter`), made when a read first waits: a memory
        #: link makes its wake-up pipe only then (an in-process run's reads find the bytes there, and
        #: the pipe would cost a write and a read a tick); False: the link has no descriptor
        self._wait: Waiter | bool | None = None

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
        q = self._out_queue
        if not q:  # (most ticks: no FC frame on the way)
            return 0
        data = self._drain(q, self.to_onboard)
        if not data:
            return 0
        if self.hold_output:
            self._held += data
            return len(data)
        return self.raw.send(data) if not self.raw.closed else 0

    def send_sync(self, frame: bytes) -> None:
        """Write a lockstep tick straight to the real link (no model, no faults, not seen by the FC),
        after the held FC frames, in one write."""
        held = self._held
        if held:
            held += frame
            frame = bytes(held)
            held.clear()
        if not self.raw.closed:
            self.raw.send(frame)

    def discard_held(self) -> None:
        """Drop the held FC frames unwritten (counted in the raw link's ``bytes_dropped``): the first
        tick's, which a program opening its port would get or not depending on how fast it starts."""
        self.raw.stats.bytes_dropped += len(self._held)
        self._held.clear()

    def flush(self) -> None:
        """Write the held FC frames now."""
        if self._held:
            data = bytes(self._held)
            self._held.clear()
            if not self.raw.closed:
                self.raw.send(data)

    # --- onboard -> FC --------------------------------------------------------------------------
    def _waiter(self) -> Waiter | None:
        """The wait on the real link's descriptor (made at the first call), None where it has none."""
        wait = self._wait
        if wait is None:
            try:
                wait = Waiter([self.raw.fileno()])
            except (NotImplementedError, OSError, ValueError):
                wait = False
            self._wait = wait
        return wait or None

    def read_raw(self, timeout_s: float = 0.0, *, read_first: bool = True) -> bool:
        """Read what the onboard program wrote into the backlog of frames not yet handed to the link;
        False when nothing came within ``timeout_s`` (wall s). With a timeout the link is read once
        first (the bytes are often there already: no wait for them), unless ``read_first`` is False (a
        read has just found nothing), then waited on and read once."""
        raw = self.raw
        data = b""
        waiter = self._waiter() if timeout_s > 0 and not raw.closed else None
        if waiter is not None:
            if read_first:
                data = raw.recv(0.0)
            if not data:
                if not waiter.wait(timeout_s, self.spin_s):
                    return False
                timeout_s = 0.0
        if not data:
            data = raw.recv(timeout_s)
        if not data:
            return False
        self._backlog.extend(self.splitter.feed(data))
        return True

    def read_onboard(self, timeout_s: float = 0.0) -> bool:
        """Read what the onboard program wrote and queue all of it for the FC, handed to the link now
        plus ``compute_s`` (real time; a lockstep answer is the harness's, not the FC's: dropped). False
        when nothing came in time."""
        got = self.read_raw(timeout_s)
        now = self.clock.now_s() + self.compute_s
        backlog = self._backlog
        while backlog:
            frame = backlog.popleft()
            if self._answered_ns(frame) is None:
                self._queue_for_fc(frame, now)
        return got

    def take_until_answer(self, tick_ns: int, stamp_s: float, read: bool = False) -> bool | None:
        """Queue for the FC, handed to the link at ``stamp_s`` (s), what the onboard program wrote for
        the tick at ``tick_ns`` (the frames before its answer); True once that answer has come. Frames
        answered for a later tick (this one's TIMESYNC was lost to corrupt bytes and sent again) wait
        for their own tick; what follows the last answer (the next tick's outputs) stays.

        With ``read``, where the frames read before hold neither that answer nor one to a later tick,
        what the onboard program has written by now is read (no wait) and taken the same way: False
        then when bytes came without the answer, None when nothing came (or nothing was read)."""
        later = self._answered_later
        if later:
            stashed = later.pop(tick_ns, None)
            if stashed is not None:
                for frame in stashed:
                    self._queue_for_fc(frame, stamp_s)
                return True
        backlog, frames, answered_ns = self._backlog, self._unanswered, self._answered_ns
        while True:
            while backlog:
                frame = backlog.popleft()
                answered = answered_ns(frame)
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
            if not read:
                return False
            read = False
            if self._answered_later and self.answered_later_than(tick_ns):
                return None  # (the tick is to be sent again first)
            data = self.raw.recv(0.0)
            if not data:
                return None
            backlog.extend(self.splitter.feed(data))

    def answered_later_than(self, tick_ns: int) -> bool:
        """Whether the onboard program has answered a tick after ``tick_ns`` (so it never saw that one)."""
        later = self._answered_later
        return bool(later) and any(k > tick_ns for k in later)

    def _queue_for_fc(self, frame: bytes, handed_s: float) -> None:
        if self._is_setpoint(frame):
            self.setpoints_sent += 1
        self.to_fc.frames_sent += 1
        arrival = self._in.arrival_s(handed_s, len(frame))
        if arrival is None:
            self.to_fc.frames_lost += 1
            return
        self._seq += 1
        heapq.heappush(self._in_queue, (arrival, self._seq, frame))
        if arrival < self.next_input_s:
            self.next_input_s = arrival

    def next_arrival_s(self) -> float:
        """When the next onboard frame reaches the FC (s; inf when none is on the way)."""
        return self._in_queue[0][0] if self._in_queue else math.inf

    def input_due(self) -> bool:
        """Whether the FC's codec has anything to read now (`next_input_s`): an onboard frame has
        arrived, or the link is closed, which its read says."""
        return self.next_input_s <= self.clock.now_s() + 1e-12

    def _recv_internal(self, max_bytes: int) -> bytes:
        q = self._in_queue
        data = self._drain(q, self.to_fc)
        self.next_input_s = q[0][0] if q else math.inf  # (open: `recv` reads only an open link)
        return data

    def _drain(self, q: list, st: DirectionStats) -> bytes:
        """The frames of queue ``q`` that have arrived by now, with the link's faults applied."""
        due = self.clock.now_s() + 1e-12
        if not q or q[0][0] > due:
            return b""
        faults = self.faults
        on_frame = faults.on_frame if faults.has_command_faults else None
        chunks = []
        pop = heapq.heappop
        while q and q[0][0] <= due:
            t, _, frame = pop(q)
            if on_frame is not None:
                frame, flipped = on_frame("command", frame, t, self._corrupt_rng)
                st.bytes_corrupted += flipped
                if frame is None:
                    st.frames_dropped_fault += 1
                    continue
            st.frames_delivered += 1
            st.bytes_delivered += len(frame)
            chunks.append(frame)
        return b"".join(chunks)

    def fileno(self) -> int:
        return self.raw.fileno()

    def _wait_readable(self, timeout_s: float | None) -> None:
        return  # the FC's codec only ever polls (timeout 0)

    def _close_internal(self) -> None:
        self.next_input_s = -math.inf
        self.raw.close()
