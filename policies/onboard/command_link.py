"""The onboard computer's MAVLink client over the command link: heartbeats, commands with ACKs, mode
tracking from the FC's HEARTBEAT, attitude-thrust setpoints, and lockstep TIMESYNC ticks.

World ENU / body FLU inside; the conversion to NED/FRD happens here, through `hil.link.mavlink`.
Nothing here blocks: `poll()` parses what has arrived, the senders write one frame each.

Only the FC (system ``target_system``, component autopilot 1) sets the program's view of the FC, answers
its commands and ticks its clock: heartbeats, ACKs and lockstep ticks (TIMESYNC requests and the mocap
byte count) from anyone else on the link are ignored and counted in ``foreign``.
"""

from __future__ import annotations

import contextlib
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

from hil.link.clock import Clock
from hil.link.lockstep import (
    TICK_MSG_IDS,
    TIMESYNC_ID,
    answer_payload,
    mocap_count,
    read_tick_frame,
    tick_request_s,
)
from hil.link.mavlink import (
    PX4_AUTO_LOITER,
    PX4_MAIN_AUTO,
    PX4_MAIN_OFFBOARD,
    MavlinkCodec,
    MAVLinkMessage,
    decode_frame,
    mav,
    px4_mode_parts,
    quat_enu_flu_to_ned_frd_tuple,
    quat_from_euler_tuple,
    quat_ned_frd_from_euler,
)
from hil.link.transport import Transport
from policies.compiling import Kernel

ONBOARD_SYSTEM_ID = 1  # same vehicle as the FC (PX4 companion convention)
ONBOARD_COMPONENT_ID = mav.MAV_COMP_ID_ONBOARD_COMPUTER
FC_COMPONENT_ID = mav.MAV_COMP_ID_AUTOPILOT1
#: the FC's messages this client acts on; other telemetry is CRC-checked and dropped undecoded
USED_MSG_IDS = frozenset({mav.MAVLINK_MSG_ID_HEARTBEAT, mav.MAVLINK_MSG_ID_COMMAND_ACK,
                          mav.MAVLINK_MSG_ID_TIMESYNC, mav.MAVLINK_MSG_ID_STATUSTEXT,
                          mav.MAVLINK_MSG_ID_NAMED_VALUE_INT})
#: the lockstep's own per-tick messages, which the codec hands over as frames and this client reads
#: straight from the payload (`hil.link.lockstep.read_tick_frame`): no pymavlink objects for them
RAW_MSG_IDS = TICK_MSG_IDS
#: lockstep ticks whose answers are kept to be sent again unchanged when a tick is repeated
ANSWERS_KEPT = 8
READ_BYTES = 65536  # one read takes up to this much
#: a read shorter than this emptied the link (a tty hands over at most its 4 KiB line buffer per read)
SHORT_READ_BYTES = 4000
#: payload layouts (wire order) of the per-tick messages, framed by `MavlinkCodec.pack_payload`
_ATTITUDE_TARGET = mav.MAVLink_set_attitude_target_message.unpacker
_ATTITUDE_TARGET_ID = mav.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET
#: SET_ATTITUDE_TARGET type_mask: ignore the three body rates, use attitude and thrust
ATTITUDE_THRUST_TYPE_MASK = 0b0000_0111
#: the setpoint's attitude as the wire's body FRD -> world NED quaternion, compiled (one call a setpoint
#: instead of three and their float math): `quat_ned_frd_from_euler`
NED_FRD_QUAT = Kernel(quat_ned_frd_from_euler, quat_from_euler_tuple=Kernel(quat_from_euler_tuple),
                      quat_enu_flu_to_ned_frd_tuple=Kernel(quat_enu_flu_to_ned_frd_tuple))
#: DO_SET_MODE base mode: custom mode enabled (1) | safety armed flag passed through (128)
PX4_BASE_MODE_CUSTOM = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_SAFETY_ARMED


def clipped_thrust(fraction: float) -> float:
    """A thrust fraction within 0..1 (a finite one; as min(1, max(0, fraction)), without the two calls)."""
    return (fraction if fraction < 1.0 else 1.0) if fraction > 0.0 else 0.0


def setpoint_wire(roll_rad: float, pitch_rad: float, yaw_rad: float, thrust_fraction: float
                  ) -> tuple[float, float, float, float, float]:
    """A setpoint's numbers as SET_ATTITUDE_TARGET carries them: the attitude of ZYX Euler angles of body
    FLU -> world ENU (rad) as body FRD -> world NED (w, x, y, z: `quat_ned_frd_from_euler`), and the
    thrust fraction clipped to 0..1 (`clipped_thrust`; a finite one). Compiled (`SETPOINT_WIRE`): one
    call a setpoint."""
    w, x, y, z = quat_ned_frd_from_euler(roll_rad, pitch_rad, yaw_rad)
    return w, x, y, z, clipped_thrust(thrust_fraction)


