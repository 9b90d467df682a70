"""The FC's MAVLink endpoint: PX4-style heartbeat and telemetry, commands, offboard attitude setpoints.

`MavlinkServer.poll(now_s)` parses what arrived, acts on it, and sends what is due at ``now_s`` (clock
seconds), so a real-time loop and a lockstep runner drive it the same way. SET_ATTITUDE_TARGET is mapped
onto the N3 attitude-thrust interface: quaternion (NED -> FRD) -> ground-frame roll/pitch/yaw, thrust
0..1 -> 0..100 %, type_mask bit 4 clear -> yaw rate from body_yaw_rate. Bad input is counted in `stats`
and answered where MAVLink has a way (COMMAND_ACK, STATUSTEXT); it never raises out of `poll`.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from operator import index
from typing import Any

from numba import njit

from emulator.fc.modes import CommandResult, FcState
from emulator.fc.n3 import (
    ACCEPTED_FIELDS,
    ATTITUDE_THRUST_YAW_ANGLE,
    ATTITUDE_THRUST_YAW_RATE,
    SetpointRejected,
    attitude_thrust_target,
    attitude_thrust_values,
    rejection,
)
from emulator.kernel_cache import entry
from emulator.params import BY_NAME, INT, PARAMS, ParamDef, ParamError, Parameters, read_param_file
from emulator.servers.arrivals import arrivals
from emulator.servers.link_budget import LinkBudget
from emulator.servers.telemetry import DEFAULT_INTERVALS_S, MIN_INTERVAL_S, Home, TelemetryEncoder
from emulator.vehicle import EmulatedVehicle
from hil.link.mavlink import (
    PX4_AUTO_LAND,
    PX4_AUTO_LOITER,
    PX4_MAIN_AUTO,
    PX4_MAIN_OFFBOARD,
    MavlinkCodec,
    MAVLinkMessage,
    decode_frame,
    euler_from_quat,
    mav,
    max_frame_bytes,
    message_from_payload,
)

#: messages acted on in one `MavlinkServer.poll` at most: the rest wait for the next pass (and a flood
#: waits in the transport, where a UDP socket counts what it drops), so a flood cannot stall the loop
MAX_MESSAGES_PER_POLL = 512
FORCE_DISARM_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that forces a disarm in the air
ON_REQUEST = (mav.MAVLINK_MSG_ID_HOME_POSITION, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
#: ids the server can take as undecoded frames: a codec built with these as its ``raw_ids`` hands the
#: setpoints over as bytes, and `handle` reads them without a message object
RAW_MSG_IDS: frozenset[int] = frozenset({mav.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET})
_SET_ATTITUDE_TARGET = mav.MAVLink_set_attitude_target_message.unpacker  # its payload, in wire order
_SET_ATTITUDE_TARGET_SIZE = _SET_ATTITUDE_TARGET.size  # (bytes; a Struct's size is a slow attribute)
_SET_ATTITUDE_TARGET_ID = mav.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET
#: streamed messages read from the vehicle's state (`TelemetryEncoder.state_values`, read once per send)
_STATE_STREAMS = frozenset({mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED})
#: streams the link budget keeps at their rate up to 1 Hz (a ground station counts a link lost without it)
FIXED_STREAMS = frozenset({mav.MAVLINK_MSG_ID_HEARTBEAT})
#: the recorder's ``tick`` (its flush check, for a link that has gone quiet: each frame recorded checks
#: too) is called at most this often (s of the poll's clock)
RECORDER_TICK_S = 0.05


@dataclass(frozen=True)
class ServerConfig:
    """Identity and behaviour of the FC's MAVLink endpoint."""

    system_id: int = 1
    component_id: int = mav.MAV_COMP_ID_AUTOPILOT1
    home: Home = field(default_factory=Home)
    statustext_interval_s: float = 1.0  # repeats of one kind of STATUSTEXT at most this often
    stream_intervals_s: dict[int, float] = field(default_factory=lambda: dict(DEFAULT_INTERVALS_S))
    #: the parameter file MAV_CMD_PREFLIGHT_STORAGE reads (param1 0) and writes (param1 1); None: none
    param_file: str | None = None
    #: the command link's baud when it is a serial line (bit/s): the streams then keep to its data rate
    #: (`emulator.servers.link_budget`); None: no budget unless MAV_0_RATE sets one
    link_baud: int | None = None


