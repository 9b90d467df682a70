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
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

ESC_STATUS_RATE_HZ = 50.0  # how often each ESC reports esc.Status
NODE_STATUS_PERIOD_S = 1.0  # uavcan.protocol.NodeStatus, every node
RAW_COMMAND_MAX = 8191  # int14: full throttle
ESC_COMMAND_TIMEOUT_S = 0.1  # an ESC that hears no RawCommand this long stops its motor
FRAME_OVERHEAD_BITS = 67  # a 29-bit-id data frame besides its data: SOF, id, control, CRC, ACK, EOF, IFS
ERROR_FRAME_BITS = 20  # an error flag, its delimiter and the intermission
BUS_SPECS = ("sim", "virtual:CHANNEL", "udp_multicast[:GROUP]", "socketcan:IFACE", "mcast[:N]")
#: NodeStatus health and mode values (uavcan.protocol.NodeStatus)
HEALTH_OK, HEALTH_CRITICAL = 0, 2
MODE_OPERATIONAL = 0


@dataclass(frozen=True)
class EscBusConfig:
    """The ESC bus: its wire, its nodes and what the FC does about a failed ESC (SI units)."""

    bitrate_bps: int = 1_000_000
    command_rate_hz: float = 400.0  # RawCommand (and the FC's loop) rate
    status_rate_hz: float = ESC_STATUS_RATE_HZ
    fc_node_id: int = 10
    esc_node_ids: tuple[int, ...] = (20, 21, 22, 23)  # ESC index i (the FC's motor i) is this node
    #: ESC node ids served by a node outside this process (their motor follows its esc.Status rpm)
    external: tuple[int, ...] = ()
    loss: float = 0.0  # fraction of frames lost (never reach a receiver)
    corruption: float = 0.0  # fraction of frames hit by a bit error (an error frame, then resent)
    status_timeout_s: float = 0.1  # an ESC silent this long is reported failed
    failsafe_action: str = "report"  # on a failed ESC: report, land or disarm

    def __post_init__(self) -> None:
        if not 10_000 <= self.bitrate_bps <= 1_000_000:
            raise ValueError(f"ESC bus bitrate must be 10 kbit/s..1 Mbit/s, got {self.bitrate_bps}")
        for name in ("command_rate_hz", "status_rate_hz", "status_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"EscBusConfig.{name} must be a positive number, got {v!r}")
        for name in ("loss", "corruption"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 <= v < 1.0):
                raise ValueError(f"EscBusConfig.{name} must be in [0, 1), got {v!r}")
        ids = (self.fc_node_id, *self.esc_node_ids)
        if len(self.esc_node_ids) != 4 or len(set(ids)) != len(ids) or not all(1 <= i <= 127 for i in ids):
            raise ValueError(f"node ids must be 1..127 and distinct, four ESCs: fc {self.fc_node_id}, "
                             f"escs {self.esc_node_ids}")
        for nid in self.external:
            if nid not in self.esc_node_ids:
                raise ValueError(f"external ESC node {nid} is none of the ESC node ids {self.esc_node_ids}")
        if self.failsafe_action not in ("report", "land", "disarm"):
            raise ValueError(f"failsafe_action must be report, land or disarm, got {self.failsafe_action!r}")


def frame_bits(data_len: int) -> int:
    """Bits on the wire of an extended data frame with ``data_len`` bytes, with the stuff bits a typical
    payload needs (one in five of the stuffed part, worst case one in four)."""
    stuffed = 54 + 8 * data_len  # SOF through CRC
    return FRAME_OVERHEAD_BITS + 8 * data_len + stuffed // 5


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
    """A real CAN bus beside the model: frames out (`send`) and in (`receive`), through python-can
    (``virtual:CHANNEL``, ``udp_multicast[:GROUP]``, ``socketcan:IFACE``) or dronecan's own multicast
    driver (``mcast[:N]``, the one dronecan nodes and ArduPilot's simulation join). A frame the real bus
    refuses is counted in ``errors``, never fatal."""

    def __init__(self, spec: str, bitrate_bps: int) -> None:
        kind, _, arg = parse_bus_spec(spec).partition(":")
        self.spec, self.errors = spec, 0
        self._bus: Any = None
        self._driver: Any = None
        try:
            if kind == "mcast":
                from dronecan.driver import make_driver

                self._driver = make_driver(f"mcast:{arg or 0}")
            else:
                import can

                channel = arg or ("239.74.163.2" if kind == "udp_multicast" else "")
                self._bus = can.Bus(interface=kind, channel=channel, bitrate=bitrate_bps)
                self._message = can.Message
        except Exception as exc:  # (python-can's CanError family, a socket's OSError, a bad group)
            raise OSError(f"cannot open the CAN bus {spec!r}: {exc}") from exc

    def send(self, can_id: int, data: bytes) -> None:
        try:
            if self._driver is not None:
                self._driver.send(can_id, bytes(data), extended=True)
            else:
                self._bus.send(self._message(arbitration_id=can_id, data=data, is_extended_id=True))
        except Exception:  # (python-can's CanError, an OSError of the socket): counted, the run goes on
            self.errors += 1

    def receive(self) -> list[tuple[int, bytes]]:
        """The extended frames that have come in."""
        out = []
        while True:
            if self._driver is not None:
                # (its receive waits 1 ms for nothing: ask only when its queue holds something)
                frame = None if self._driver.rx_queue.empty() else self._driver.receive(0)
                if frame is None:
                    return out
                can_id, data, extended = frame.id, frame.data, frame.extended
            else:
                msg = self._bus.recv(0)
                if msg is None:
                    return out
                can_id, data, extended = msg.arbitration_id, msg.data, msg.is_extended_id
            if extended:
                out.append((can_id, bytes(data)))

    def close(self) -> None:
        if self._driver is not None:
            self._driver.close()
        else:
            self._bus.shutdown()


def parse_bus_spec(spec: str) -> str:
    """``spec`` checked (ValueError naming the kinds); "sim": the model alone."""
    kind, _, arg = spec.partition(":")
    if kind in ("sim", "mcast", "udp_multicast") or (kind in ("virtual", "socketcan") and arg):
        return spec
    raise ValueError(f"ESC bus {spec!r}: expected one of {', '.join(BUS_SPECS)}")


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


class CanBus:
    """The bus in the clock's time (see the module doc). Nodes attach with `attach(node_id, fn)`:
    ``fn(message, t)`` gets every complete `Message` but its own.

    A transfer's frames are those dronecan's transport cuts from the message (their number and lengths,
    worked out once per message layout): each takes its time on the wire and may be corrupted (resent)
    or lost, and a transfer with a lost frame never completes. Between the nodes of this process the
    message is handed on as its field values at the end of its last frame, without a byte-level round
    trip; its frames are encoded by dronecan whenever they leave for a real bus (``bridge``), and frames
    from a real bus are reassembled and decoded by dronecan's transport."""

    def __init__(self, config: EscBusConfig, rng: np.random.Generator, bridge: Bridge | None = None) -> None:
        from dronecan.transport import TransferManager

        self.config = config
        self.rng = rng
        self.bridge = bridge
        self.stats = BusStats()
        self._bit_s = 1.0 / config.bitrate_bps
        self._free_s = 0.0  # the wire is busy until then
        #: (done_s, seq, message or None, frames for a real bus or to reassemble, frames delivered)
        self._queue: list[tuple[float, int, Message | None, list[tuple[int, bytes]], int]] = []
        self._seq = 0
        self._rx = TransferManager()
        self._routes: list[tuple[int, Callable[[Message, float], None], tuple[Any, ...] | None]] = []
        self._by_type: dict[Any, list[tuple[int, Callable[[Message, float], None]]]] = {}  # (from _routes)
        self._layouts: dict[tuple[Any, ...], tuple[int, ...]] = {}
        self.bus_off_until_s = -math.inf
        self.extra_loss = 0.0  # frames lost on top of ``config.loss`` (a fault), the larger counts
        self.start_s: float | None = None

    def attach(self, node_id: int, on_message: Callable[[Message, float], None],
               dtypes: tuple[Any, ...] | None = None) -> None:
        """``on_message(message, t)`` gets the messages of ``dtypes`` (None: of every type) but its own."""
        self._routes.append((node_id, on_message, dtypes))
        self._by_type.clear()

    def next_event_s(self) -> float:
        return self._queue[0][0] if self._queue else math.inf

    def send(self, message: Message, transfer_id: int, priority: int, t: float) -> None:
        """Put ``message`` on the bus at ``t`` (s): its frames queue for the wire."""
        if self.bridge is not None:
            frames = message.encode(transfer_id, priority)
            lengths = tuple(len(data) for _, data in frames)
        else:
            frames = []
            lengths = self._frame_lengths(message, priority)
        self._queue_transfer(message, frames, lengths, t)

    def _frame_lengths(self, message: Message, priority: int) -> tuple[int, ...]:
        """Data bytes of each frame of ``message`` (dronecan's cut, worked out once per type, priority
        and array lengths: the tail byte's transfer id does not change them)."""
        key = (message.dtype, priority,
               *(len(v) for v in message.fields.values() if isinstance(v, list | tuple)))
        lengths = self._layouts.get(key)
        if lengths is None:
            lengths = self._layouts[key] = tuple(len(data) for _, data in message.encode(0, priority))
        return lengths

    def _queue_transfer(self, message: Message | None, frames: list[tuple[int, bytes]],
                        lengths: tuple[int, ...], t: float) -> None:
        """Queue the frames of one transfer (``message`` None: a frame from the real bus, in ``frames``)
        from ``t`` (s), in order, behind what the wire already carries."""
        if self.start_s is None:
            self.start_s = t
        cfg, st = self.config, self.stats
        if t < self.bus_off_until_s:
            st.bus_off_dropped += len(lengths)
            return
        loss = cfg.loss if cfg.loss > self.extra_loss else self.extra_loss
        start = max(t, self._free_s)
        kept: list[tuple[int, bytes]] = []  # the frames not lost, when they have bytes
        n_kept = 0
        for i, n in enumerate(lengths):
            bits = frame_bits(n)
            while cfg.corruption > 0 and self.rng.random() < cfg.corruption:  # error frame, then resent
                st.error_frames += 1
                start += (bits // 2 + ERROR_FRAME_BITS) * self._bit_s
            done = start + bits * self._bit_s
            st.bits += bits
            st.busy_s += done - start
            start = done
            if loss > 0 and self.rng.random() < loss:
                st.lost += 1
                continue
            n_kept += 1
            if frames:
                kept.append(frames[i])
        self._free_s = start
        if n_kept:  # (a transfer short of a frame never completes: its other frames still pass)
            self._seq += 1
            complete = n_kept == len(lengths)
            heapq.heappush(self._queue, (start, self._seq, message if complete else None, kept, n_kept))

    def take_external(self, t: float) -> None:
        """Put what the real bus brought on the wire at ``t`` (s)."""
        if self.bridge is None:
            return
        for can_id, data in self.bridge.receive():
            if self._from_outside(can_id & 0x7F):  # (a multicast bus hands back what this process sent)
                self.stats.external_in += 1
                self._queue_transfer(None, [(can_id, data)], (len(data),), t)

    def advance_to(self, t: float) -> None:
        """Deliver every transfer whose frames are off the wire by ``t`` (s)."""
        q = self._queue
        while q and q[0][0] <= t + 1e-12:
            done, _, message, frames, n = heapq.heappop(q)
            self.stats.frames += n
            if message is not None:  # ours, complete
                self._send_out(frames)
                self._hand_out(message, done)
            elif frames and self._from_outside(frames[0][0] & 0x7F):  # a frame from the real bus
                got = self._reassemble(*frames[0])
                if got is not None:
                    self._hand_out(got, done)
            else:  # what was left of one of ours
                self._send_out(frames)

    def _send_out(self, frames: list[tuple[int, bytes]]) -> None:
        if self.bridge is not None:
            for can_id, data in frames:
                self.bridge.send(can_id, data)
            self.stats.external_out += len(frames)

    def _reassemble(self, can_id: int, data: bytes) -> Message | None:
        from dronecan.transport import Frame, Transfer

        frames = self._rx.receive_frame(Frame(can_id, data))
        if not frames:
            return None
        tr = Transfer()
        try:
            tr.from_frames(frames)
        except Exception:  # a transfer of a type this process does not know, or a bad CRC: not ours
            return None
        return Message.decoded(tr)

    def _from_outside(self, src: int) -> bool:
        return all(src != nid for nid, _, _ in self._routes)

    def _hand_out(self, message: Message, t: float) -> None:
        receivers = self._by_type.get(message.dtype)
        if receivers is None:
            receivers = self._by_type[message.dtype] = [
                (nid, fn) for nid, fn, dtypes in self._routes if dtypes is None or message.dtype in dtypes]
        src = message.source_node_id
        for nid, on_message in receivers:
            if nid != src:
                on_message(message, t)

    def load(self, now_s: float) -> float:
        """Fraction of the time since the first frame the wire was busy."""
        if self.start_s is None or now_s <= self.start_s:
            return 0.0
        return self.stats.busy_s / (now_s - self.start_s)

    def close(self) -> None:
        if self.bridge is not None:
            self.bridge.close()


class _Node:
    """A DroneCAN node's own bookkeeping: its id, transfer ids by type, its NodeStatus."""

    def __init__(self, bus: CanBus, node_id: int, t0: float) -> None:
        self.bus, self.node_id = bus, node_id
        self._tid: dict[int, int] = {}
        self.t0 = t0
        self.next_node_status_s = t0
        self.health = HEALTH_OK

    def broadcast(self, dtype: Any, fields: dict[str, Any], t: float, priority: int = 16) -> None:
        key = dtype.default_dtid
        tid = self._tid.get(key, 0)
        self._tid[key] = (tid + 1) & 31
        self.bus.send(Message(dtype, self.node_id, fields), tid, priority, t)

    def node_status(self, t: float) -> None:
        while t >= self.next_node_status_s - 1e-12:
            from dronecan import uavcan

            self.broadcast(uavcan.protocol.NodeStatus, {
                "uptime_sec": int(t - self.t0), "health": self.health, "mode": MODE_OPERATIONAL,
                "sub_mode": 0, "vendor_specific_status_code": 0}, t, priority=24)
            self.next_node_status_s += NODE_STATUS_PERIOD_S


class EmulatedEsc(_Node):
    """One ESC node: takes channel ``index`` of each RawCommand, holds its motor's throttle there, and
    reports esc.Status (rpm from the physics' rotor speed)."""

    def __init__(self, bus: CanBus, node_id: int, index: int, throttle: np.ndarray, t0: float) -> None:
        super().__init__(bus, node_id, t0)
        self.index, self.throttle = index, throttle
        self.silent = False  # esc_silent: answers nothing and stops its motor
        self.last_command_s = -math.inf
        self.error_count = 0  # commands it timed out on
        self.next_status_s = t0 + index * 1e-4  # (the four ESCs a little apart on the wire)
        self.period_s = 1.0 / bus.config.status_rate_hz
        from dronecan import uavcan

        self._raw_command_type = uavcan.equipment.esc.RawCommand
        self._status_type = uavcan.equipment.esc.Status
        bus.attach(node_id, self.on_message, (self._raw_command_type,))

    def due_s(self) -> float:
        """When `poll` has something to do next (s): a status, a NodeStatus, or the command timeout."""
        due = self.next_status_s if self.next_status_s < self.next_node_status_s else self.next_node_status_s
        if self.throttle[self.index] != 0.0 and self.last_command_s + ESC_COMMAND_TIMEOUT_S < due:
            due = self.last_command_s + ESC_COMMAND_TIMEOUT_S
        return due

    def on_message(self, msg: Message, t: float) -> None:
        if self.silent or msg.dtype is not self._raw_command_type:
            return
        cmd = msg.fields["cmd"]
        if self.index < len(cmd):
            self.throttle[self.index] = max(0, int(cmd[self.index])) / RAW_COMMAND_MAX
            self.last_command_s = t

    def poll(self, t: float, rotor_speed_rad_s: float) -> None:
        if self.silent:  # its slots pass unused (a stepper waits for the next one, not for this one)
            self.throttle[self.index] = 0.0
            while t >= self.next_status_s - 1e-12:
                self.next_status_s += self.period_s
            while t >= self.next_node_status_s - 1e-12:
                self.next_node_status_s += NODE_STATUS_PERIOD_S
            return
        if t - self.last_command_s > ESC_COMMAND_TIMEOUT_S and self.throttle[self.index] != 0.0:
            self.throttle[self.index] = 0.0  # the command stream stopped: the motor stops
            self.error_count += 1
        self.node_status(t)
        if t >= self.next_status_s - 1e-12:
            u = float(self.throttle[self.index])
            self.broadcast(self._status_type, {
                "error_count": self.error_count, "voltage": 15.2 - 1.2 * u, "current": 25.0 * u**1.5,
                "temperature": 300.0 + 40.0 * u, "rpm": int(rotor_speed_rad_s * 60.0 / (2.0 * math.pi)),
                "power_rating_pct": round(100 * u), "esc_index": self.index}, t)
            self.next_status_s += self.period_s
            if self.next_status_s <= t:
                self.next_status_s = t + self.period_s


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


class FcEscNode(_Node):
    """The FC's node: RawCommand from the FC's motor outputs at the motor rate, NodeStatus, and the
    watch over each ESC's esc.Status (silent past the timeout, or counting errors: reported by
    ``report(severity, text, t)``, and the failsafe when configured)."""

    def __init__(self, bus: CanBus, config: EscBusConfig, t0: float,
                 report: Callable[[str, str, float], None], failsafe: Callable[[str, float], None]) -> None:
        super().__init__(bus, config.fc_node_id, t0)
        self.config = config
        self.report, self.failsafe = report, failsafe
        self.escs = [EscHealth(last_status_s=t0) for _ in config.esc_node_ids]
        from dronecan import uavcan

        self._raw_command_type = uavcan.equipment.esc.RawCommand
        self._status_type = uavcan.equipment.esc.Status
        self.commands_sent = 0
        bus.attach(self.node_id, self.on_message, (self._status_type,))

    def due_s(self) -> float:
        """When `poll` has something to do next (s): its NodeStatus or an ESC's status timeout."""
        due = self.next_node_status_s
        timeout = self.config.status_timeout_s
        for h in self.escs:
            if not h.failed and h.last_status_s + timeout < due:
                due = h.last_status_s + timeout
        return due

    def send_command(self, throttles: np.ndarray | Sequence[float], t: float) -> None:
        values = throttles.tolist() if isinstance(throttles, np.ndarray) else throttles
        cmd = [min(RAW_COMMAND_MAX, max(0, round(u * RAW_COMMAND_MAX))) for u in values]
        self.broadcast(self._raw_command_type, {"cmd": cmd}, t, priority=8)
        self.commands_sent += 1

    def on_message(self, msg: Message, t: float) -> None:
        p = msg.fields
        if msg.dtype is not self._status_type or not 0 <= p["esc_index"] < len(self.escs):
            return
        index, errors = p["esc_index"], p["error_count"]
        h = self.escs[index]
        if errors > h.error_count:
            self.report("warning", f"ESC {index} errors: {errors}", t)
        h.last_status_s, h.error_count, h.rpm = t, errors, p["rpm"]
        h.voltage_v, h.current_a, h.temperature_k = p["voltage"], p["current"], p["temperature"]
        if h.failed:
            h.failed = False
            self.report("info", f"ESC {index} answers again", t)
            if not any(e.failed for e in self.escs):
                self.health = HEALTH_OK

    def poll(self, t: float, armed: bool) -> None:
        self.node_status(t)
        timeout = self.config.status_timeout_s
        for i, h in enumerate(self.escs):
            if not h.failed and t - h.last_status_s > timeout:
                h.failed = True
                self.health = HEALTH_CRITICAL
                self.report("critical", f"ESC {i} silent for {timeout:g} s", t)
                if armed and self.config.failsafe_action != "report":
                    self.failsafe(self.config.failsafe_action, t)


class EscBus:
    """The FC, its four ESCs (some possibly outside this process) and the bus between them."""

    def __init__(self, config: EscBusConfig, rng: np.random.Generator, t0: float,
                 report: Callable[[str, str, float], None], failsafe: Callable[[str, float], None],
                 bridge: Bridge | None = None) -> None:
        self.config = config
        self.bus = CanBus(config, rng, bridge)
        self.throttle = np.zeros(len(config.esc_node_ids))  # what each ESC drives its motor at (0..1)
        self.fc_node = FcEscNode(self.bus, config, t0, report, failsafe)
        self.escs = {nid: EmulatedEsc(self.bus, nid, i, self.throttle, t0)
                     for i, nid in enumerate(config.esc_node_ids) if nid not in config.external}
        self._external_index = {config.esc_node_ids.index(nid) for nid in config.external}
        self.max_rotor_speed_rad_s = 1.0
        self._nodes_due_s = t0  # the earliest `due_s` of the nodes, as of the last poll

    def reconfigure(self, **changes: Any) -> None:
        """Change the FC's ESC watch in flight (``status_timeout_s``, ``failsafe_action``)."""
        self.config = replace(self.config, **changes)
        self.fc_node.config = self.config
        self._nodes_due_s = -math.inf  # (poll at the next step)

    def poll(self, t: float, rotor_speed_rad_s: np.ndarray, armed: bool) -> None:
        """Everything due by ``t`` (s): frames delivered, ESC reports, the FC's watch."""
        self.bus.advance_to(t)  # (what it delivers only moves the nodes' times later)
        fc = self.fc_node
        if t >= self._nodes_due_s - 1e-12:
            due = math.inf
            for esc in self.escs.values():
                d = esc.due_s()
                if t >= d - 1e-12 or esc.silent:
                    esc.poll(t, float(rotor_speed_rad_s[esc.index]))
                    d = esc.due_s()
                due = d if d < due else due
            d = fc.due_s()
            if t >= d - 1e-12:
                fc.poll(t, armed)
                d = fc.due_s()
            self._nodes_due_s = d if d < due else due
        for i in self._external_index:  # an outside ESC's motor follows the rpm it reports
            w = fc.escs[i].rpm * 2.0 * math.pi / 60.0
            self.throttle[i] = min(1.0, max(0.0, w / self.max_rotor_speed_rad_s) ** 2)

    def set_silent(self, esc_index: int, silent: bool) -> None:
        for esc in self.escs.values():
            if esc.index == esc_index:
                esc.silent = silent
        self._nodes_due_s = -math.inf  # (poll at the next step)

    def next_event_s(self) -> float:
        """When the bus or a node next has something to do (s). The nodes' times are those of the last
        poll: a status coming in only moves the FC's watch later, and a command due at an ESC arrives
        on the bus, whose own time is always current."""
        head = self.bus.next_event_s()
        return head if head < self._nodes_due_s else self._nodes_due_s

    def close(self) -> None:
        self.bus.close()


class EscBusStepper:
    """Steps an EmulatedVehicle with its motors behind an `EscBus`: the FC's loop at the motor rate
    (its output sent as RawCommand), the physics at its own rate with each motor at its ESC's throttle."""

    def __init__(self, vehicle: Any, esc: EscBus) -> None:
        self.vehicle, self.esc = vehicle, esc
        self.period_s = 1.0 / esc.config.command_rate_hz
        self.next_command_s = vehicle.time_s
        esc.max_rotor_speed_rad_s = vehicle.profile.max_rotor_speed_rad_s
        self.fc_steps = 0
        self.fc_quiet_steps = 0  # of them, those flown by the inner loop alone (see `_fc_throttles`)
        self.physics_steps = 0
        self.polls = 0  # times the bus and its nodes were polled (at their events only)
        #: the native backend's state rows (`NativeBackend.kernel_arrays`), None on another backend
        arrays = getattr(vehicle.backend, "kernel_arrays", None)
        self._x = None if arrays is None else arrays[0]

    def step(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps."""
        v, esc = self.vehicle, self.esc
        fc, be, dt = v.fc, v.backend, v.dt_s
        rotor = slice(13, 17)  # (`VehicleState.to_vector` layout: the rotor speeds)
        esc.bus.take_external(v.time_s)  # (a real bus: read once per call, about once a millisecond)
        while n_steps > 0:
            t = v.time_s
            event_s = esc.next_event_s()
            if t >= event_s - 1e-9:
                esc.poll(t, v.state_vector()[rotor], fc.state.armed)
                self.polls += 1
                event_s = esc.next_event_s()
            if t >= self.next_command_s - 1e-9:
                esc.fc_node.send_command(self._fc_throttles(t), t)
                self.fc_steps += 1
                self.next_command_s += self.period_s
                if self.next_command_s <= t:
                    self.next_command_s = t + self.period_s
                esc.bus.advance_to(t)
                event_s = esc.next_event_s()
            until = min(self.next_command_s, event_s)
            k = max(1, min(n_steps, math.ceil((until - t) / dt - 1e-6)))
            be.step(esc.throttle, k)
            v.invalidate_state()
            v.steps += k
            self.physics_steps += k
            n_steps -= k

    def _fc_throttles(self, t: float) -> np.ndarray:
        """The FC's motor outputs at ``t`` (s). While it flies an offboard attitude target with no timed
        change due (`FlightController.quiet_steps`), as the lockstep runner's batched steps do: its
        inner loop on the state's rows, then `stepped_outside`'s bookkeeping; else its own `update`."""
        v, x = self.vehicle, self._x
        fc = v.fc
        tg = fc.held_target()
        if x is None or tg is None or fc.quiet_steps(t, v.dt_s, 1) < 1:
            return fc.update(v.state)
        out = fc.inner.update(x[6:10], x[10:13], tg.roll_rad, tg.pitch_rad, tg.yaw_rad, tg.thrust_n)
        fc.stepped_outside(t, x.item(2), x.item(5))
        self.fc_quiet_steps += 1
        return out

    def summary(self, now_s: float) -> dict[str, Any]:
        bus = self.esc.bus
        return {
            "bus": bus.stats.as_dict(), "load": round(bus.load(now_s), 4), "commands_sent":
            self.esc.fc_node.commands_sent,
            "throttle": [round(float(u), 4) for u in self.esc.throttle],  # what each motor runs at
            "escs": [
                {"index": i, "node_id": nid, "external": nid in self.esc.config.external,
                 "failed": h.failed, "rpm": h.rpm, "error_count": h.error_count}
                for i, (nid, h) in enumerate(zip(self.esc.config.esc_node_ids, self.esc.fc_node.escs,
                                                 strict=True))],
        }



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
    stepper = EscBusStepper(vehicle, esc)
    vehicle.motor_path = stepper
    server.params.esc = esc
    return stepper