CLIPPED_THRUST = Kernel(clipped_thrust)
#: the setpoint's numbers on the wire, compiled: `setpoint_wire`
SETPOINT_WIRE = Kernel(setpoint_wire, quat_ned_frd_from_euler=NED_FRD_QUAT, clipped_thrust=CLIPPED_THRUST)


@dataclass(frozen=True)
class CommandAck:
    """The FC's answer to a COMMAND_LONG: result code (MAV_RESULT) and our clock time (s)."""

    command: int
    result: int
    time_s: float

    @property
    def accepted(self) -> bool:
        return self.result == mav.MAV_RESULT_ACCEPTED


@dataclass(frozen=True)
class FcStatus:
    """What the FC's last HEARTBEAT said: armed flag, PX4 main and sub mode, when it came (s)."""

    armed: bool
    main_mode: int
    sub_mode: int
    system_status: int
    time_s: float

    @property
    def offboard(self) -> bool:
        return self.main_mode == PX4_MAIN_OFFBOARD

    @property
    def holding(self) -> bool:
        """AUTO.LOITER (PX4 "Hold"): the FC holds position on its own."""
        return self.main_mode == PX4_MAIN_AUTO and self.sub_mode == PX4_AUTO_LOITER


class CommandLink:
    """MAVLink client of the FC on ``transport``, stamped with ``clock`` (s)."""

    #: the protocol, as the onboard program's options name it
    protocol = "mavlink"

    def __init__(self, transport: Transport, clock: Clock, target_system: int = 1, *,
                 codec: Any = None) -> None:
        """``codec``: another protocol's codec (a subclass's: `DjiCommandLink`), whose ``feed`` gives
        the items `_handle` acts on; None: MAVLink 2."""
        self.codec = codec or MavlinkCodec(transport, clock, ONBOARD_SYSTEM_ID, ONBOARD_COMPONENT_ID,
                                           accept_ids=USED_MSG_IDS, raw_ids=RAW_MSG_IDS)
        self.clock = clock
        self.target_system = target_system
        #: whether a read shorter than `SHORT_READ_BYTES` took all there was (the transport's kind)
        self._short_read_is_all = getattr(self.codec.transport, "short_read_is_all", False)
        self.status: FcStatus | None = None
        self.acks: dict[int, CommandAck] = {}
        self.status_texts: list[str] = []
        #: TIMESYNC ticks (s of the FC's simulated time) received and not yet taken by `take_ticks`
        self._ticks: list[float] = []
        self.setpoints_sent = 0
        #: set when the program runs on lockstep ticks: then, while ticks taken by `take_ticks` are not
        #: yet answered, frames are held and go out with the last answer in one write
        self.lockstep = False
        self._open_ticks = 0
        self._answers: dict[float, bytes] = {}  # the latest ticks answered (s) -> the answer's frame
        self._held: list[bytes] = []
        #: lockstep: messages (or frames of `RAW_MSG_IDS`) parsed but not yet acted on (those after a
        #: tick wait for it to be done)
        self._backlog: deque[MAVLinkMessage | bytes] = deque()
        #: lockstep: whether messages read are still waiting for their tick (the next `read` acts on them
        #: without new bytes; a plain attribute, set by each read: asked once a tick)
        self.backlogged = False
        #: lockstep: the mocap bytes the harness has written in all, as of the last tick handled (mod
        #: 2^31; None: it never said)
        self.mocap_announced: int | None = None
        #: messages ignored for not coming from the FC: heartbeats, acks, ticks (TIMESYNC requests and
        #: mocap byte counts)
        self.foreign = {"heartbeats": 0, "acks": 0, "ticks": 0}
        self._setpoint_wire = SETPOINT_WIRE.entry(0.0, 0.0, 0.0, 0.0)  # (compiled for floats: no dispatch)

    @property
    def transport(self) -> Transport:
        return self.codec.transport

    # --- input --------------------------------------------------------------------------------
    def poll(self, timeout_s: float = 0.0) -> list[MAVLinkMessage]:
        """Parse what has arrived (waiting up to ``timeout_s`` for the first bytes), act on it and return
        the messages acted on."""
        return [decode_frame(m) if m.__class__ is bytes else m for m in self._poll(timeout_s)]

    def read(self, timeout_s: float = 0.0) -> int:
        """`poll` without handing the messages back (the per-tick path: the lockstep's own messages are
        never built as pymavlink objects); returns how many were acted on."""
        return len(self._poll(timeout_s))

    def _poll(self, timeout_s: float) -> list[MAVLinkMessage | bytes]:
        """`poll`, with the frames of `RAW_MSG_IDS` the codec passed undecoded left as bytes."""
        if self._held:
            self.flush()
        codec = self.codec
        transport = codec.transport
        data = transport.recv(timeout_s, READ_BYTES)
        msgs = codec.feed(data) if data else []
        # drain what is waiting; on a stream whose short read took it all, no second (empty) read
        while data and not (self._short_read_is_all and len(data) < SHORT_READ_BYTES):
            data = transport.recv(0.0, READ_BYTES)
            if data:
                msgs.extend(codec.feed(data))
        # lockstep: act on the messages up to the next tick only; what came after it (the FC's next
        # tick, already written when the harness keeps two ticks in flight) waits for that tick
        backlog = self._backlog
        if backlog:  # (those waiting first; usually none: the read's own list is walked as it is)
            backlog.extend(msgs)
            msgs = list(backlog)
            backlog.clear()
        tick_list = self._ticks
        stop = len(tick_list) + 1 if self.lockstep else -1  # (the ticks at which it stops; -1: none)
        handle, target = self._handle, self.target_system
        done = 0  # messages acted on
        for m in msgs:
            done += 1
            if m.__class__ is not bytes:
                handle(m)
                if len(tick_list) == stop:
                    break
            # a good MAVLink 2 frame of one of `RAW_MSG_IDS`, read here (`_handle` of its message, two
            # calls less a frame: two a tick)
            elif m[5] != target or m[6] != FC_COMPONENT_ID:  # MAVLink 2: sender at 5, 6
                self.foreign["ticks"] += 1
            else:
                tick_s, mocap_total = read_tick_frame(m)  # (`_on_tick`'s, without the call)
                if mocap_total is not None:
                    self.mocap_announced = mocap_total
                if tick_s is not None:
                    tick_list.append(tick_s)
                    if len(tick_list) == stop:
                        break
        if done < len(msgs):  # the rest waits for its tick
            backlog.extend(msgs[done:])
            self.backlogged = True
            return msgs[:done]
        self.backlogged = False
        return msgs

    def _on_tick(self, tick_s: float | None, mocap_total: int | None) -> None:
        """The harness's mocap byte total, then a lockstep tick request at ``tick_s`` (s) (None: not
        said)."""
        if mocap_total is not None:
            self.mocap_announced = mocap_total
        if tick_s is not None:
            self._ticks.append(tick_s)

    def _handle(self, m: MAVLinkMessage) -> None:
        kind = m.get_type()
        now = self.clock.now_s()
        if kind != "STATUSTEXT" and (m.get_srcSystem() != self.target_system
                                     or m.get_srcComponent() != FC_COMPONENT_ID):
            key = "heartbeats" if kind == "HEARTBEAT" else "acks" if kind == "COMMAND_ACK" else "ticks"
            self.foreign[key] += 1
            return
        if kind == "HEARTBEAT":
            if m.autopilot == mav.MAV_AUTOPILOT_INVALID:
                self.foreign["heartbeats"] += 1
                return
            main, sub = px4_mode_parts(m.custom_mode)
            armed = bool(m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
            self.status = FcStatus(armed, main, sub, m.system_status, now)
        elif kind == "COMMAND_ACK":
            self.acks[m.command] = CommandAck(m.command, m.result, now)
        elif kind == "TIMESYNC":
            self._on_tick(tick_request_s(m.tc1, m.ts1), None)
        elif kind == "NAMED_VALUE_INT":
            self._on_tick(None, mocap_count(m.name, m.value))
        elif kind == "STATUSTEXT":
            self.status_texts.append(str(m.text))

    def take_ticks(self) -> list[float]:
        """The TIMESYNC tick times (s) received since the last call, oldest first."""
        ticks, self._ticks = self._ticks, []
        if self.lockstep:
            self._open_ticks = len(ticks)
        return ticks

    def read_ticks(self) -> list[float]:
        """`read`, then `take_ticks`: the lockstep's read of its command link, one call a tick."""
        self._poll(0.0)
        ticks, self._ticks = self._ticks, []  # (`take_ticks`, without its call)
        if self.lockstep:
            self._open_ticks = len(ticks)
        return ticks

    def heartbeat_age_s(self, now_s: float) -> float:
        """Seconds since the FC's last HEARTBEAT (inf if none yet)."""
        return math.inf if self.status is None else now_s - self.status.time_s

    # --- output -------------------------------------------------------------------------------
    def _send(self, msg: MAVLinkMessage) -> None:
        self._send_frame(self.codec.pack(msg))

    def _send_frame(self, frame: bytes) -> None:
        if self._open_ticks > 0:
            self._held.append(frame)
        else:
            transport = self.codec.transport
            transport.send(frame)

    def flush(self) -> None:
        """Write the held frames now (one write)."""
        if self._held:
            data = b"".join(self._held)
            self._held.clear()
            transport = self.codec.transport
            if not transport.closed:
                transport.send(data)

    def send_heartbeat(self) -> None:
        """The companion computer's own 1 Hz HEARTBEAT."""
        self._send(self.codec.mav.heartbeat_encode(
            mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE))

    def send_attitude_target(self, roll_rad: float, pitch_rad: float, yaw_rad: float,
                             thrust_fraction: float) -> None:
        """One attitude-thrust setpoint: ZYX Euler angles of body FLU -> world ENU (rad), thrust 0..1 of
        the N3's full thrust (clipped). Sent as SET_ATTITUDE_TARGET, NED -> FRD quaternion. ValueError,
        nothing sent, when a value is not finite (a NaN thrust is no zero thrust)."""
        thrust = float(thrust_fraction)
        if not math.isfinite(roll_rad + pitch_rad + yaw_rad + thrust):
            raise ValueError(f"setpoint not finite: roll {roll_rad} rad, pitch {pitch_rad} rad, "
                             f"yaw {yaw_rad} rad, thrust {thrust}")
        w, x, y, z, thrust = self._setpoint_wire(roll_rad, pitch_rad, yaw_rad, thrust)  # (`setpoint_wire`)
        now_ms = int(self.clock.now_s() * 1000) & 0xFFFFFFFF
        payload = _ATTITUDE_TARGET.pack(now_ms, w, x, y, z, 0.0, 0.0, 0.0, thrust, self.target_system,
                                        FC_COMPONENT_ID, ATTITUDE_THRUST_TYPE_MASK)
        frame = self.codec.pack_payload(_ATTITUDE_TARGET_ID, payload)
        if self._open_ticks > 0:  # held for the tick's answer (`_send_frame`, without the call: per tick)
            self._held.append(frame)
        else:
            self._send_frame(frame)
        self.setpoints_sent += 1

    def send_command(self, command: int, *params: float) -> None:
        """COMMAND_LONG ``command`` with up to seven parameters; forgets any earlier ACK of it."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.acks.pop(command, None)
        self._send(self.codec.mav.command_long_encode(
            self.target_system, FC_COMPONENT_ID, command, 0, *p))

    def request_arm(self) -> None:
        self.send_command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)

    def request_heartbeat(self) -> None:
        """MAV_CMD_REQUEST_MESSAGE for the FC's HEARTBEAT: sent while none has come, so the program need
        not wait up to a second for the FC's own 1 Hz one."""
        self.send_command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HEARTBEAT)

    def request_offboard(self) -> None:
        """DO_SET_MODE to PX4 OFFBOARD (p1 = 129, p2 = 6)."""
        self.send_command(mav.MAV_CMD_DO_SET_MODE, PX4_BASE_MODE_CUSTOM, PX4_MAIN_OFFBOARD)

    def request_hold(self) -> None:
        """DO_SET_MODE to PX4 AUTO.LOITER ("Hold": p2 = 4, p3 = 3), the FC hovering on its own."""
        self.send_command(mav.MAV_CMD_DO_SET_MODE, PX4_BASE_MODE_CUSTOM, PX4_MAIN_AUTO, PX4_AUTO_LOITER)

    def answer_tick(self, tick_s: float) -> None:
        """Lockstep "done with this tick" (`hil.link.lockstep`). A tick answered before (sent again on the
        harness's wall-clock timeout) gets the same frame again, sequence number and all: how often a
        tick is repeated depends on process scheduling, and the frames after it must not."""
        answers = self._answers
        frame = answers.get(tick_s)
        if frame is None:
            frame = self._answer_frame(tick_s)
            if len(answers) >= ANSWERS_KEPT:
                del answers[next(iter(answers))]
            answers[tick_s] = frame
        open_ticks = self._open_ticks
        if open_ticks > 0:  # held with the tick's other frames (`_send_frame`, without the call: per tick)
            held = self._held
            held.append(frame)
            self._open_ticks = open_ticks = open_ticks - 1
            if open_ticks == 0:  # the last tick taken is answered: its frames go in one write (`flush`,
                data = b"".join(held)  # without its call: per tick)
                held.clear()
                transport = self.codec.transport
                if not transport.closed:
                    transport.send(data)
        else:
            self._send_frame(frame)
            self.flush()

    def _answer_frame(self, tick_s: float) -> bytes:
        """The frame that answers the tick at ``tick_s`` (s) on this link's protocol."""
        return self.codec.pack_payload(TIMESYNC_ID, answer_payload(tick_s))

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.flush()
        self.codec.transport.close()
