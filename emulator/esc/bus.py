"""The motors on a DroneCAN bus: the FC sends uavcan.equipment.esc.RawCommand at its motor rate, four ESC
nodes take their channel, drive the physics motors and answer uavcan.equipment.esc.Status; every node
sends uavcan.protocol.NodeStatus at 1 Hz. Messages are the `dronecan` package's DSDL types, cut into
and read back from CAN frames by its transport (multi-frame transfers with their CRC and toggle bits).

`CanBus` is the bus in the clock's time (simulated in lockstep, the wall clock in real time): each
frame takes its time on the wire at the bitrate (29-bit id, stuff bits), frames queue behind each other
in the order they are sent (arbitration by id between frames ready at the same instant is not
modelled), and loss, corruption (an error frame, then the controller's retransmission) and bus-off
windows act on them. Every frame can also go out to, and come in from, a real bus through python-can
(`virtual`, `udp_multicast`, `socketcan`, ...) or dronecan's own multicast driver (``mcast:N``), so a
separate process's dronecan node sees the traffic and may stand in for any ESC (``external``: the motor
then follows the rpm that node reports).

`EscBusStepper` steps a vehicle with its motors behind the bus: the FC's loop runs at the motor rate
and the physics at its own rate, each motor at the throttle its ESC holds.

The arithmetic of all of it (the wire, the queue, the emulated nodes, the stepper's loop) is compiled,
in `emulator.esc.kernels`, over flat arrays; the classes here are views of those arrays and do in
Python only what needs Python: dronecan's encoding for a real bus, frames coming in from one, listeners
attached from Python, the FC's reports and failsafe.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from operator import attrgetter
from typing import Any

import numpy as np

from emulator.esc import kernels as k
from emulator.esc.config import ACTIONS
from emulator.esc.config import ESC_STATUS_RATE_HZ as ESC_STATUS_RATE_HZ
from emulator.esc.config import EscBusConfig as EscBusConfig
from emulator.esc.kernels import RAW_COMMAND_MAX as RAW_COMMAND_MAX
from emulator.esc.kernels import frame_bits as frame_bits
from hil.link.can_multicast import FORMATS as MCAST_FORMATS
from hil.link.can_multicast import McastCanSocket, split_interface

BUS_SPECS = ("sim", "virtual:CHANNEL", "udp_multicast[:GROUP][@ADDR]", "socketcan:IFACE", "mcast[:N][@ADDR]")
#: NodeStatus health and mode values (uavcan.protocol.NodeStatus)
MODE_OPERATIONAL = 0
DRAW_BLOCK = 8192  # uniform draws taken from the bus's generator at a time (`emulator.esc.kernels`)
#: frames taken from a real bus in one pass (`CanBus.take_external`, about once a millisecond): what the
#: wire could carry since the last pass (shortest frames back to back), at least the first, at most the
#: second: a bound on the time a pass spends on them, whatever floods the real bus
MIN_INTAKE_FRAMES, MAX_INTAKE_FRAMES = 64, 1024
FRAMES_KEPT = 4096  # encoded messages kept for sending again (`CanBus._compiled_frames`)


@dataclass
class BusStats:
    """What the bus carried (counts; times in s)."""

    frames: int = 0  # delivered frames
    bits: int = 0
    busy_s: float = 0.0
    lost: int = 0
    error_frames: int = 0  # corrupted on the wire, then resent
    bus_off_dropped: int = 0
    external_in: int = 0  # frames from the real bus
    external_out: int = 0

    def as_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class Bridge:
    """A real CAN bus beside the model: frames out (`send`) and in (`receive`). ``mcast[:N]`` (dronecan's
    multicast datagrams, the bus dronecan nodes and ArduPilot's simulation join) and
    ``udp_multicast[:GROUP]`` (python-can's) cross processes on this machine's loopback interface only,
    or on a lab network's with ``@ADDR`` (an interface's IPv4 address: `hil.link.can_multicast`);
    ``virtual:CHANNEL`` and ``socketcan:IFACE`` go through python-can. A frame the real bus refuses is
    counted in ``errors``, never fatal; a multicast bus never hands back this process's own frames."""

    def __init__(self, spec: str, bitrate_bps: int) -> None:
        bus, interface = split_interface(parse_bus_spec(spec))
        kind, _, arg = bus.partition(":")
        self.spec, self.errors = spec, 0
        self.mcast: McastCanSocket | None = None
        self._bus: Any = None
        try:
            if kind in MCAST_FORMATS:
                self.mcast = McastCanSocket(kind, arg, interface)
            else:
                import can  # (python-can's buses load on first use: only for a bus that needs them)

                self._bus = can.Bus(interface=kind, channel=arg, bitrate=bitrate_bps)
                self._message = can.Message
        except Exception as exc:  # (python-can's CanError family, a socket's OSError, a bad group)
            raise OSError(f"cannot open the CAN bus {spec!r}: {exc}") from exc

    def send(self, can_id: int, data: bytes) -> None:
        if self.mcast is not None:
            if not self.mcast.send(can_id, data):
                self.errors += 1
            return
        try:
            self._bus.send(self._message(arbitration_id=can_id, data=data, is_extended_id=True))
        except Exception:  # (python-can's CanError, an OSError of the socket): counted, the run goes on
            self.errors += 1

    def receive(self, max_frames: int) -> tuple[list[tuple[int, bytes]], bool]:
        """Up to ``max_frames`` extended frames that have come in, and whether more may be waiting."""
        if self.mcast is not None:
            return self.mcast.receive(max_frames)
        out = []
        while len(out) < max_frames:
            msg = self._bus.recv(0)
            if msg is None:
                return out, False
            if msg.is_extended_id and not msg.is_error_frame and not msg.is_remote_frame:
                out.append((msg.arbitration_id, bytes(msg.data)))
        return out, True

    def close(self) -> None:
        if self.mcast is not None:
            self.mcast.close()
        else:
            self._bus.shutdown()


def parse_bus_spec(spec: str) -> str:
    """``spec`` checked (ValueError naming the kinds); "sim": the model alone."""
    bus, at, _ = spec.partition("@")
    kind, _, arg = bus.partition(":")
    if at and kind not in MCAST_FORMATS:
        raise ValueError(f"ESC bus {spec!r}: @ADDR (a network interface) is for "
                         f"{' and '.join(MCAST_FORMATS)}")
    if kind in ("sim", *MCAST_FORMATS) or (kind in ("virtual", "socketcan") and arg):
        split_interface(spec)  # (ValueError for an address that is none)
        return spec
    raise ValueError(f"ESC bus {spec!r}: expected one of {', '.join(BUS_SPECS)}")


@dataclass
class OutsideNode:
    """A node heard on the real bus (times in s): another process's or machine's, or one that uses a
    node id of this process (``conflict``: two nodes with one id, which DroneCAN forbids)."""

    node_id: int
    first_heard_s: float
    last_heard_s: float
    frames: int = 0
    conflict: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {"node_id": self.node_id, "frames": self.frames, "conflict": self.conflict,
                "first_heard_s": round(self.first_heard_s, 4), "last_heard_s": round(self.last_heard_s, 4)}


@dataclass(frozen=True, slots=True)
class Message:
    """A DroneCAN message as the nodes of this process hand it on: its DSDL type (dronecan's, for
    example ``uavcan.equipment.esc.RawCommand``), its sender and its field values (a snapshot)."""

    dtype: Any
    source_node_id: int
    fields: dict[str, Any]

    def encode(self, transfer_id: int, priority: int) -> list[tuple[int, bytes]]:
        """Its CAN frames (id, data) as dronecan's transport cuts them: DSDL encoding, the multi-frame
        CRC, the tail bytes."""
        from dronecan.transport import Transfer

        tr = Transfer(payload=self.dtype(**self.fields), source_node_id=self.source_node_id,
                      transfer_id=transfer_id, transfer_priority=priority, service_not_message=False)
        return [(f.message_id, bytes(f.bytes)) for f in tr.to_frames()]

    @classmethod
    def decoded(cls, transfer: Any) -> Message:
        """The message a dronecan Transfer (decoded from the wire) carries."""
        payload = transfer.payload
        return cls(payload._type, transfer.source_node_id,
                   {name: _plain(getattr(payload, name)) for name in payload._fields})


def _plain(value: Any) -> Any:
    from dronecan.transport import ArrayValue

    return list(value) if isinstance(value, ArrayValue) else value


class _Slot:
    """One float of the compiled model's arrays as an attribute: ``array`` names the array (a dotted path
    from the owner), ``index`` the float in it."""

    def __init__(self, array: str, index: int, doc: str) -> None:
        self._array, self.index, self.__doc__ = attrgetter(array), index, doc

    def __get__(self, owner: Any, cls: Any = None) -> Any:
        return self if owner is None else float(self._array(owner)[self.index])

    def __set__(self, owner: Any, value: float) -> None:
        self._array(owner)[self.index] = value


def _kind_types() -> tuple[Any, Any, Any]:
    """The DSDL types of the kinds the compiled nodes send (`emulator.esc.kernels` RAW_COMMAND, ESC_STATUS,
    NODE_STATUS), in that order."""
    from dronecan import uavcan

    return uavcan.equipment.esc.RawCommand, uavcan.equipment.esc.Status, uavcan.protocol.NodeStatus


#: esc.Status's fields in the order of an `ESC_STATUS` payload, each with its Python type
STATUS_FIELDS = (("error_count", int), ("voltage", float), ("current", float), ("temperature", float),
                 ("rpm", int), ("power_rating_pct", int), ("esc_index", int))


def _fields_of(kind: int, p: np.ndarray) -> dict[str, Any]:
    """A compiled node's payload as the DSDL fields of its kind."""
    if kind == k.RAW_COMMAND:
        return {"cmd": [int(v) for v in p[:int(p[k.PAYLOAD - 1])]]}
    if kind == k.ESC_STATUS:
        return {name: kind_of(p[i]) for i, (name, kind_of) in enumerate(STATUS_FIELDS)}
    return {"uptime_sec": int(p[0]), "health": int(p[1]), "mode": MODE_OPERATIONAL, "sub_mode": 0,
            "vendor_specific_status_code": 0}


def _payload_of(kind: int, fields: dict[str, Any]) -> np.ndarray:
    """The payload (`emulator.esc.kernels.PAYLOAD`,) a compiled node takes from a message's fields."""
    p = np.zeros(k.PAYLOAD)
    if kind == k.RAW_COMMAND:
        cmd = list(fields.get("cmd", ()))[:k.PAYLOAD - 1]
        p[:len(cmd)] = cmd
        p[k.PAYLOAD - 1] = len(cmd)
    elif kind == k.ESC_STATUS:
        for i, (name, _) in enumerate(STATUS_FIELDS):
            p[i] = float(fields.get(name, 0))
    return p


class CanBus:
    """The bus in the clock's time (see the module doc). Nodes attach with `attach(node_id, fn)`:
    ``fn(message, t)`` gets every complete `Message` but its own.

    A transfer's frames are those dronecan's transport cuts from the message (their number and lengths,
    worked out once per message layout): each takes its time on the wire and may be corrupted (resent)
    or lost, and a transfer with a lost frame never completes. Between the nodes of this process the
    message is handed on as its field values at the end of its last frame, without a byte-level round
    trip; its frames are encoded by dronecan whenever they leave for a real bus (``bridge``), and frames
    from a real bus are reassembled and decoded by dronecan's transport.

    Its state is the compiled model's arrays (`emulator.esc.kernels`): ``wire``, ``queue`` and the
    nodes' (none until an `EscBus` puts its own there)."""

    def __init__(self, config: EscBusConfig, rng: np.random.Generator, bridge: Bridge | None = None) -> None:
        from dronecan.transport import TransferManager

        self.config = config
        self.rng = rng
        self.bridge = bridge
        self.wire, self.queue = k.new_wire()
        w = self.wire
        w[k.W_BIT_S] = 1.0 / config.bitrate_bps
        w[k.W_LOSS], w[k.W_CORRUPTION] = config.loss, config.corruption
        w[k.W_BRIDGE] = bridge is not None
        self.draws = rng.random(DRAW_BLOCK)
        # the compiled nodes: none on a bare bus (an `EscBus` puts its FC and ESCs here)
        self.escs = np.zeros((0, k.E_SIZE))
        self.health = np.zeros((0, k.H_SIZE))
        self.fc = np.zeros(k.F_SIZE)
        self.fc[k.F_NODE] = -1.0
        self.fc[k.F_NODES_DUE_S] = math.inf
        self.events = np.zeros((k.EVENT_ROWS, 4))
        self.outbox = np.zeros((k.OUTBOX_ROWS, k.Q_SIZE))
        self.throttle = np.zeros(4)
        self._layouts: dict[tuple[Any, ...], tuple[int, ...]] = {}
        types = _kind_types()
        self._kinds = {dtype: i for i, dtype in enumerate(types)}
        self.layouts = np.zeros((k.N_KINDS, k.MAX_FRAMES), dtype=np.int64)
        self.n_frames = np.zeros(k.N_KINDS, dtype=np.int64)
        for i, dtype in enumerate(types):
            cut = self._frame_lengths(Message(dtype, 1, _fields_of(i, _payload_of(i, {"cmd": [0] * 4}))), 8)
            self.layouts[i, :len(cut)] = cut
            self.n_frames[i] = len(cut)
        self.node_ids: set[int] = set()  # the compiled nodes' ids
        #: what the compiled nodes say through the FC: rows (code, ESC index, value, t), see `EscBus`
        self.on_events: Callable[[np.ndarray], None] = lambda rows: None
        #: what Python keeps of a queued transfer, by sequence number: its message (None: frames only), its
        #: frames, and whether they go out (an answer to a request) or came in from the real bus
        self._python: dict[int, tuple[Message | None, list[tuple[int, bytes]], bool]] = {}
        self._row = np.zeros(k.Q_SIZE)
        self._objects = [dtype() for dtype in types]  # a DSDL object of each compiled kind, to encode on
        self._frames: dict[tuple[float, ...], list[tuple[int, bytes]]] = {}  # (see `_compiled_frames`)
        self._rx = TransferManager()
        self._routes: list[tuple[int, Callable[[Message, float], None], tuple[Any, ...] | None]] = []
        self._by_type: dict[Any, list[tuple[int, Callable[[Message, float], None]]]] = {}  # (from _routes)
        #: the nodes heard on the real bus, by node id; each new one is handed to ``on_outside_node``
        self.outside_nodes: dict[int, OutsideNode] = {}
        self.on_outside_node: Callable[[OutsideNode, float], None] = lambda node, t: None
        self.intake_deferred = 0  # passes that left frames waiting on the real bus (`take_external`)
        self._intake_s: float | None = None  # the last pass's time
        self._shortest_frame_s = frame_bits(0) / config.bitrate_bps
        #: the answer to a service request from the real bus (a dronecan Transfer) at t, None: no answer
        self.on_request: Callable[[Any, float], Any | None] = lambda transfer, t: None
        self.transfers_in = 0  # complete transfers from the real bus
        self.transfer_errors = 0  # transfers from the real bus that did not decode (bad CRC, unknown type)
        self.frames_in_queued = 0  # frames from the real bus put on the model's wire

    # the wire's settings and counters, as the arrays hold them
    @property
    def stats(self) -> BusStats:
        w = self.wire
        return BusStats(frames=int(w[k.W_FRAMES]), bits=int(w[k.W_BITS]), busy_s=float(w[k.W_BUSY_S]),
                        lost=int(w[k.W_LOST]), error_frames=int(w[k.W_ERROR_FRAMES]),
                        bus_off_dropped=int(w[k.W_BUS_OFF_DROPPED]), external_in=int(w[k.W_EXTERNAL_IN]),
                        external_out=int(w[k.W_EXTERNAL_OUT]))

    bus_off_until_s = _Slot("wire", k.W_BUS_OFF_UNTIL_S,
                            "frames sent before this time (s) are dropped (a bus-off window)")
    extra_loss = _Slot("wire", k.W_EXTRA_LOSS,
                       "frames lost on top of ``config.loss`` (a fault), the larger counts")

    @property
    def start_s(self) -> float | None:
        """When the first frame was sent (s), None before."""
        s = float(self.wire[k.W_START_S])
        return None if math.isnan(s) else s

    def attach(self, node_id: int, on_message: Callable[[Message, float], None],
               dtypes: tuple[Any, ...] | None = None) -> None:
        """``on_message(message, t)`` gets the messages of ``dtypes`` (None: of every type) but its own."""
        self._routes.append((node_id, on_message, dtypes))
        self._by_type.clear()
        for dtype, kind in self._kinds.items():
            if dtypes is None or dtype in dtypes:
                self.wire[k.W_LISTEN + kind] = 1.0

    def next_event_s(self) -> float:
        return k.next_event_s(self.wire, self.queue, self.fc)

    def ready(self, transfers: int = k.QUEUE_RESERVE) -> None:
        """Room for ``transfers`` more in the queue and the draws a compiled call may use."""
        w = self.wire
        at = int(w[k.W_DRAW_AT])
        if at > len(self.draws) - k.DRAW_RESERVE:
            self.draws = np.concatenate([self.draws[at:], self.rng.random(DRAW_BLOCK)])
            w[k.W_DRAW_AT] = 0.0
        count, cap = int(w[k.W_COUNT]), len(self.queue)
        if count + transfers > cap:  # (a bus past its capacity: the queue grows, in order)
            head = int(w[k.W_HEAD])
            order = (head + np.arange(count)) % cap
            grown = np.zeros((2 * (count + transfers), k.Q_SIZE))
            grown[:count] = self.queue[order]
            self.queue = grown
            w[k.W_HEAD] = 0.0

    def send(self, message: Message, transfer_id: int, priority: int, t: float) -> None:
        """Put ``message`` on the bus at ``t`` (s): its frames queue for the wire."""
        if self.bridge is not None:
            frames = message.encode(transfer_id, priority)
            lengths = tuple(len(data) for _, data in frames)
        else:
            frames = []
            lengths = self._frame_lengths(message, priority)
        self._queue_python(message, frames, lengths, transfer_id, priority, t)

    def _queue_python(self, message: Message | None, frames: list[tuple[int, bytes]],
                      lengths: tuple[int, ...], transfer_id: int, priority: int, t: float,
                      outgoing: bool = True) -> int:
        if len(lengths) > k.MAX_FRAMES:
            raise ValueError(f"a transfer of {len(lengths)} frames: the bus model takes at most "
                             f"{k.MAX_FRAMES}")
        self.ready(1)
        src = message.source_node_id if message is not None else frames[0][0] & 0x7F
        seq = k.queue_transfer(self.wire, self.queue, self.draws, k.PYTHON, src, transfer_id, priority,
                               self._row[:0], np.asarray(lengths, dtype=np.int64), len(lengths), t)
        if seq >= 0:
            self._python[seq] = (message, frames, outgoing)
        return seq

    def _frame_lengths(self, message: Message, priority: int) -> tuple[int, ...]:
        """Data bytes of each frame of ``message`` (dronecan's cut, worked out once per type, priority
        and array lengths: the tail byte's transfer id does not change them)."""
        key = (message.dtype, priority,
               *(len(v) for v in message.fields.values() if isinstance(v, list | tuple | str)))
        lengths = self._layouts.get(key)
        if lengths is None:
            lengths = self._layouts[key] = tuple(len(data) for _, data in message.encode(0, priority))
        return lengths

    def take_external(self, t: float) -> None:
        """Put what the real bus brought on the wire at ``t`` (s): at most what the wire could carry since
        the last pass (`MIN_INTAKE_FRAMES`..`MAX_INTAKE_FRAMES`), so that a flood from outside cannot
        stall the caller's loop. The rest wait in the real bus's socket for the next pass (counted in
        ``intake_deferred``); what overflows the socket is lost there, counted (`Bridge` stats)."""
        if self.bridge is None:
            return
        since_s = 0.0 if self._intake_s is None else t - self._intake_s
        self._intake_s = t
        fits = since_s / self._shortest_frame_s
        frames, more = self.bridge.receive(int(min(MAX_INTAKE_FRAMES, max(MIN_INTAKE_FRAMES, fits))))
        self.intake_deferred += more
        for can_id, data in frames:
            self._heard(can_id & 0x7F, t)
            self.wire[k.W_EXTERNAL_IN] += 1
            if self._queue_python(None, [(can_id, data)], (len(data),), 0, 0, t, outgoing=False) >= 0:
                self.frames_in_queued += 1

    def _heard(self, src: int, t: float) -> None:
        """A frame from node ``src`` of the real bus (0: anonymous) at ``t`` (s): noted, and the first one
        from a node handed to ``on_outside_node`` (a conflict when it uses this process's id)."""
        if src == 0:
            return
        node = self.outside_nodes.get(src)
        if node is None:
            node = self.outside_nodes[src] = OutsideNode(src, t, t, conflict=src in self.local_ids())
            self.on_outside_node(node, t)
        node.frames += 1
        node.last_heard_s = t

    def local_ids(self) -> set[int]:
        """The node ids this process's nodes use (the compiled ones and those attached from Python)."""
        return self.node_ids | {nid for nid, _, _ in self._routes}

    def advance_to(self, t: float) -> None:
        """Deliver every transfer whose frames are off the wire by ``t`` (s)."""
        while True:
            why = k.deliver(self.wire, self.queue, self.escs, self.health, self.fc, self.events,
                            self.outbox, self.throttle, t)
            self.flush_events()
            if why == k.FOR_PYTHON:
                self.deliver_head()
            elif why != k.EVENTS:
                return

    def deliver_head(self) -> None:
        """Deliver the transfer at the head of the queue through Python: one the compiled nodes cannot
        take alone (a message from Python, a frame from a real bus, a real bus or a listener to serve)."""
        if self.bridge is not None:
            self.flush_outbox()  # (what went before it goes out first)
        row = self._row
        k.pop_head(self.wire, self.queue, row)
        kind, src, done = int(row[k.Q_KIND]), int(row[k.Q_SRC]), float(row[k.Q_DONE_S])
        mask = int(row[k.Q_MASK])
        frames: list[tuple[int, bytes]] | None
        outgoing = True
        if kind != k.PYTHON:  # a compiled node's message
            self._deliver_compiled(kind, src, row, mask, done)
            return
        message, frames, outgoing = self._python.pop(int(row[k.Q_SEQ]))
        if message is None:
            if outgoing:  # an answer to a request: its frames that were not lost
                self._send_out([f for i, f in enumerate(frames) if mask >> i & 1])
            else:  # a frame from the real bus
                self._take_in(*frames[0], done)
            return
        if self.bridge is not None:
            self._send_out([f for i, f in enumerate(frames) if mask >> i & 1])
        if row[k.Q_KEPT] == row[k.Q_FRAMES]:
            self._hand_out(message, done)

    def _deliver_compiled(self, kind: int, src: int, row: np.ndarray, mask: int, done: float) -> None:
        """A compiled node's transfer, off the wire: its frames to the real bus, the message to the
        compiled nodes and the listeners when complete."""
        payload = row[k.Q_PAYLOAD:]
        if self.bridge is not None:
            frames = self._compiled_frames(kind, src, int(row[k.Q_TID]), int(row[k.Q_PRIORITY]), payload)
            self._send_out([f for i, f in enumerate(frames) if mask >> i & 1])
        if row[k.Q_KEPT] != row[k.Q_FRAMES]:
            return
        if self.fc[k.F_NODE] >= 0:
            k.hand_to_nodes(self.escs, self.health, self.fc, self.events, self.throttle, kind, src, payload,
                            done)
            self.flush_events()
        dtype = _kind_types()[kind]
        receivers = self._receivers(dtype)
        if receivers:
            message = Message(dtype, src, _fields_of(kind, payload))
            for nid, on_message in receivers:
                if nid != src:
                    on_message(message, done)

    def _compiled_frames(self, kind: int, src: int, tid: int, priority: int,
                         payload: np.ndarray) -> list[tuple[int, bytes]]:
        """A compiled node's message as dronecan cuts it into frames. dronecan's encoding is pure Python
        (a few hundred us a message): a message the same as one sent before (an idle motor's command,
        a resting ESC's status) takes the frames kept from then; the others are encoded on a DSDL
        object kept for the kind (setting its fields costs less than building one)."""
        key = (kind, src, tid, priority, *payload.tolist())
        frames = self._frames.get(key)
        if frames is None:
            from dronecan.transport import Transfer

            if len(self._frames) >= FRAMES_KEPT:
                self._frames.clear()
            obj = self._objects[kind]
            for name, value in _fields_of(kind, payload).items():
                setattr(obj, name, value)
            tr = Transfer(payload=obj, source_node_id=src, transfer_id=tid, transfer_priority=priority)
            frames = self._frames[key] = [(f.message_id, bytes(f.bytes)) for f in tr.to_frames()]
        return frames

    def _take_in(self, can_id: int, data: bytes, t: float) -> None:
        """A frame from the real bus off the model's wire at ``t`` (s): once its transfer is complete, a
        message handed out, a request to a node of this process answered."""
        tr = self._reassemble(can_id, data)
        if tr is None:
            return
        self.transfers_in += 1
        if not tr.service_not_message:
            self._hand_out(Message.decoded(tr), t)
        elif tr.request_not_response and tr.dest_node_id in self.node_ids:
            self._answer(tr, t)

    def _answer(self, request: Any, t: float) -> None:
        from dronecan.transport import Transfer

        payload = self.on_request(request, t)
        if payload is None:
            return
        tr = Transfer(payload=payload, source_node_id=request.dest_node_id,
                      dest_node_id=request.source_node_id, transfer_id=request.transfer_id,
                      transfer_priority=request.transfer_priority, service_not_message=True,
                      request_not_response=False)
        frames = [(f.message_id, bytes(f.bytes)) for f in tr.to_frames()]
        self._queue_python(None, frames, tuple(len(d) for _, d in frames), request.transfer_id,
                           request.transfer_priority, t)

    def flush_events(self) -> None:
        """Hand what the compiled nodes have to say to ``on_events``, and send their outbox."""
        if self.bridge is not None:
            self.flush_outbox()
        n = int(self.fc[k.F_EVENTS])
        if n:
            rows = self.events[:n].copy()
            self.fc[k.F_EVENTS] = 0.0
            self.on_events(rows)

    def flush_outbox(self) -> None:
        """Send the compiled nodes' transfers delivered since the last flush to the real bus, in order
        (each one's frames that were not lost)."""
        n = int(self.wire[k.W_OUTBOX])
        if not n:
            return
        self.wire[k.W_OUTBOX] = 0.0
        frames: list[tuple[int, bytes]] = []
        for row in self.outbox[:n]:
            mask = int(row[k.Q_MASK])
            cut = self._compiled_frames(int(row[k.Q_KIND]), int(row[k.Q_SRC]), int(row[k.Q_TID]),
                                        int(row[k.Q_PRIORITY]), row[k.Q_PAYLOAD:])
            frames.extend(f for i, f in enumerate(cut) if mask >> i & 1)
        self._send_out(frames)

    def _send_out(self, frames: list[tuple[int, bytes]]) -> None:
        if self.bridge is not None:
            for can_id, data in frames:
                self.bridge.send(can_id, data)
            self.wire[k.W_EXTERNAL_OUT] += len(frames)

    def _reassemble(self, can_id: int, data: bytes) -> Any | None:
        """The dronecan Transfer a frame from the real bus completes, None while it is incomplete or when it
        does not decode (counted)."""
        from dronecan.transport import Frame, Transfer

        frames = self._rx.receive_frame(Frame(can_id, data))
        if not frames:
            return None
        tr = Transfer()
        try:
            tr.from_frames(frames)
        except Exception:  # a transfer of a type this process does not know, or a bad CRC: not ours
            self.transfer_errors += 1
            return None
        return tr

    def _hand_out(self, message: Message, t: float) -> None:
        src = message.source_node_id
        kind = self._kinds.get(message.dtype)
        if kind is not None and self.fc[k.F_NODE] >= 0:  # this process's compiled nodes
            k.hand_to_nodes(self.escs, self.health, self.fc, self.events, self.throttle, kind, src,
                            _payload_of(kind, message.fields), t)
            self.flush_events()
        for nid, on_message in self._receivers(message.dtype):
            if nid != src:
                on_message(message, t)

    def _receivers(self, dtype: Any) -> list[tuple[int, Callable[[Message, float], None]]]:
        """The listeners attached from Python that take ``dtype``."""
        receivers = self._by_type.get(dtype)
        if receivers is None:
            receivers = self._by_type[dtype] = [
                (nid, fn) for nid, fn, dtypes in self._routes if dtypes is None or dtype in dtypes]
        return receivers

    def load(self, now_s: float) -> float:
        """Fraction of the time since the first frame the wire was busy."""
        start = self.start_s
        if start is None or now_s <= start:
            return 0.0
        return float(self.wire[k.W_BUSY_S]) / (now_s - start)

    def close(self) -> None:
        if self.bridge is not None:
            self.bridge.close()


@dataclass
class EscHealth:
    """What the FC knows about one ESC from its esc.Status."""

    last_status_s: float = -math.inf
    error_count: int = 0
    rpm: int = 0
    voltage_v: float = 0.0
    current_a: float = 0.0
    temperature_k: float = 0.0
    failed: bool = False


class FcEscNode:
    """The FC's node (a view of the bus's arrays): RawCommand from the FC's motor outputs at the motor
    rate, NodeStatus, and the watch over each ESC's esc.Status (silent past the timeout, or counting
    errors: reported, and the failsafe when configured; see `EscBus`)."""

    def __init__(self, bus: CanBus, config: EscBusConfig) -> None:
        self.bus, self.config = bus, config
        self.node_id = config.fc_node_id

    @property
    def escs(self) -> list[EscHealth]:
        """A snapshot of what it knows of each ESC."""
        return [EscHealth(float(h[k.H_LAST_S]), int(h[k.H_ERRORS]), int(h[k.H_RPM]), float(h[k.H_VOLTAGE_V]),
                          float(h[k.H_CURRENT_A]), float(h[k.H_TEMPERATURE_K]), bool(h[k.H_FAILED]))
                for h in self.bus.health]

    @property
    def commands_sent(self) -> int:
        return int(self.bus.fc[k.F_COMMANDS])

    def send_command(self, throttles: np.ndarray | Sequence[float], t: float) -> None:
        """RawCommand from the motor outputs ``throttles`` (4,) in [0, 1] at ``t`` (s)."""
        b = self.bus
        b.ready()
        k.send_command(b.wire, b.queue, b.draws, b.layouts, b.n_frames, b.fc,
                       np.asarray(throttles, dtype=np.float64), t)


class EscBus:
    """The FC, its four ESCs (some possibly outside this process) and the bus between them."""

    def __init__(self, config: EscBusConfig, rng: np.random.Generator, t0: float,
                 report: Callable[[str, str, float], None], failsafe: Callable[[str, float], None],
                 bridge: Bridge | None = None) -> None:
        self.config = config
        self.report, self.failsafe = report, failsafe
        self.bus = b = CanBus(config, rng, bridge)
        n = len(config.esc_node_ids)
        b.escs, b.health = np.zeros((n, k.E_SIZE)), np.zeros((n, k.H_SIZE))
        for i, nid in enumerate(config.esc_node_ids):
            e = b.escs[i]
            e[k.E_INDEX], e[k.E_NODE], e[k.E_EMULATED] = i, nid, nid not in config.external
            e[k.E_LAST_COMMAND_S] = -math.inf
            e[k.E_NEXT_STATUS_S] = t0 + i * 1e-4  # (the four ESCs a little apart on the wire)
            e[k.E_NEXT_NODE_S] = e[k.E_T0] = t0
            b.health[i, k.H_LAST_S] = t0
        f = b.fc
        f[k.F_NODE], f[k.F_T0], f[k.F_NEXT_NODE_S], f[k.F_NODES_DUE_S] = config.fc_node_id, t0, t0, t0
        f[k.F_COMMAND_PERIOD_S] = 1.0 / config.command_rate_hz
        f[k.F_STATUS_PERIOD_S] = 1.0 / config.status_rate_hz
        f[k.F_MAX_ROTOR], f[k.F_EFFICIENCY] = 1.0, 1.0  # (no power train until `set_power_train`)
        self._configure_watch()
        b.node_ids = {config.fc_node_id, *(nid for nid in config.esc_node_ids if nid not in config.external)}
        b.on_events = self._on_events
        self.throttle = b.throttle  # what each ESC drives its motor at (0..1)
        self.fc_node = FcEscNode(b, config)
        #: whether the motors are armed (an ESC refuses to restart then); `attach` asks the FC
        self.armed: Callable[[], bool] = lambda: False
        from emulator.esc import services as sv  # (dronecan's types: loaded with a bus, not this module)

        identities = {config.fc_node_id: sv.NodeIdentity(config.fc_node_id, sv.FC_NAME)}
        identities.update({nid: sv.NodeIdentity(nid, sv.ESC_NAME) for nid in config.esc_node_ids
                           if nid not in config.external})
        self.services = sv.NodeServices(identities, self._status_of, self._interface_counts, self._restart)
        b.on_request = self.services.answer
        b.on_outside_node = self._on_outside_node
        self._log_tid = 0

    def _node_row(self, node_id: int) -> tuple[np.ndarray, int, int]:
        """The compiled row of an emulated node and its uptime-origin and health columns."""
        if node_id == self.config.fc_node_id:
            return self.bus.fc, k.F_T0, k.F_HEALTH
        return self.bus.escs[self.config.esc_node_ids.index(node_id)], k.E_T0, k.E_HEALTH

    def _status_of(self, node_id: int, t: float) -> tuple[int, int]:
        row, t0, health = self._node_row(node_id)
        return int(t - row[t0]), int(row[health])

    def _restart(self, node_id: int, t: float) -> bool:
        if node_id == self.config.fc_node_id or self.armed():
            return False
        row, _, _ = self._node_row(node_id)
        row[k.E_T0], row[k.E_ERRORS], row[k.E_NEXT_NODE_S] = t, 0.0, t  # (its NodeStatus at once, uptime 0)
        self.bus.fc[k.F_NODES_DUE_S] = -math.inf
        self.report("info", f"ESC node {node_id} restarted on request", t)
        return True

    def _interface_counts(self) -> Any:
        """The process's interface to the bus (`emulator.esc.services.InterfaceCounts`)."""
        from emulator.esc.services import InterfaceCounts  # (loaded with the bus: see __init__)

        b, w = self.bus, self.bus.wire
        return InterfaceCounts(transfers_tx=int(w[k.W_SEQ]) - b.frames_in_queued, transfers_rx=b.transfers_in,
                               transfer_errors=b.transfer_errors, frames_tx=int(w[k.W_EXTERNAL_OUT]),
                               frames_rx=int(w[k.W_EXTERNAL_IN]),
                               errors=int(w[k.W_ERROR_FRAMES]) + (b.bridge.errors if b.bridge else 0))

    def _on_outside_node(self, node: OutsideNode, t: float) -> None:
        """A node first heard on the real bus: reported; one using an emulated node's id is a conflict,
        also told on the bus by the FC's node (uavcan.protocol.debug.LogMessage, level warning)."""
        if not node.conflict:
            self.report("info", f"DroneCAN node {node.node_id} heard on the bus", t)
            return
        text = f"node id {node.node_id} conflict: another node on the bus uses it"
        # (STATUSTEXT holds 50 characters)
        self.report("warning", f"DroneCAN node id {node.node_id} used by two nodes", t)
        from dronecan import uavcan  # (loaded with the bus: `CanBus`)

        log = uavcan.protocol.debug
        fields = {"level": log.LogLevel(value=log.LogLevel().WARNING), "source": "esc_bus", "text": text}
        self.bus.send(Message(log.LogMessage, self.config.fc_node_id, fields), self._log_tid, 28, t)
        self._log_tid = (self._log_tid + 1) & 31

    def _configure_watch(self) -> None:
        f = self.bus.fc
        f[k.F_TIMEOUT_S] = self.config.status_timeout_s
        f[k.F_ACTION] = ACTIONS.index(self.config.failsafe_action)

    max_rotor_speed_rad_s = _Slot("bus.fc", k.F_MAX_ROTOR,
                                  "the motors' top speed (rad/s): an outside ESC's rpm is read against it")

    def set_power_train(self, profile: Any) -> None:
        """The motors, their top speed and the pack of a `VehicleProfile`: what the emulated ESCs report
        in esc.Status (`emulator.esc.kernels.esc_power`)."""
        f = self.bus.fc
        f[k.F_MAX_ROTOR] = profile.max_rotor_speed_rad_s
        f[k.F_DRAG_COEFF] = profile.drag_torque_coeff_nm_s2
        f[k.F_PACK_V], f[k.F_PACK_OHM] = profile.battery_voltage_v, profile.battery_resistance_ohm
        f[k.F_EFFICIENCY] = profile.motor_efficiency

    def reconfigure(self, **changes: Any) -> None:
        """Change the FC's ESC watch in flight (``status_timeout_s``, ``failsafe_action``)."""
        self.config = replace(self.config, **changes)
        self.fc_node.config = self.config
        self._configure_watch()
        self.bus.fc[k.F_NODES_DUE_S] = -math.inf  # (poll at the next step)

    def _on_events(self, rows: np.ndarray) -> None:
        for code, index, value, t in rows.tolist():
            i = int(index)
            if code == k.EV_ERRORS:
                self.report("warning", f"ESC {i} errors: {int(value)}", t)
            elif code == k.EV_ANSWERS_AGAIN:
                self.report("info", f"ESC {i} answers again", t)
            elif code == k.EV_SILENT:
                self.report("critical", f"ESC {i} silent for {value:g} s", t)
            elif code == k.EV_FAILSAFE:
                self.failsafe(ACTIONS[int(value)], t)

    def poll(self, t: float, rotor_speed_rad_s: np.ndarray, armed: bool) -> None:
        """Everything due by ``t`` (s): frames delivered, ESC reports, the FC's watch."""
        b = self.bus
        rotor = np.asarray(rotor_speed_rad_s, dtype=np.float64)
        while True:
            b.ready()
            why = k.poll(b.wire, b.queue, b.draws, b.escs, b.health, b.fc, b.events, b.outbox, b.layouts,
                         b.n_frames, b.throttle, rotor, t, armed)
            b.flush_events()
            if why == k.FOR_PYTHON:
                b.deliver_head()
            elif why != k.EVENTS:  # (after events: on, until nothing is left due at t)
                return

    def command(self, throttles: np.ndarray, t: float) -> None:
        """The FC's motor tick at ``t`` (s) with its outputs ``throttles`` (4,): sent, the next tick
        scheduled, what is due delivered."""
        b = self.bus
        b.ready()
        why = k.command(b.wire, b.queue, b.draws, b.escs, b.health, b.fc, b.events, b.outbox, b.layouts,
                        b.n_frames, b.throttle, np.asarray(throttles, dtype=np.float64), t)
        b.flush_events()
        if why != k.DONE:  # (a delivery for Python, or events taken before the rest is delivered)
            b.advance_to(t)

    def set_silent(self, esc_index: int, silent: bool) -> None:
        for e in self.bus.escs:
            if e[k.E_INDEX] == esc_index and e[k.E_EMULATED] and bool(e[k.E_SILENT]) != silent:
                e[k.E_SILENT] = silent
                self.bus.fc[k.F_NODES_DUE_S] = -math.inf  # (poll at the next step)

    def close(self) -> None:
        self.bus.close()


class EscBusStepper:
    """Steps an EmulatedVehicle with its motors behind an `EscBus`: the FC's loop at the motor rate
    (its output sent as RawCommand), the physics at its own rate with each motor at its ESC's throttle.

    One compiled loop (`emulator.esc.kernels.run`) does it, the FC's motor ticks included while it flies an
    offboard attitude target with nothing timed due (its inner loop on the state's rows, then
    `stepped_outside`'s bookkeeping, as the lockstep runner's batched steps do); it hands back to
    Python for the FC's own `update` on its other ticks, for what a real bus or a listener needs, and
    for the FC's reports. On a backend other than the native one it hands back each physics stretch."""

    def __init__(self, vehicle: Any, esc: EscBus) -> None:
        self.vehicle, self.esc = vehicle, esc
        b = esc.bus
        b.fc[k.F_NEXT_COMMAND_S] = vehicle.time_s
        esc.set_power_train(vehicle.profile)
        #: the FC's quiet motor ticks in the compiled loop (False: every tick through its own update)
        self.quiet_commands = True
        #: the native backend's arrays (`NativeBackend.kernel_arrays`), None on another backend
        self._arrays = getattr(vehicle.backend, "kernel_arrays", None)
        self._target = np.zeros(k.T_SIZE)
        self._none = np.zeros(0)
        self.compile_kernels()

    fc_steps = property(lambda self: int(self.esc.bus.fc[k.F_FC_STEPS]), doc="motor ticks of the FC")
    fc_quiet_steps = property(lambda self: int(self.esc.bus.fc[k.F_QUIET_STEPS]),
                              doc="of them, those flown by the inner loop alone")
    physics_steps = property(lambda self: int(self.esc.bus.fc[k.F_PHYSICS_STEPS]))
    polls = property(lambda self: int(self.esc.bus.fc[k.F_POLLS]),
                     doc="times the bus and its nodes were polled (at their events only)")

    def compile_kernels(self) -> None:
        """Compile (or load from numba's cache) every kernel the steps may call, now rather than in
        flight (a real-time loop), on copies: no state changes."""
        b, v = self.esc.bus, self.vehicle
        inner = v.fc.inner
        wire, queue, fc = b.wire.copy(), b.queue.copy(), b.fc.copy()
        escs, health, events, throttle = b.escs.copy(), b.health.copy(), b.events.copy(), b.throttle.copy()
        outbox = b.outbox.copy()
        x = v.state_vector()
        aux, p = (self._arrays[1].copy(), self._arrays[2]) if self._arrays is not None else (x, x)
        k.run(x, aux, p, self._arrays is not None, wire, queue, b.draws, escs, health, fc, events, outbox,
              b.layouts, b.n_frames, throttle, self._target, inner.params, inner.mix_inv,
              inner.motor_cmd.copy(), 0, 0.0, 0, v.dt_s, False)
        k.poll(wire, queue, b.draws, escs, health, fc, events, outbox, b.layouts, b.n_frames, throttle,
               x[13:17], -1.0, False)
        k.command(wire, queue, b.draws, escs, health, fc, events, outbox, b.layouts, b.n_frames, throttle,
                  np.zeros(4), -1.0)
        k.pop_head(wire, queue, np.zeros(k.Q_SIZE))
        k.hand_to_nodes(escs, health, fc, events, throttle, k.RAW_COMMAND, -1.0, np.zeros(k.PAYLOAD), -1.0)
        k.queue_transfer(wire, queue, b.draws, k.PYTHON, 0, 0, 0, self._none, np.zeros(1, dtype=np.int64), 1,
                         -1.0)
        k.next_event_s(wire, queue, fc)
        k.deliver(wire, queue, escs, health, fc, events, outbox, throttle, -1.0)
        k.send_command(wire, queue, b.draws, b.layouts, b.n_frames, fc, np.zeros(4), -1.0)

    def step(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps."""
        v, esc = self.vehicle, self.esc
        b = esc.bus
        fc, be, dt = v.fc, v.backend, v.dt_s
        f, tg = b.fc, self._target
        inner = fc.inner
        b.take_external(v.time_s)  # (a real bus: read once per call, about once a millisecond)
        native = self._arrays is not None
        b.ready()
        armed = fc.state.armed
        while n_steps > 0:
            held = fc.held_target() if self.quiet_commands and native else None
            if held is None:
                tg[k.T_ON] = 0.0
            else:
                tg[k.T_ROLL], tg[k.T_PITCH], tg[k.T_YAW] = held.roll_rad, held.pitch_rad, held.yaw_rad
                tg[k.T_THRUST], tg[k.T_ON] = held.thrust_n, 1.0
                tg[k.T_QUIET_UNTIL_S] = fc.quiet_until_s()
            f[k.F_REST_Z], f[k.F_LANDED_MARGIN] = fc.rest_height_m, fc.config.landed_margin_m
            if native:
                x, aux, p = self._arrays
                t0, steps0 = be.clock
            else:
                x = v.state_vector()
                aux = p = x
                t0, steps0 = v.time_s, 0
            taken, why = k.run(x, aux, p, native, b.wire, b.queue, b.draws, b.escs, b.health, f, b.events,
                               b.outbox, b.layouts, b.n_frames, b.throttle, tg, inner.params, inner.mix_inv,
                               inner.motor_cmd, n_steps, t0, steps0, dt, armed)
            if taken:
                be.advance_clock(taken)
                v.steps += taken
                v.invalidate_state()
                n_steps -= taken
            if f[k.F_QUIETED]:
                f[k.F_QUIETED] = 0.0
                fc.stepped_outside(float(f[k.F_QUIET_T]), float(f[k.F_QUIET_Z]), float(f[k.F_QUIET_VZ]))
            if why == k.DONE:
                if b.bridge is not None:
                    b.flush_outbox()  # (what the compiled nodes sent in the call, to the real bus)
                return
            if why == k.FOR_PYTHON:
                b.deliver_head()
            elif why == k.EVENTS:
                b.flush_events()
                armed = fc.state.armed  # (a failsafe may have disarmed it)
            elif why == k.COMMAND:
                esc.command(fc.update(v.state), v.time_s)
                armed = fc.state.armed
            elif why == k.REFILL:
                b.ready()
            elif why == k.PHYSICS:
                n = int(f[k.F_PENDING_STEPS])
                be.step(b.throttle, n)
                v.invalidate_state()
                v.steps += n
                f[k.F_PHYSICS_STEPS] += n
                n_steps -= n

    def summary(self, now_s: float) -> dict[str, Any]:
        bus = self.esc.bus
        return {
            "bus": bus.stats.as_dict(), "load": round(bus.load(now_s), 4), "commands_sent":
            self.esc.fc_node.commands_sent,
            "throttle": [round(float(u), 4) for u in self.esc.throttle],  # what each motor runs at
            # nodes heard on the real bus (a conflict: one using an emulated node's id), services answered
            "outside_nodes": [n.as_dict() for _, n in sorted(bus.outside_nodes.items())],
            "conflicts": sorted(n.node_id for n in bus.outside_nodes.values() if n.conflict),
            "services_answered": dict(self.esc.services.answered),
            "real_bus": self._real_bus(bus),
            "escs": [
                {"index": i, "node_id": nid, "external": nid in self.esc.config.external,
                 "failed": h.failed, "rpm": h.rpm, "error_count": h.error_count,
                 "voltage_v": round(h.voltage_v, 3), "current_a": round(h.current_a, 3),
                 "temperature_k": round(h.temperature_k, 2)}
                for i, (nid, h) in enumerate(zip(self.esc.config.esc_node_ids, self.esc.fc_node.escs,
                                                 strict=True))],
        }


    @staticmethod
    def _real_bus(bus: CanBus) -> dict[str, Any] | None:
        """The real bus's intake: transfers in, those that did not decode, passes that left frames
        waiting, and a multicast socket's own counts (drops in the socket among them)."""
        if bus.bridge is None:
            return None
        out: dict[str, Any] = {"transfers_in": bus.transfers_in, "transfer_errors": bus.transfer_errors,
                               "intake_deferred": bus.intake_deferred, "send_errors": bus.bridge.errors}
        if bus.bridge.mcast is not None:
            out["socket"] = bus.bridge.mcast.stats.as_dict()
        return out


_SEVERITY = {"info": 6, "warning": 4, "critical": 2}  # MAV_SEVERITY


def attach(vehicle: Any, server: Any, config: EscBusConfig, rng: np.random.Generator,
           bridge: Bridge | None = None) -> EscBusStepper:
    """Put ``vehicle``'s motors behind an ESC bus: its FC (served by the MAVLink ``server``) reports ESC
    trouble as STATUSTEXT and fails safe as configured; the bus's settings become parameters."""
    fc = vehicle.fc

    def report(severity: str, text: str, t: float) -> None:
        server.statustext(_SEVERITY[severity], text, t, key=f"esc:{text}")

    esc = EscBus(config, rng, vehicle.time_s, report,
                 lambda action, t: fc.motor_failsafe(action, t, "ESC failed"), bridge)
    esc.armed = lambda: fc.state.armed
    stepper = EscBusStepper(vehicle, esc)
    vehicle.motor_path = stepper
    server.params.esc = esc
    return stepper
