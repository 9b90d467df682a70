"""The onboard computer's DJI OPEN-protocol client of the FC (Onboard SDK 3.x, as on the paper's TX2 and
N3): activation, the N3's telemetry by subscription (the broadcast turned off), control authority,
arming, the attitude-thrust setpoint, and the harness's lockstep ticks (`hil.link.lockstep`'s, on command
set 0xFE).

It is a `CommandLink` to the onboard program: the same requests (`request_offboard` obtains control
authority, `request_hold` releases it, `request_arm` arms), their answers in ``acks`` under the same
request keys (the MAVLink command ids the program waits on), and the FC's state in ``status`` (from the
subscribed topics: armed is the flight status past "stopped", offboard is the onboard device holding
control).
The lockstep's reading (actions up to the next tick, outputs held until the tick is answered) is
`CommandLink`'s. Commands go on reliable sessions (resent with the same SESSION and SEQ until their ACK);
setpoints and the tick answers on session 0. World ENU / body FLU inside; NED Euler angles in degrees
on the wire (`hil.link.dji_open`, docs/dji-open-link.md).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from hil.link import dji_open as dj
from hil.link.clock import Clock
from hil.link.lockstep import dji_answer_payload, dji_read_tick
from hil.link.mavlink import euler_from_quat, mav, quat_ned_frd_from_euler
from hil.link.transport import Transport
from policies.compiling import Kernel
from policies.onboard.command_link import (
    CLIPPED_THRUST,
    NED_FRD_QUAT,
    CommandAck,
    CommandLink,
    clipped_thrust,
)

#: the Onboard SDK app's activation: app id, reserved, the FC's version (as OSDK sends it), the bundle id
APP_ID = 1069806
APP_BUNDLE = b"12345678901234567890123456789012"
#: the broadcast off: the program reads its telemetry by subscription
BROADCAST_RATES = bytes(16)
#: the subscription the program reads: package 0, flight status, display mode, control device and
#: battery at 50 Hz
PACKAGE_ID = 0
PACKAGE_HZ = 50
PACKAGE_TOPICS = ("status_flight", "status_displaymode", "control_device", "battery_info")
ACTIVATION_RETRY_S = 0.5  # a refused or unanswered activation is asked again this often (s)
_OBTAIN, _RELEASE = b"\x01", b"\x00"
_PACKAGE_UIDS = tuple(dj.TOPIC_UID[name] for name in PACKAGE_TOPICS)
_PACKAGE = dj.SUB_PACKAGE_HEAD.pack(PACKAGE_ID, PACKAGE_HZ, 0, len(_PACKAGE_UIDS)) + struct.pack(
    f"<{len(_PACKAGE_UIDS)}I", *_PACKAGE_UIDS)
_PACKAGE_BYTES = 1 + sum(dj.TOPIC_STRUCTS[u].size for u in _PACKAGE_UIDS)
_CONTROL = (dj.SET_CONTROL, dj.CMD_CONTROL_AUTHORITY)
_ARM = (dj.SET_CONTROL, dj.CMD_ARM)
_ACTIVATE = (dj.SET_ACTIVATION, dj.CMD_ACTIVATE)
_RATES = (dj.SET_ACTIVATION, dj.CMD_BROADCAST_FREQ)
_SUB_VERSION = (dj.SET_SUBSCRIBE, dj.CMD_SUB_VERSION)
_SUB_ADD = (dj.SET_SUBSCRIBE, dj.CMD_SUB_ADD)
#: the FC's commands the program acts on, as their first two data bytes (command set, command id)
_TICK = bytes((dj.SET_HIL, dj.CMD_HIL_TICK))
_PACKAGE_DATA = bytes((dj.SET_BROADCAST, dj.CMD_SUBSCRIPTION_DATA))
_CONTROL_LOST = bytes((dj.SET_BROADCAST, dj.CMD_CONTROL_LOST))
#: the setup after activation, in order: each step's command and payload
_SETUP = ((_RATES, BROADCAST_RATES), (_SUB_VERSION, struct.pack("<I", dj.SUB_DB_VERSION)),
          (_SUB_ADD, _PACKAGE))


def ned_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float]:
    """The N3's roll, pitch and heading (rad; NED, Z-Y-X) of ZYX Euler angles of body FLU -> world ENU
    (rad): `euler_from_quat` of `quat_ned_frd_from_euler`. Compiled by numba (`NED_EULER`), which is how
    the setpoint runs it."""
    return euler_from_quat(quat_ned_frd_from_euler(roll_rad, pitch_rad, yaw_rad))


#: the setpoint's angles on the wire, compiled: `ned_euler`
NED_EULER = Kernel(ned_euler, quat_ned_frd_from_euler=NED_FRD_QUAT,
                   euler_from_quat=Kernel(euler_from_quat))


def setpoint_angles(roll_rad: float, pitch_rad: float, yaw_rad: float, thrust_fraction: float
                    ) -> tuple[float, float, float, float]:
    """A setpoint's numbers as the OPEN setpoint (0x01 0x03) carries them: the N3's roll, pitch (deg;
    `ned_euler` of ZYX Euler angles of body FLU -> world ENU, rad), the thrust fraction as 0..100 %
    (`clipped_thrust`; a finite one) and the heading (deg). Compiled (`SETPOINT_ANGLES`): one call a
    setpoint."""
    roll, pitch, yaw = ned_euler(roll_rad, pitch_rad, yaw_rad)
    return math.degrees(roll), math.degrees(pitch), 100.0 * clipped_thrust(thrust_fraction), math.degrees(yaw)


#: the setpoint's numbers on the wire, compiled: `setpoint_angles`
SETPOINT_ANGLES = Kernel(setpoint_angles, ned_euler=NED_EULER, clipped_thrust=CLIPPED_THRUST)


@dataclass(frozen=True)
class DjiStatus:
    """What the FC's flight data last said: flight status, control device byte, when it came (s)."""

    flight_status: int
    device: int
    time_s: float
    display_mode: int = dj.MODE_P_GPS

    @property
    def armed(self) -> bool:
        return self.flight_status != dj.FLIGHT_STOPPED

    @property
    def offboard(self) -> bool:
        """The FC flies (or, motors off, will fly) the onboard device's setpoints: the device holds control
        authority and the FC is in SDK control, not in its own hover after the setpoints stopped."""
        sdk = self.display_mode == dj.MODE_NAVI_SDK_CTRL or self.flight_status == dj.FLIGHT_STOPPED
        return self.device & dj.DEVICE_MASK == dj.DEVICE_ONBOARD and sdk

    @property
    def holding(self) -> bool:
        """The FC flies on its own (authority released or taken back)."""
        return not self.offboard


