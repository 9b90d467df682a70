"""MAVLink telemetry of an emulated vehicle: its state encoded as PX4 would send it (NED/FRD on the wire)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from emulator.fc.modes import FcState
from emulator.profile import GRAVITY_M_S2
from emulator.vehicle import EmulatedVehicle
from hil.link.mavlink import (
    PX4_AUTO_LAND,
    PX4_AUTO_LOITER,
    PX4_AUTO_RTL,
    PX4_AUTO_TAKEOFF,
    PX4_MAIN_AUTO,
    PX4_MAIN_OFFBOARD,
    MAVLinkMessage,
    enu_to_ned,
    euler_from_quat,
    flu_to_frd,
    mav,
    px4_custom_mode,
    quat_enu_flu_to_ned_frd_tuple,
)

EARTH_RADIUS_M = 6378137.0
MAG_FIELD_NED_GAUSS = np.array([0.38, -0.02, 0.23])  # a mid-latitude field (gauss)
BATTERY_CELLS = 4
BATTERY_ENDURANCE_S = 900.0  # armed time from full to empty (s)
MIN_INTERVAL_S = 0.002  # fastest stream rate granted by SET_MESSAGE_INTERVAL and the rate parameters (500 Hz)
#: default telemetry intervals (s), by message id
DEFAULT_INTERVALS_S: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 1 / 50,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 1 / 50,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1 / 30,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 1 / 10,
    mav.MAVLINK_MSG_ID_HIGHRES_IMU: 1 / 50,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1 / 5,
}
#: PX4 custom mode shown for each state (HOLD = AUTO.LOITER)
CUSTOM_MODE = {
    FcState.DISARMED: px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_LOITER),
    FcState.HOLD: px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_LOITER),
    FcState.OFFBOARD: px4_custom_mode(PX4_MAIN_OFFBOARD),
    FcState.LAND: px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_LAND),
    FcState.TAKEOFF: px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_TAKEOFF),
    FcState.GO_HOME: px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_RTL),
    FcState.FAILSAFE_HOVER: px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_LOITER),
    FcState.FAILSAFE_LAND: px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_LAND),
}
SENSORS = (
    mav.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mav.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mav.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mav.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mav.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
)


@dataclass(frozen=True)
class Home:
    """Where the world origin lies on Earth (WGS84 degrees, metres above mean sea level)."""

    lat_deg: float = 22.3364  # a campus in Hong Kong
    lon_deg: float = 114.2655
    alt_m: float = 10.0


class TelemetryEncoder:
    """Builds telemetry messages for one vehicle; ``mav_obj`` is the codec's pymavlink object."""

    def __init__(self, vehicle: EmulatedVehicle, mav_obj: mav.MAVLink, home: Home) -> None:
        self.vehicle = vehicle
        self.mav = mav_obj
        self.home = home
        #: the battery model's armed time: each poll counts the time since the poll before it when the
        #: FC's state at that poll is armed. The state changes only with an FC event, so the server says
        #: when events came (`state_changed`) and the time is kept in stretches: the sum of those settled
        #: (s) and the poll the current one counts from (s; None while disarmed), read by `battery`
        self._armed_sum_s = 0.0
        self._armed_from_s: float | None = None
        self._machine = vehicle.fc.machine  # (the FC's state machine)

    def state_changed(self, prev_poll_s: float | None, now_s: float) -> None:
        """The FC's state may have changed since the poll at ``prev_poll_s`` (s; None: the poll at
        ``now_s`` is the first): the armed time's stretch before it settled, or one started there (the
        state now counts from the poll before). Called at the polls that see new FC events."""
        at_s = now_s if prev_poll_s is None else prev_poll_s
        from_s = self._armed_from_s
        if self._machine.state is not _DISARMED:
            if from_s is None:
                self._armed_from_s = at_s
        elif from_s is not None:
            if at_s > from_s:  # (never backwards)
                self._armed_sum_s += at_s - from_s
            self._armed_from_s = None

    # --- the streamed state and status: payloads (fields in wire order, packed by the message's own
    # ``unpacker``, for `MavlinkCodec.pack_payload`), built without message objects
    def state_values(self) -> list[float]:
        """The vehicle's state now as plain floats (`VehicleState.to_vector` layout), read without
        building a VehicleState (none is built between the batched steps of a lockstep run)."""
        return self.vehicle.state_vector().tolist()

    def heartbeat_payload(self) -> bytes:
        """HEARTBEAT now."""
        st = self.vehicle.fc.state
        custom = CUSTOM_MODE[st]
        if st is FcState.DISARMED and self.vehicle.fc.offboard_selected:
            custom = px4_custom_mode(PX4_MAIN_OFFBOARD)
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if st.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        if st is not FcState.DISARMED and st is not FcState.HOLD:
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED | mav.MAV_MODE_FLAG_AUTO_ENABLED
        if st.failsafe:
            status = mav.MAV_STATE_CRITICAL
        else:
            status = mav.MAV_STATE_ACTIVE if st.armed else mav.MAV_STATE_STANDBY
        kind, autopilot = mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4
        return _HEARTBEAT.pack(custom, kind, autopilot, base, status, _MAVLINK_VERSION)  # wire order

    # the per-tick messages work in plain floats (FLU -> FRD and ENU -> NED are sign flips and swaps)
    def attitude_payload(self, now_s: float, x: list[float]) -> bytes:
        """ATTITUDE (FRD, NED) at ``now_s`` (s) of the state values ``x`` (`state_values`)."""
        roll, pitch, yaw = euler_from_quat(quat_enu_flu_to_ned_frd_tuple(*x[6:10]))
        p, q, r = x[10:13]
        return _ATTITUDE.pack(_ms(now_s), roll, pitch, yaw, p, -q, -r)

    def local_position_ned_payload(self, now_s: float, x: list[float]) -> bytes:
        """LOCAL_POSITION_NED at ``now_s`` (s) of the state values ``x`` (`state_values`)."""
        e, n, u, ve, vn, vu = x[0:6]
        return _LOCAL_POSITION_NED.pack(_ms(now_s), n, e, -u, vn, ve, -vu)

    def extended_sys_state_payload(self) -> bytes:
        """EXTENDED_SYS_STATE now."""
        return _EXTENDED_SYS_STATE.pack(mav.MAV_VTOL_STATE_UNDEFINED, self.vehicle.fc.landed_state.value)

    # --- the other messages, as pymavlink messages --------------------------------------------
    def attitude_quaternion(self, now_s: float) -> MAVLinkMessage:
        s = self.vehicle.state
        q = quat_enu_flu_to_ned_frd_tuple(*s.quat_wxyz.tolist())
        p, qr, r = s.omega_rad_s.tolist()
        return self.mav.attitude_quaternion_encode(_ms(now_s), *q, p, -qr, -r, [0.0] * 4)

    def global_position_int(self, now_s: float) -> MAVLinkMessage:
        s = self.vehicle.state
        lat, lon = self.lat_lon_deg(s.pos_m)
        v = enu_to_ned(s.vel_m_s) * 100.0
        _, _, yaw = euler_from_quat(quat_enu_flu_to_ned_frd_tuple(*s.quat_wxyz.tolist()))
        hdg = round(math.degrees(yaw) % 360.0 * 100) % 36000
        return self.mav.global_position_int_encode(
            _ms(now_s),
            round(lat * 1e7),
            round(lon * 1e7),
            round((self.home.alt_m + s.pos_m[2]) * 1000),
            round(s.pos_m[2] * 1000),
            *(_i16(x) for x in v),
            hdg,
        )

    def highres_imu(self, now_s: float) -> MAVLinkMessage:
        s = self.vehicle.state
        rot = s.rotation_matrix()  # body FLU -> world ENU
        specific_enu = np.asarray(s.accel_m_s2) + np.array([0.0, 0.0, GRAVITY_M_S2])
        acc = flu_to_frd(rot.T @ specific_enu)
        gyro = flu_to_frd(s.omega_rad_s)
        mag = flu_to_frd(rot.T @ enu_to_ned(MAG_FIELD_NED_GAUSS))
        alt = self.home.alt_m + s.pos_m[2]
        pressure_hpa = 1013.25 * (1.0 - 2.25577e-5 * alt) ** 5.25588
        return self.mav.highres_imu_encode(
            _us(now_s), *acc, *gyro, *mag, pressure_hpa, 0.0, alt, 25.0, 0x1FFF, 0
        )

    def sys_status(self, now_s: float, errors_comm: int) -> MAVLinkMessage:
        volts, pct = self.battery(now_s)
        return self.mav.sys_status_encode(
            SENSORS,
            SENSORS,
            SENSORS,
            200,
            round(volts * 1000),
            -1,
            pct,
            0,
            min(errors_comm, 65535),
            0,
            0,
            0,
            0,
        )

    def battery_status(self, now_s: float) -> MAVLinkMessage:
        volts, pct = self.battery(now_s)
        cell_mv = round(volts * 1000 / BATTERY_CELLS)
        cells = [cell_mv] * BATTERY_CELLS + [65535] * (10 - BATTERY_CELLS)
        return self.mav.battery_status_encode(
            0, mav.MAV_BATTERY_FUNCTION_ALL, mav.MAV_BATTERY_TYPE_LIPO, 32767, cells, -1, -1, -1, pct
        )

    def home_position(self, now_s: float) -> MAVLinkMessage:
        h = self.home
        return self.mav.home_position_encode(
            round(h.lat_deg * 1e7),
            round(h.lon_deg * 1e7),
            round(h.alt_m * 1000),
            0.0,
            0.0,
            0.0,
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            _us(now_s),
        )

    def autopilot_version(self, system_id: int) -> MAVLinkMessage:
        caps = (
            mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
            | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE  # PX4's integer parameters
        )
        version = (1 << 24) | (14 << 16) | (0 << 8) | 255  # reports itself as PX4 1.14.0 release
        return self.mav.autopilot_version_encode(
            caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x4E33000000000000 | system_id
        )

    # --- helpers ---------------------------------------------------------------------------
    def lat_lon_deg(self, pos_enu_m: np.ndarray) -> tuple[float, float]:
        """Flat-Earth latitude, longitude (deg) of a world ENU position (m)."""
        lat = self.home.lat_deg + math.degrees(pos_enu_m[1] / EARTH_RADIUS_M)
        lon = self.home.lon_deg + math.degrees(pos_enu_m[0] / (EARTH_RADIUS_M * math.cos(math.radians(lat))))
        return lat, lon

    def battery(self, now_s: float) -> tuple[float, int]:
        """(pack voltage (V), charge (%)) of the battery model at the poll at ``now_s`` (s): full less the
        armed time as a share of `BATTERY_ENDURANCE_S`."""
        armed_s, from_s = self._armed_sum_s, self._armed_from_s
        if from_s is not None and now_s > from_s:  # (armed now: the current stretch so far too)
            armed_s += now_s - from_s
        frac = max(0.0, 1.0 - armed_s / BATTERY_ENDURANCE_S)
        volts = BATTERY_CELLS * (3.5 + 0.7 * frac)
        return volts, round(100 * frac)


_DISARMED = FcState.DISARMED
_HEARTBEAT = mav.MAVLink_heartbeat_message.unpacker  # wire order: custom_mode first
_MAVLINK_VERSION = 3  # what ``heartbeat_encode`` puts in
_ATTITUDE = mav.MAVLink_attitude_message.unpacker
_LOCAL_POSITION_NED = mav.MAVLink_local_position_ned_message.unpacker
_EXTENDED_SYS_STATE = mav.MAVLink_extended_sys_state_message.unpacker


def _ms(t_s: float) -> int:
    return int(t_s * 1000.0) & 0xFFFFFFFF


def _us(t_s: float) -> int:
    return max(0, int(t_s * 1e6))


def _i16(x: float) -> int:
    return max(-32768, min(32767, round(x)))