@dataclass
class ServerStats:
    """What the server did with what it received (counts)."""

    setpoints_applied: int = 0
    setpoints_rejected: int = 0
    commands_accepted: int = 0
    commands_denied: int = 0
    commands_unsupported: int = 0
    foreign_target: int = 0  # addressed to another system or component: ignored
    statustext_sent: int = 0
    statustext_suppressed: int = 0
    handler_errors: int = 0
    params_sent: int = 0  # PARAM_VALUEs
    params_set: int = 0  # PARAM_SETs that changed a value (or set the same)
    params_refused: int = 0  # PARAM_SETs refused: unknown name, wrong type, out of range
    ftp_nak: int = 0  # MAVLink FTP requests answered NAK (this FC has no file system)
    intake_deferred: int = 0  # messages put off to the next pass (more than MAX_MESSAGES_PER_POLL waited)

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class MavlinkServer:
    """Serves one vehicle's FC over one MAVLink codec."""

    def __init__(
        self, vehicle: EmulatedVehicle, codec: MavlinkCodec, config: ServerConfig | None = None
    ) -> None:
        self.vehicle = vehicle
        self.fc = vehicle.fc
        self._fc_events = vehicle.fc.events  # (the FC's list of events, appended to)
        self.codec = codec
        self.config = config or ServerConfig()
        self.stats = ServerStats()
        #: the target ids this server answers to: 0 (broadcast) or the codec's own (fixed for its life)
        self._systems = (0, codec.system_id)
        self._components = (0, codec.component_id)
        self.telemetry = TelemetryEncoder(vehicle, codec.mav, self.config.home)
        self._requested = dict(self.config.stream_intervals_s)  # intervals asked for (s)
        self._now_s = 0.0  # the last poll's time (s)
        self._polled_s: float | None = None  # the same, None before the first poll
        #: the link's data-rate budget (None: none, every stream at the rate asked)
        self.budget: LinkBudget | None = None
        if self.config.link_baud is not None:
            self.budget = self._new_budget(self.config.link_baud)
        self._intervals = self._granted()  # intervals streamed at (s)
        self._next_due: dict[int, float] = {}
        self._streams_due_s = -math.inf  # the earliest next due time of any stream (s)
        #: the earlier of `_streams_due_s` and `_recorder_tick_s`: a poll before it sends nothing (s)
        self._due_s = -math.inf
        self._events_seen = 0
        self._backlog: list[Any] = []  # received, to be acted on in the next passes
        self._param_list: deque[int] = deque()  # parameter indices still to send (a budgeted link)
        self._timed_transport: object | None = None  # the transport `_arrivals` is of
        self._arrivals: Any = arrivals(None)  # what ``next_input_s`` is read from (the transport)
        self._last_text_s: dict[str, float] = {}
        #: never called: whatever this server has to say goes to the peer in a STATUSTEXT
        #: (`emulator.servers.registry.FcServer.on_untold`)
        self.on_untold: Callable[[str], None] | None = None
        #: called with (message, now_s) after a setpoint is applied (for latency measurements)
        self.on_setpoint: Callable[[MAVLinkMessage, float], None] | None = None
        self._senders: dict[int, Callable[[float], MAVLinkMessage]] = {
            mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self.telemetry.attitude_quaternion,
            mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self.telemetry.global_position_int,
            mav.MAVLINK_MSG_ID_HIGHRES_IMU: self.telemetry.highres_imu,
            mav.MAVLINK_MSG_ID_SYS_STATUS: lambda t: self.telemetry.sys_status(t, self.codec.stats.errors),
            mav.MAVLINK_MSG_ID_BATTERY_STATUS: self.telemetry.battery_status,
            mav.MAVLINK_MSG_ID_HOME_POSITION: self.telemetry.home_position,
            mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: lambda t: self.telemetry.autopilot_version(
                self.codec.system_id
            ),
        }
        self._handlers: dict[str, Callable[[MAVLinkMessage, float], None]] = {
            "SET_ATTITUDE_TARGET": self._on_set_attitude_target,
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_MODE": self._on_set_mode,
            "PING": self._on_ping,
            "TIMESYNC": self._on_timesync,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "FILE_TRANSFER_PROTOCOL": self._on_ftp,
            "MISSION_REQUEST_LIST": self._on_mission_request_list,
        }
        #: the same by message class (a class's messages all have its type name): one lookup per message
        self._class_handlers: dict[type, Callable[[MAVLinkMessage, float], None]] = {
            mav.mavlink_map[getattr(mav, f"MAVLINK_MSG_ID_{name}")]: handler
            for name, handler in self._handlers.items()
        }
        #: streams the telemetry gives as payloads (built without message objects): the message, when
        #: one is asked for, is read back from the payload
        t = self.telemetry
        self._payloads: dict[int, Callable[[float, Any], bytes]] = {
            mav.MAVLINK_MSG_ID_HEARTBEAT: lambda now_s, x: t.heartbeat_payload(),
            mav.MAVLINK_MSG_ID_ATTITUDE: t.attitude_payload,
            mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: t.local_position_ned_payload,
            mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: lambda now_s, x: t.extended_sys_state_payload(),
        }
        for msg_id, make in self._payloads.items():
            self._senders[msg_id] = lambda now_s, i=msg_id, f=make: message_from_payload(
                i, f(now_s, t.state_values()))
        self._recorder: object | None = None  # what `poll` last looked up ``tick`` on
        self._recorder_tick: Callable[[], None] | None = None
        self._recorder_tick_s = math.inf  # when `poll` calls it next (s; inf: no recorder)
        #: the FC's parameters (`emulator.params`); every change is broadcast as a PARAM_VALUE
        self.params = Parameters(self.fc, self)
        self.params.on_change = lambda name, value: self._send_param(BY_NAME[name], value)
        self._attitude_target = setpoint_kernel()

    # --- the loop ----------------------------------------------------------------------------
    def poll(self, now_s: float) -> None:
        """Parse and act on what arrived (at most `MAX_MESSAGES_PER_POLL`), then send what is due at
        ``now_s``.

        A transport that models arrival times is read only when something has arrived
        (`emulator.servers.arrivals`)."""
        self._now_s = now_s
        prev_s, self._polled_s = self._polled_s, now_s
        codec = self.codec
        if codec.transport is not self._timed_transport:  # (looked up once per transport)
            self._timed_transport = codec.transport
            self._arrivals = arrivals(codec.transport)
        if self._backlog or self._arrivals.next_input_s <= now_s + 1e-12:
            backlog = self._backlog
            msgs = backlog or codec.receive(0.0, now_s)  # (logged at the time they are acted on)
            if len(msgs) > MAX_MESSAGES_PER_POLL:
                self._backlog = msgs[MAX_MESSAGES_PER_POLL:]
                self.stats.intake_deferred += len(self._backlog)
                msgs = msgs[:MAX_MESSAGES_PER_POLL]
            elif backlog:
                self._backlog = []
            for msg in msgs:
                self.handle(msg, now_s)
        if self._param_list:
            self._send_param_list()
        if self._events_seen != len(self._fc_events):
            self.telemetry.state_changed(prev_s, now_s)  # (the battery's armed time)
            self._report_events(now_s)
        if now_s >= self._due_s:  # (most polls: nothing streamed, no flush check)
            self._send_due(now_s)

    def _send_due(self, now_s: float) -> None:
        """The streams due at ``now_s`` and the recorder's flush check when it is due; `_due_s` set to
        the earlier of the two next times."""
        if now_s >= self._streams_due_s:
            self._send_streams(now_s)
        recorder = self.codec.recorder
        if recorder is not self._recorder:  # (looked up once per recorder)
            self._recorder = recorder
            self._recorder_tick = getattr(recorder, "tick", None) if recorder is not None else None
            self._recorder_tick_s = -math.inf if self._recorder_tick is not None else math.inf
        if now_s >= self._recorder_tick_s:
            self._recorder_tick_s = now_s + RECORDER_TICK_S
            self._recorder_tick()  # type: ignore[misc]
        due = self._streams_due_s
        self._due_s = due if due < self._recorder_tick_s else self._recorder_tick_s

    def handle(self, msg: MAVLinkMessage | bytes, now_s: float) -> None:
        """Act on one received message, or on the frame of one a codec hands over undecoded
        (`RAW_MSG_IDS`); never raises."""
        if msg.__class__ is bytes:
            frame: bytes = msg  # type: ignore[assignment]
            if frame[7] | frame[8] << 8 | frame[9] << 16 == _SET_ATTITUDE_TARGET_ID:
                handler = self._on_set_attitude_target_frame
            else:
                msg = decode_frame(frame)
                handler = self._handlers.get(msg.get_type())
        else:
            handler = self._class_handlers.get(msg.__class__) or self._handlers.get(msg.get_type())
        if handler is None:
            return
        try:
            handler(msg, now_s)
        except Exception as exc:  # a message the handlers did not foresee: count and tell, don't die
            self.stats.handler_errors += 1
            name = "SET_ATTITUDE_TARGET" if msg.__class__ is bytes else msg.get_type()
            self.statustext(mav.MAV_SEVERITY_ERROR, f"{name} ignored: {type(exc).__name__}", now_s)

    def send(self, msg: MAVLinkMessage) -> None:
        """Send an answer (or anything not streamed); on a budgeted line only while it fits whole."""
        if self._admitted(msg.get_msgId(), False):
            self.codec.send(msg)

    def statustext(self, severity: int, text: str, now_s: float, key: str | None = None) -> bool:
        """Send a STATUSTEXT (at most 50 characters), rate-limited per ``key``; True if sent."""
        key = key or text
        last = self._last_text_s.get(key)
        if last is not None and now_s - last < self.config.statustext_interval_s:
            self.stats.statustext_suppressed += 1
            return False
        self._last_text_s[key] = now_s
        self.send(self.codec.mav.statustext_encode(severity, text.encode("ascii", "replace")[:50]))
        self.stats.statustext_sent += 1
        return True

    def _send_streams(self, now_s: float) -> None:
        if now_s < self._streams_due_s:
            return  # nothing due yet (most polls)
        due_min = math.inf
        next_due, payloads, budget = self._next_due, self._payloads, self.budget
        x = None  # the vehicle's state values, read once for all the streams due now
        for msg_id, interval in self._intervals.items():
            due = next_due.get(msg_id, now_s)
            if now_s >= due:
                make = payloads.get(msg_id)
                if budget is not None and msg_id not in FIXED_STREAMS and not self._admitted(msg_id, True):
                    pass  # the line's queue is too deep: this one is dropped (counted)
                elif make is None:
                    self.codec.send(self._senders[msg_id](now_s))
                else:
                    if x is None and msg_id in _STATE_STREAMS:
                        x = self.telemetry.state_values()
                    self._send_payload(msg_id, make(now_s, x))
                nxt = due + interval
                due = next_due[msg_id] = nxt if nxt > now_s else now_s + interval
            if due < due_min:
                due_min = due
        self._streams_due_s = due_min

    def _report_events(self, now_s: float) -> None:
        events = self.fc.events
        if self._events_seen == len(events):
            return
        for ev in events[self._events_seen :]:
            if ev.to_state.failsafe:
                self.statustext(
                    mav.MAV_SEVERITY_CRITICAL, f"Failsafe: {ev.reason}", now_s, key=f"ev:{ev.reason}"
                )
            else:
                self.statustext(mav.MAV_SEVERITY_INFO, ev.reason, now_s, key=f"ev:{ev.reason}")
        self._events_seen = len(events)
        # let clients see the new mode now, not at the next 1 Hz beat
        self._send_payload(mav.MAVLINK_MSG_ID_HEARTBEAT, self.telemetry.heartbeat_payload())

    def _send_payload(self, msg_id: int, payload: bytes) -> None:
        if msg_id in FIXED_STREAMS and not self._admitted(msg_id, False):
            return
        codec = self.codec
        codec.transport.send(codec.pack_payload(msg_id, payload))

    # --- setpoints -------------------------------------------------------------------------
    def _for_me(self, target_system: int, target_component: int | None) -> bool:
        mine = target_system in self._systems and (
            target_component is None or target_component in self._components
        )
        if not mine:
            self.stats.foreign_target += 1
        return mine

    def _on_set_attitude_target(self, msg: MAVLinkMessage, now_s: float) -> None:
        if not self._for_me(msg.target_system, msg.target_component):
            return
        try:
            values = attitude_target_values(msg.type_mask, msg.q, msg.thrust, msg.body_yaw_rate)
        except SetpointRejected as exc:
            self._setpoint_rejected(exc.reason, now_s)
            return
        if self._take_setpoint(*values, now_s) and self.on_setpoint is not None:
            self.on_setpoint(msg, now_s)

    def _on_set_attitude_target_frame(self, frame: bytes, now_s: float) -> None:
        """`_on_set_attitude_target` of the message in ``frame`` (unsigned, CRC checked), read from
        its payload (zero-padded or cut to the message's size, as pymavlink does)."""
        size = _SET_ATTITUDE_TARGET_SIZE
        if frame[1] == size:  # (the usual case: no trailing zeros trimmed)
            values = _SET_ATTITUDE_TARGET.unpack_from(frame, 10)
        else:
            values = _SET_ATTITUDE_TARGET.unpack(frame[10 : 10 + frame[1]][:size].ljust(size, b"\x00"))
        _, q0, q1, q2, q3, _, _, yaw_rate, thrust, target_system, target_component, type_mask = values
        if target_system not in self._systems or target_component not in self._components:
            self._for_me(target_system, target_component)  # (counts it)
            return
        fc = self.fc
        profile = fc.profile
        (verdict, flag, roll, pitch, thrust_percent, yaw, norm, fc_verdict, roll_rad, pitch_rad, heading,
         rate) = self._attitude_target(type_mask, q0, q1, q2, q3, thrust, yaw_rate, profile.max_tilt_deg,
                                       profile.max_yaw_rate_deg_s)
        if verdict != ATTITUDE_TAKEN:
            self._setpoint_rejected(attitude_rejection(verdict, thrust, norm), now_s)
            return
        if fc_verdict != ACCEPTED_FIELDS:
            self._setpoint_rejected(rejection(fc_verdict, roll, pitch, thrust_percent, yaw), now_s)
            return
        target = attitude_thrust_target(flag, roll_rad, pitch_rad, heading, rate, thrust_percent, profile)
        fc.take_target(target, now_s)
        self.stats.setpoints_applied += 1
        if self.on_setpoint is not None:
            self.on_setpoint(decode_frame(frame), now_s)

    def _take_setpoint(self, flag: int, roll_deg: float, pitch_deg: float, thrust_percent: float, yaw: float,
                       now_s: float) -> bool:
        """Hand a SET_ATTITUDE_TARGET's setpoint (`attitude_target_values`) to the FC; False (counted,
        told) when the FC refuses it."""
        try:
            self.fc.set_setpoint_values(flag, roll_deg, pitch_deg, thrust_percent, yaw, now_s)
        except SetpointRejected as exc:
            self._setpoint_rejected(exc.reason, now_s)
            return False
        self.stats.setpoints_applied += 1
        return True

    def _setpoint_rejected(self, reason: str, now_s: float) -> None:
        self.stats.setpoints_rejected += 1
        self.statustext(mav.MAV_SEVERITY_WARNING, f"Setpoint rejected: {reason}", now_s, key="setpoint")

    # --- commands --------------------------------------------------------------------------
    def _on_command_long(self, msg: MAVLinkMessage, now_s: float) -> None:
        if not self._for_me(msg.target_system, msg.target_component):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._command(msg, msg.command, params, now_s)

    def _on_command_int(self, msg: MAVLinkMessage, now_s: float) -> None:
        if not self._for_me(msg.target_system, msg.target_component):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._command(msg, msg.command, params, now_s)

    def _on_set_mode(self, msg: MAVLinkMessage, now_s: float) -> None:
        if not self._for_me(msg.target_system, None):
            return
        main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
        result = self._set_mode(msg.base_mode, main, sub, now_s)
        if not result.accepted:
            self.statustext(mav.MAV_SEVERITY_WARNING, result.reason, now_s, key="cmd:mode")

    def _command(self, msg: MAVLinkMessage, command: int, p: tuple[float, ...], now_s: float) -> None:
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        result, mav_result, follow_up = self._run_command(command, p, now_s)
        if mav_result == mav.MAV_RESULT_ACCEPTED:
            self.stats.commands_accepted += 1
        elif mav_result == mav.MAV_RESULT_UNSUPPORTED:
            self.stats.commands_unsupported += 1
        else:
            self.stats.commands_denied += 1
        if result.reason:
            self.statustext(mav.MAV_SEVERITY_WARNING, result.reason, now_s, key=f"cmd:{command}")
        self.send(self.codec.mav.command_ack_encode(command, mav_result, 0, 0, src_sys, src_comp))
        if follow_up is not None:
            self.send(follow_up)

    def _run_command(
        self, command: int, p: tuple[float, ...], now_s: float
    ) -> tuple[CommandResult, int, MAVLinkMessage | None]:
        """(result, MAV_RESULT, message to send after the ACK)."""
        denied = mav.MAV_RESULT_DENIED
        if command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] not in (0.0, 1.0):
                return CommandResult(False, f"arm/disarm: param1 must be 0 or 1, got {p[0]}"), denied, None
            if p[0] == 1.0:
                res = self.fc.arm(now_s)
            else:
                res = self.fc.disarm(now_s, force=p[1] == FORCE_DISARM_MAGIC)
            return res, _mav_result(res), None
        if command == mav.MAV_CMD_DO_SET_MODE:
            if not all(math.isfinite(x) for x in p[:3]):
                return CommandResult(False, "set mode: non-finite parameters"), denied, None
            res = self._set_mode(int(p[0]), int(p[1]), int(p[2]), now_s)
            return res, _mav_result(res), None
        if command == mav.MAV_CMD_NAV_LAND:
            res = self.fc.request_land(now_s)
            return res, _mav_result(res), None
        if command in (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            msg_id = int(p[0]) if command == mav.MAV_CMD_REQUEST_MESSAGE and math.isfinite(p[0]) else -1
            if command == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
                msg_id = mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION
            sender = self._senders.get(msg_id)
            if sender is None:
                return CommandResult(True), mav.MAV_RESULT_UNSUPPORTED, None
            return CommandResult(True), mav.MAV_RESULT_ACCEPTED, sender(now_s)
        if command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(p[0], p[1])
        if command == mav.MAV_CMD_PREFLIGHT_STORAGE:
            return self._param_storage(p[0], now_s)
        return CommandResult(True), mav.MAV_RESULT_UNSUPPORTED, None

    def _set_interval(self, id_param: float, interval_us: float) -> tuple[CommandResult, int, None]:
        if not (math.isfinite(id_param) and math.isfinite(interval_us)):
            return (
                CommandResult(False, "message interval: non-finite parameters"),
                mav.MAV_RESULT_DENIED,
                None,
            )
        msg_id = int(id_param)
        if msg_id not in self._senders or msg_id in ON_REQUEST:
            return CommandResult(True), mav.MAV_RESULT_UNSUPPORTED, None
        if interval_us == -1:
            hz = 0.0
        elif interval_us == 0:
            default = DEFAULT_INTERVALS_S.get(msg_id)
            hz = 0.0 if default is None else 1.0 / default
        elif interval_us > 0:
            hz = 1e6 / interval_us
        else:
            return (
                CommandResult(False, f"message interval {interval_us:g} us invalid"),
                mav.MAV_RESULT_DENIED,
                None,
            )
        self.set_stream_rate(msg_id, hz)
        return CommandResult(True), mav.MAV_RESULT_ACCEPTED, None

    def stream_rate_hz(self, msg_id: int) -> float:
        """The rate (Hz) asked for message ``msg_id`` (0: not streamed); `granted_rate_hz` is what the
        link's budget grants."""
        interval = self._requested.get(msg_id)
        return 0.0 if interval is None else 1.0 / interval

    def granted_rate_hz(self, msg_id: int) -> float:
        """The rate (Hz) message ``msg_id`` is streamed at now (0: not streamed)."""
        interval = self._intervals.get(msg_id)
        return 0.0 if interval is None else 1.0 / interval

    def _granted(self) -> dict[int, float]:
        return dict(self._requested) if self.budget is None else self.budget.grant(self._requested)

    def link_rate_bytes_s(self) -> float:
        """MAV_0_RATE: the streams' budget (bytes/s; 0: half the line, no budget off a serial line)."""
        return 0.0 if self.budget is None else self.budget.rate_param_bytes_s

    def set_link_rate(self, rate_bytes_s: float) -> None:
        """Set MAV_0_RATE (bytes/s, 0: from the baud) and scale the streams to it, from now."""
        if self.budget is None:
            self.budget = self._new_budget(None)
        self.budget.rate_param_bytes_s = float(rate_bytes_s)
        self._regrant()

    def _new_budget(self, baud: int | None) -> LinkBudget:
        return LinkBudget(baud, getattr(self.codec.transport, "uart", None), self._frame_bytes, FIXED_STREAMS)

    def _frame_bytes(self, msg_id: int) -> int:
        """The longest frame of ``msg_id`` on this link (bytes)."""
        return max_frame_bytes(msg_id, self.codec.signing)

    def _admitted(self, msg_id: int, stream: bool) -> bool:
        """Whether a frame of ``msg_id`` may be written now (a ``stream``'s, or an answer): always without
        a budget (`LinkBudget.admit`)."""
        return self.budget is None or self.budget.admit(self._frame_bytes(msg_id), stream)

    def _regrant(self) -> None:
        self._intervals = self._granted()
        self._next_due.clear()
        self._streams_due_s = self._due_s = -math.inf

    def set_stream_rate(self, msg_id: int, rate_hz: float) -> None:
        """Stream message ``msg_id`` at ``rate_hz`` (Hz; at most 1 / `MIN_INTERVAL_S`; 0: stop), from now."""
        if msg_id not in self._senders or msg_id in ON_REQUEST:
            raise ValueError(f"message {msg_id} cannot be streamed")
        if not (math.isfinite(rate_hz) and rate_hz >= 0):
            raise ValueError(f"stream rate must be a finite number >= 0 Hz, got {rate_hz!r}")
        if rate_hz == 0:
            self._requested.pop(msg_id, None)
        else:
            self._requested[msg_id] = max(MIN_INTERVAL_S, 1.0 / rate_hz)
        if self.budget is None:
            self._intervals = dict(self._requested)
            self._next_due.pop(msg_id, None)
            self._streams_due_s = self._due_s = -math.inf
            return
        self._regrant()
        asked, granted = self.stream_rate_hz(msg_id), self.granted_rate_hz(msg_id)
        if granted < asked * (1 - 1e-9):  # the line cannot carry it: say so
            text = self.budget.capped(mav.mavlink_map[msg_id].msgname, asked, granted)
            self.statustext(mav.MAV_SEVERITY_WARNING, text, self._now_s, key=f"cap:{msg_id}")

    def _set_mode(self, base_mode: int, main: int, sub: int, now_s: float) -> CommandResult:
        if not base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return CommandResult(False, "set mode: only PX4 custom modes supported")
        if main == PX4_MAIN_OFFBOARD:
            return self.fc.request_offboard(now_s)
        if main == PX4_MAIN_AUTO and sub == PX4_AUTO_LOITER:
            return self.fc.request_hold(now_s)
        if main == PX4_MAIN_AUTO and sub == PX4_AUTO_LAND:
            return self.fc.request_land(now_s)
        return CommandResult(False, f"mode {main}.{sub} unsupported: use OFFBOARD/HOLD/LAND")

    # --- small protocol services -------------------------------------------------------------
    def _on_ping(self, msg: MAVLinkMessage, now_s: float) -> None:
        if msg.target_system == 0 and msg.target_component == 0:  # a request, not someone's reply
            self.send(
                self.codec.mav.ping_encode(
                    msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )

    def _on_timesync(self, msg: MAVLinkMessage, now_s: float) -> None:
        if msg.tc1 == 0:
            self.send(self.codec.mav.timesync_encode(int(now_s * 1e9), msg.ts1))

    # --- parameters (PX4's parameter protocol; integers encoded bytewise, as PX4 does) -----------
    def _send_param(self, index: int, value: float | int) -> None:
        self.send(self._param_value(index, value))
        self.stats.params_sent += 1

    def _param_value(self, index: int, value: float | int) -> MAVLinkMessage:
        p = PARAMS[index]
        if p.kind == INT:
            wire, ptype = _INT_AS_FLOAT.unpack(_INT_BYTES.pack(int(value)))[0], mav.MAV_PARAM_TYPE_INT32
        else:
            wire, ptype = float(value), mav.MAV_PARAM_TYPE_REAL32
        return self.codec.mav.param_value_encode(p.name.encode(), wire, ptype, len(PARAMS), index)

    def _on_param_request_list(self, msg: MAVLinkMessage, now_s: float) -> None:
        if not self._for_me(msg.target_system, msg.target_component):
            return
        if self.budget is None:
            for index, _, value in self.params.items():
                self._send_param(index, value)
            return
        self._param_list = deque(range(len(PARAMS)))  # at the streams' pace (`_send_param_list`)
        self._send_param_list()

    def _send_param_list(self) -> None:
        """The parameter list's next PARAM_VALUEs, as many as the line takes now without queueing
        answers behind them; the rest in later passes."""
        budget, pending = self.budget, self._param_list
        n_bytes = self._frame_bytes(mav.MAVLINK_MSG_ID_PARAM_VALUE)
        while pending and (budget is None or budget.has_room(n_bytes)):
            index = pending.popleft()
            self.codec.send(self._param_value(index, self.params.get(PARAMS[index].name)))
            self.stats.params_sent += 1

    def _on_param_request_read(self, msg: MAVLinkMessage, now_s: float) -> None:
        if not self._for_me(msg.target_system, msg.target_component):
            return
        name = _param_name(msg.param_id)
        index = msg.param_index if msg.param_index >= 0 else BY_NAME.get(name, -1)
        if not 0 <= index < len(PARAMS):
            what = name if msg.param_index < 0 else f"index {msg.param_index}"
            self._param_refused(msg, name, index, mav.MAV_PARAM_ERROR_DOES_NOT_EXIST,
                                f"unknown parameter {what}", now_s)
            return
        self._send_param(index, self.params.get(PARAMS[index].name))

    def _on_param_set(self, msg: MAVLinkMessage, now_s: float) -> None:
        """Set a parameter; the answer is always the PARAM_VALUE in force (the old one when refused),
        with a PARAM_ERROR and a STATUSTEXT saying why it was refused."""
        if not self._for_me(msg.target_system, msg.target_component):
            return
        name = _param_name(msg.param_id)
        index = BY_NAME.get(name)
        if index is None:
            self._param_refused(msg, name, -1, mav.MAV_PARAM_ERROR_DOES_NOT_EXIST,
                                f"unknown parameter {name}", now_s)
            return
        try:
            self.params.set(name, _param_set_value(PARAMS[index], msg.param_type, msg.param_value))
            # (broadcasts the new value, with the parameter's own type)
        except ParamError as exc:
            error = mav.MAV_PARAM_ERROR_PERMISSION_DENIED if exc.kind == "invalid" else \
                mav.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE  # (a wrong type: a value it cannot take)
            self._param_refused(msg, name, index, error, exc.reason, now_s)
            self._send_param(index, self.params.get(name))
            return
        self.stats.params_set += 1

    def _param_refused(self, msg: MAVLinkMessage, name: str, index: int, error: int, reason: str,
                       now_s: float) -> None:
        self.stats.params_refused += 1
        self.send(self.codec.mav.param_error_encode(
            msg.get_srcSystem(), msg.get_srcComponent(), name.encode(), index, error))
        self.statustext(mav.MAV_SEVERITY_WARNING, reason, now_s, key=f"param:{reason}")

    def _param_storage(self, action: float, now_s: float) -> tuple[CommandResult, int, None]:
        """MAV_CMD_PREFLIGHT_STORAGE's parameter action: 0 read the parameter file, 1 write it,
        2 every parameter back to its default."""
        path = self.config.param_file
        try:
            if action == 2:
                self.params.reset()
            elif action not in (0, 1):
                return CommandResult(True), mav.MAV_RESULT_UNSUPPORTED, None
            elif path is None:
                return CommandResult(False, "no parameter file (hil fc --params FILE)"), \
                    mav.MAV_RESULT_DENIED, None
            elif action == 0:
                self.params.set_many(read_param_file(path))
            else:
                self.params.save(path)
        except (OSError, ValueError) as exc:
            return CommandResult(False, f"parameter file: {exc}"[:50]), mav.MAV_RESULT_FAILED, None
        return CommandResult(True), mav.MAV_RESULT_ACCEPTED, None

    # --- what a ground station asks while it connects --------------------------------------------
    def _on_ftp(self, msg: MAVLinkMessage, now_s: float) -> None:
        """MAVLink FTP: NAK every request at once (no file system here), so a client falls back to the
        parameter protocol without waiting for its time-out."""
        if not self._for_me(msg.target_system, msg.target_component) or len(msg.payload) < 12:
            return
        seq, session, opcode = msg.payload[0] | msg.payload[1] << 8, msg.payload[2], msg.payload[3]
        if opcode in (mav.MAV_FTP_OPCODE_ACK, mav.MAV_FTP_OPCODE_NAK):
            return
        if opcode in (mav.MAV_FTP_OPCODE_TERMINATESESSION, mav.MAV_FTP_OPCODE_RESETSESSION,
                      mav.MAV_FTP_OPCODE_READFILE, mav.MAV_FTP_OPCODE_WRITEFILE,
                      mav.MAV_FTP_OPCODE_BURSTREADFILE):
            error = mav.MAV_FTP_ERR_INVALIDSESSION
        else:
            error = mav.MAV_FTP_ERR_FILENOTFOUND
        reply = bytearray(251)
        reply[0:2] = ((seq + 1) & 0xFFFF).to_bytes(2, "little")
        reply[2], reply[3], reply[4], reply[5], reply[12] = session, mav.MAV_FTP_OPCODE_NAK, 1, opcode, error
        self.send(self.codec.mav.file_transfer_protocol_encode(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(reply)))
        self.stats.ftp_nak += 1

    def _on_mission_request_list(self, msg: MAVLinkMessage, now_s: float) -> None:
        """No mission on board: MISSION_COUNT 0 of the type asked for, so a connection completes."""
        if not self._for_me(msg.target_system, msg.target_component):
            return
        self.send(self.codec.mav.mission_count_encode(
            msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type))

    @property
    def state(self) -> FcState:
        return self.fc.state


def _mav_result(res: CommandResult) -> int:
    return mav.MAV_RESULT_ACCEPTED if res.accepted else mav.MAV_RESULT_DENIED


_ATTITUDE_IGNORE = mav.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE
_THROTTLE_IGNORE = mav.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
_YAW_RATE_IGNORE = mav.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE
_euler_from_quat = njit(cache=True)(euler_from_quat)  # (the link's own, compiled for `attitude_fields`)

#: what `attitude_fields` says of a SET_ATTITUDE_TARGET: taken, or why not (`attitude_rejection`)
(ATTITUDE_TAKEN, ATTITUDE_IGNORED, THROTTLE_IGNORED, QUATERNION_NON_FINITE, THRUST_OUTSIDE_0_1, NORM_OFF,
 YAW_RATE_NON_FINITE) = range(7)


@njit(cache=True)
def attitude_fields(type_mask: int, q0: float, q1: float, q2: float, q3: float, thrust: float,
                    body_yaw_rate: float) -> tuple[int, int, float, float, float, float, float]:
    """The N3Setpoint fields of a SET_ATTITUDE_TARGET with these fields (quaternion NED -> FRD, thrust
    0..1, yaw rate rad/s, read only without the mask's yaw-rate bit): (verdict, flag, roll, pitch (deg),
    thrust (%), yaw (deg or deg/s), the quaternion's norm); a verdict other than `ATTITUDE_TAKEN` says
    why it is refused (`attitude_rejection`), the fields then 0."""
    if type_mask & _ATTITUDE_IGNORE:
        return ATTITUDE_IGNORED, 0, 0.0, 0.0, 0.0, 0.0, 0.0
    if type_mask & _THROTTLE_IGNORE:
        return THROTTLE_IGNORED, 0, 0.0, 0.0, 0.0, 0.0, 0.0
    if not (math.isfinite(q0) and math.isfinite(q1) and math.isfinite(q2) and math.isfinite(q3)):
        return QUATERNION_NON_FINITE, 0, 0.0, 0.0, 0.0, 0.0, 0.0
    if not math.isfinite(thrust) or not 0.0 <= thrust <= 1.0:
        return THRUST_OUTSIDE_0_1, 0, 0.0, 0.0, 0.0, 0.0, 0.0
    norm = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)  # (summed in order)
    if abs(norm - 1.0) > 0.1:
        return NORM_OFF, 0, 0.0, 0.0, 0.0, 0.0, norm
    roll, pitch, yaw = _euler_from_quat((q0 / norm, q1 / norm, q2 / norm, q3 / norm))
    if type_mask & _YAW_RATE_IGNORE:
        return (ATTITUDE_TAKEN, ATTITUDE_THRUST_YAW_ANGLE, math.degrees(roll), math.degrees(pitch),
                100.0 * thrust, math.degrees(yaw), norm)
    if not math.isfinite(body_yaw_rate):
        return YAW_RATE_NON_FINITE, 0, 0.0, 0.0, 0.0, 0.0, norm
    return (ATTITUDE_TAKEN, ATTITUDE_THRUST_YAW_RATE, math.degrees(roll), math.degrees(pitch),
            100.0 * thrust, math.degrees(body_yaw_rate), norm)


@njit(cache=True)
def attitude_target(type_mask: int, q0: float, q1: float, q2: float, q3: float, thrust: float,
                    body_yaw_rate: float, max_tilt_deg: float, max_yaw_rate_deg_s: float
                    ) -> tuple[int, int, float, float, float, float, float, int, float, float, float, float]:
    """`attitude_fields` of a SET_ATTITUDE_TARGET's fields and, when taken, the N3's
    `attitude_thrust_values` of its setpoint (the profile's limits), in one call: `attitude_fields`'s
    seven, then the N3's verdict, roll, pitch (rad), heading (rad), yaw rate (rad/s)."""
    verdict, flag, roll, pitch, thrust_percent, yaw, norm = attitude_fields(
        type_mask, q0, q1, q2, q3, thrust, body_yaw_rate)
    if verdict != ATTITUDE_TAKEN:
        return verdict, flag, roll, pitch, thrust_percent, yaw, norm, ACCEPTED_FIELDS, 0.0, 0.0, 0.0, 0.0
    fc_verdict, roll_rad, pitch_rad, heading, rate = attitude_thrust_values(
        flag, roll, pitch, thrust_percent, yaw, max_tilt_deg, max_yaw_rate_deg_s)
    return (verdict, flag, roll, pitch, thrust_percent, yaw, norm, fc_verdict, roll_rad, pitch_rad, heading,
            rate)


def setpoint_kernel() -> Callable[..., tuple]:
    """`attitude_target` compiled (or loaded from the cache) for a frame's int and floats as its struct
    unpacks them, called without numba's type dispatch: each server binds it at construction, and
    `emulator.assembly.warm_up` calls this before a wall clock starts (the protocol's registered warm-up)."""
    return entry(attitude_target, 0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0)


def attitude_rejection(verdict: int, thrust: float, norm: float) -> str:
    """The reason a SET_ATTITUDE_TARGET is refused (`attitude_fields`'s ``verdict``, its ``thrust``
    and its quaternion's ``norm``)."""
    return _ATTITUDE_REASONS[verdict].format(thrust=thrust, norm=norm)


_ATTITUDE_REASONS = {
    ATTITUDE_IGNORED: "attitude ignored: N3 flies roll/pitch angles",
    THROTTLE_IGNORED: "thrust ignored: N3 needs vertical thrust",
    QUATERNION_NON_FINITE: "non-finite attitude quaternion",
    THRUST_OUTSIDE_0_1: "thrust {thrust:.3g} outside 0..1",
    NORM_OFF: "quaternion norm {norm:.3g}, expected 1",
    YAW_RATE_NON_FINITE: "non-finite yaw rate",
}


def attitude_target_values(
    type_mask: int, q: Any, thrust: Any, body_yaw_rate: Any
) -> tuple[int, float, float, float, float]:
    """The N3Setpoint fields (flag, roll, pitch (deg), thrust (%), yaw (deg or deg/s)) of a
    SET_ATTITUDE_TARGET with these fields (quaternion NED -> FRD, four numbers; thrust 0..1; yaw rate
    rad/s): `attitude_fields` of them as floats; raises SetpointRejected with the reason."""
    q0, q1, q2, q3 = _four_floats(q)
    thrust = float(thrust)
    rate = 0.0 if type_mask & _YAW_RATE_IGNORE else float(body_yaw_rate)
    verdict, *values, norm = attitude_fields(index(type_mask), q0, q1, q2, q3, thrust, rate)
    if verdict != ATTITUDE_TAKEN:
        raise SetpointRejected(attitude_rejection(verdict, thrust, norm))
    return tuple(values)  # type: ignore[return-value]


def _four_floats(q: Any) -> tuple[float, float, float, float]:
    """An attitude quaternion's four numbers as floats; SetpointRejected when it has another count."""
    qs = tuple(map(float, q))
    if len(qs) != 4:
        raise SetpointRejected(f"attitude quaternion of {len(qs)} numbers, expected 4")
    return qs  # type: ignore[return-value]


_INT_BYTES, _INT_AS_FLOAT = struct.Struct("<i"), struct.Struct("<f")  # PX4's bytewise int32 encoding


def _param_set_value(p: ParamDef, param_type: int, wire: float) -> float | int:
    """The value a PARAM_SET carries for ``p``: REAL32 as it is; INT32 bytewise (PX4's encoding), or
    as a REAL32 holding a whole number (MAVProxy's `param load` sends integers so); ParamError else."""
    if p.kind != INT:
        if param_type != mav.MAV_PARAM_TYPE_REAL32:
            raise ParamError(f"{p.name} is REAL32", "type")
        return wire
    if param_type == mav.MAV_PARAM_TYPE_INT32:
        return _INT_BYTES.unpack(_INT_AS_FLOAT.pack(wire))[0]
    if param_type == mav.MAV_PARAM_TYPE_REAL32 and math.isfinite(wire) and wire == int(wire):
        return int(wire)
    raise ParamError(f"{p.name} is INT32", "type")


def _param_name(param_id: str | bytes) -> str:
    """A PARAM_* message's name field as text (pymavlink gives str or bytes, NUL-padded)."""
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return param_id.split("\x00", 1)[0]