class DjiCommandLink(CommandLink):
    """OPEN-protocol client of the FC on ``transport``, stamped with ``clock`` (s)."""

    protocol = "dji_open"

    def __init__(self, transport: Transport, clock: Clock, target_system: int = 1) -> None:
        codec = dj.OpenCodec(transport, clock, keep_acks=True)
        super().__init__(transport, clock, target_system, codec=codec)
        self.activated = False
        self.activation_code: int | None = None  # the FC's last answer to the activation
        self._setup_done = 0  # steps of `_SETUP` answered with success
        self._next_activation_s = -math.inf
        self._flight_status = dj.FLIGHT_STOPPED
        self._device = dj.DEVICE_RC
        self._display_mode = dj.MODE_P_GPS
        self._last_data_s: float | None = None
        self.control_lost = 0  # times the FC pushed "control lost"
        self._setpoint_angles = SETPOINT_ANGLES.entry(0.0, 0.0, 0.0, 0.0)  # (compiled: no dispatch)

    # --- input --------------------------------------------------------------------------------
    def _poll(self, timeout_s: float) -> list:
        out = super()._poll(timeout_s)
        codec = self.codec
        if codec.waiting:  # reliable commands overdue: again (none waits on most reads: no clock read)
            for frame in codec.service(self.clock.now_s()):
                self._send_frame(frame)
        return out

    def _handle(self, f: dj.Frame) -> None:  # type: ignore[override]
        if f.is_ack:
            now = self.clock.now_s()
            if self.codec.match_ack(f, now) is not None:
                self._take_acks(now)
            return
        data = f.data
        command = data[:2]  # (`Frame.cmd_set` and `cmd_id` as they stand in the data)
        if command == _TICK:
            tick_s, mocap_total = dji_read_tick(data[2:])
            self._on_tick(tick_s, mocap_total)
        elif command == _PACKAGE_DATA:
            self._on_package(data[2:], self.clock.now_s())
        elif command == _CONTROL_LOST:
            self.control_lost += 1
            self._device = dj.DEVICE_RC
            self.status_texts.append("control authority lost")

    def _take_acks(self, now_s: float) -> None:
        """The ACKs the codec has matched: the program's answers under its request keys."""
        acks = self.codec.acks
        if not acks:
            return
        for key, (value, t) in list(acks.items()):
            # (the subscription set answers one byte, the others a u16)
            code = value[0] if key[0] == dj.SET_SUBSCRIBE and value else dj.read_ack_code(value)
            del acks[key]
            step = self._setup_done
            if key == _ACTIVATE:
                self.activation_code = code
                self.activated = code == dj.ACTIVATE_SUCCESS
                if not self.activated:
                    self.status_texts.append(f"activation refused: code {code}")
                elif step < len(_SETUP):
                    self._command(*_SETUP[step])
            elif step < len(_SETUP) and key == _SETUP[step][0]:
                if code != dj.ACK_SUCCESS:
                    self.status_texts.append(f"telemetry setup refused: 0x{key[0]:02X} 0x{key[1]:02X} "
                                             f"code {code}")
                    continue  # asked again by `request_heartbeat`
                self._setup_done = step = step + 1
                if step < len(_SETUP):
                    self._command(*_SETUP[step])
            elif key == _CONTROL:
                ok = code in (dj.CONTROL_OBTAINED, dj.CONTROL_RELEASED)
                if code == dj.CONTROL_NEEDS_F_MODE:
                    self.status_texts.append("control refused: the RC is not in F mode")
                self._ack(mav.MAV_CMD_DO_SET_MODE, ok, t)
            elif key == _ARM:
                ok = code in (dj.ARM_SUCCESS, dj.ARM_ALREADY)
                if not ok:
                    self.status_texts.append(f"arm refused: code {code}")
                self._ack(mav.MAV_CMD_COMPONENT_ARM_DISARM, ok, t)

    def _ack(self, request: int, ok: bool, t_s: float) -> None:
        result = mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_DENIED
        self.acks[request] = CommandAck(request, result, t_s)

    def _on_package(self, payload: bytes, now_s: float) -> None:
        """The subscribed package: flight status, display mode, control device (mode, device), battery."""
        if len(payload) != _PACKAGE_BYTES or payload[0] != PACKAGE_ID:
            return
        self._flight_status, self._display_mode = payload[1], payload[2]
        self._device = payload[4]
        self._last_data_s = now_s
        self.status = DjiStatus(self._flight_status, self._device, now_s,  # type: ignore[assignment]
                                self._display_mode)

    def heartbeat_age_s(self, now_s: float) -> float:
        """Seconds since the FC's last flight data (inf if none yet): the OPEN protocol's sign of life."""
        return math.inf if self._last_data_s is None else now_s - self._last_data_s

    # --- output -------------------------------------------------------------------------------
    def _command(self, key: tuple[int, int], payload: bytes) -> None:
        self._send_frame(self.codec.pack_reliable(*key, payload))

    def send_heartbeat(self) -> None:
        """The OPEN protocol has no heartbeat of the onboard device: nothing to send."""

    def request_heartbeat(self) -> None:
        """Until the telemetry comes: activate (again after a refusal, every `ACTIVATION_RETRY_S`),
        then turn the broadcast off, check the subscription's version and add the package."""
        now = self.clock.now_s()
        if not self.activated:
            if now >= self._next_activation_s:
                self._next_activation_s = now + ACTIVATION_RETRY_S
                version = dj.fc_version_word()
                self._command(_ACTIVATE, struct.pack("<III", APP_ID, 2, version) + APP_BUNDLE)
        elif self._setup_done < len(_SETUP):
            key, payload = _SETUP[self._setup_done]
            if not self.codec.is_waiting(*key):
                self._command(key, payload)

    def request_offboard(self) -> None:
        """Obtain control authority (0x01 0x00, 1)."""
        self.acks.pop(mav.MAV_CMD_DO_SET_MODE, None)
        self._command(_CONTROL, _OBTAIN)

    def request_hold(self) -> None:
        """Release control authority (0x01 0x00, 0): the FC flies on its own."""
        self.acks.pop(mav.MAV_CMD_DO_SET_MODE, None)
        self._command(_CONTROL, _RELEASE)

    def request_arm(self) -> None:
        self.acks.pop(mav.MAV_CMD_COMPONENT_ARM_DISARM, None)
        self._command(_ARM, b"\x01")

    def send_command(self, command: int, *params: float) -> None:
        raise NotImplementedError("MAVLink commands do not go over the OPEN protocol")

    def send_attitude_target(self, roll_rad: float, pitch_rad: float, yaw_rad: float,
                             thrust_fraction: float) -> None:
        """One attitude-thrust setpoint (0x01 0x03): ZYX Euler angles of body FLU -> world ENU (rad) as the
        N3's NED roll, pitch, heading (deg), thrust 0..1 of full thrust as 0..100 % (clipped). ValueError,
        nothing sent, when a value is not finite."""
        thrust = float(thrust_fraction)
        if not math.isfinite(roll_rad + pitch_rad + yaw_rad + thrust):
            raise ValueError(f"setpoint not finite: roll {roll_rad} rad, pitch {pitch_rad} rad, "
                             f"yaw {yaw_rad} rad, thrust {thrust}")
        roll, pitch, percent, yaw = self._setpoint_angles(roll_rad, pitch_rad, yaw_rad, thrust)  # (compiled)
        payload = dj.setpoint_payload(dj.ATTITUDE_THRUST_YAW_ANGLE, roll, pitch, percent, yaw)
        frame = self.codec.pack_command(dj.SET_CONTROL, dj.CMD_SETPOINT, payload)
        if self._open_ticks > 0:  # held for the tick's answer (`_send_frame`, without the call: per tick)
            self._held.append(frame)
        else:
            self._send_frame(frame)
        self.setpoints_sent += 1

    def _answer_frame(self, tick_s: float) -> bytes:
        return self.codec.pack_command(dj.SET_HIL, dj.CMD_HIL_ANSWER, dji_answer_payload(tick_s))
