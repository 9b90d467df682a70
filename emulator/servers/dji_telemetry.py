"""What the emulated N3 reports on the OPEN protocol: its flight status, display mode and control device,
and the values of every broadcast item and subscription topic it serves, each computed once, from the
vehicle's state, for both (layouts: `hil.link.dji_open`, docs/dji-open-link.md).

A value function takes the server (`emulator.servers.dji_open_server.DjiOpenServer`, for the vehicle, FC,
battery model and home point) and the state vector (`VehicleState.to_vector` layout, a list) and returns
the fields of its struct in order. World ENU / body FLU inside; the N3's north-east-down frames (or
north-east-up where DJI says so) on the wire.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Callable
from typing import TYPE_CHECKING

from emulator.fc.modes import DISARMED, FAILSAFE_LAND, GO_HOME, LAND, OFFBOARD, TAKEOFF
from emulator.fc.n3 import MotionTarget
from emulator.profile import GRAVITY_M_S2
from hil.link import dji_open as dj
from hil.link.mavlink import quat_enu_flu_to_ned_frd_tuple

if TYPE_CHECKING:  # (the server imports this module)
    from emulator.servers.dji_open_server import DjiOpenServer

Values = Callable[["DjiOpenServer", list], tuple]

SATELLITES = 12  # the GNSS fix the emulated N3 reports: ideal, flat Earth about the home point
GPS_HEALTH = 5  # 0-5; position control needs 3 or more
BATTERY_CAPACITY_MAH = 4500
HOVER_CURRENT_MA = 15000  # reported while the motors run (the battery model has no current)
_RC_MODE = {"P": dj.RC_MODE_P, "A": dj.RC_MODE_A, "F": dj.RC_MODE_F}
RC_GEAR_DOWN = -4545
#: the API control mode (`control_device`) of each motion mode: (horizontal position, vertical position,
#: yaw rate) -> OSDK's CtlrMode
_MOTION_MODES = {
    (False, False, False): 3, (False, False, True): 4, (True, False, False): 5, (True, False, True): 6,
    (False, True, False): 9, (False, True, True): 10, (True, True, False): 11, (True, True, True): 12,
}


#: the value functions that do not read the state vector (`_state_free`): a push of only these builds none
_STATE_FREE: set[Values] = set()


def _state_free(fn: Values) -> Values:
    """Mark a value function that does not read the state vector (it is given None for it)."""
    _STATE_FREE.add(fn)
    return fn


# --- state -------------------------------------------------------------------------------------
_LANDING = (LAND, FAILSAFE_LAND)  # (the states read per push: `emulator.fc.modes`' module names)


def flight_status(server: DjiOpenServer) -> int:
    """The N3's flight status: motors stopped, on the ground (motors running), in the air."""
    fc = server.fc
    if fc.machine.state is DISARMED:  # (the state machine's own: read per push)
        return dj.FLIGHT_STOPPED
    return dj.FLIGHT_ON_GROUND if fc.landed else dj.FLIGHT_IN_AIR


def display_mode(server: DjiOpenServer) -> int:
    """The N3's display mode (its flight phase): engine start and auto take-off through the take-off
    task, auto landing while landing in the air, SDK control while it flies the onboard setpoints, P-GPS
    otherwise (the emulated N3 has an ideal position fix)."""
    fc = server.fc
    st = fc.machine.state
    if st is TAKEOFF:
        return dj.MODE_ENGINE_START if fc.landed else dj.MODE_AUTO_TAKEOFF
    if st in _LANDING and not fc.landed:
        return dj.MODE_AUTO_LANDING
    if st is OFFBOARD:
        return dj.MODE_NAVI_SDK_CTRL
    if st is GO_HOME:
        return dj.MODE_NAVI_GO_HOME
    return dj.MODE_P_GPS


def control_device(server: DjiOpenServer) -> tuple[int, int]:
    """(API control mode, device byte): the device is the onboard computer while it holds authority,
    else the RC; bit 3 says the onboard device holds authority; the mode is that of the setpoints flown
    (OSDK's CtlrMode; 0 when none)."""
    fc = server.fc
    device = dj.DEVICE_ONBOARD if server.sdk_control else dj.DEVICE_RC
    mode = 0
    tg = fc.target
    if server.sdk_control and tg is not None and fc.machine.state is OFFBOARD:
        rate = tg.yaw_rate_rad_s is not None
        if isinstance(tg, MotionTarget):
            mode = _MOTION_MODES[(tg.horizontal_position, tg.vertical_position, rate)]
        else:
            mode = 14 if rate else 13  # HORIZ_ANG_VERT_THR_YAW_RATE / _YAW_ANG
    return mode, device | (dj.DEVICE_SDK_ON if server.sdk_control else 0)


# --- values ------------------------------------------------------------------------------------
def _time(server: DjiOpenServer, x: list, now_s: float) -> tuple:
    ms = int(now_s * 1000.0)
    return ms & 0xFFFFFFFF, int((now_s * 1000.0 - ms) * 1e6), int(now_s * 400.0) & 0xFFFFFFFF, 0, 0


def quaternion(server: DjiOpenServer, x: list) -> tuple:
    return quat_enu_flu_to_ned_frd_tuple(*x[6:10])


def acceleration_ground(server: DjiOpenServer, x: list) -> tuple:
    acc = server.vehicle.state.accel_m_s2.tolist()  # world ENU (m/s^2), gravity excluded
    return acc[1], acc[0], acc[2]


def acceleration_body(server: DjiOpenServer, x: list) -> tuple:
    """Specific force in body FRD (m/s^2): what an accelerometer reads."""
    n, e, u = acceleration_ground(server, x)
    w, qx, qy, qz = quaternion(server, x)  # body FRD -> NED
    return _rotate((w, -qx, -qy, -qz), (n, e, -(u + GRAVITY_M_S2)))  # NED -> body, gravity's reaction


def _cross(a: tuple, b: tuple) -> tuple:
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


def _rotate(q: tuple, v: tuple) -> tuple:
    """``v`` rotated by the unit quaternion ``q`` (w, x, y, z)."""
    u = q[1:]
    t = tuple(2.0 * c for c in _cross(u, v))
    ut = _cross(u, t)
    return tuple(v[i] + q[0] * t[i] + ut[i] for i in range(3))


def velocity(server: DjiOpenServer, x: list) -> tuple:
    return x[4], x[3], x[5], 1  # north, east, up; health: valid


def angular_rate(server: DjiOpenServer, x: list) -> tuple:
    return x[10], -x[11], -x[12]


def _lat_lon_rad(server: DjiOpenServer, x: list) -> tuple[float, float]:
    lat, lon = server.telemetry.lat_lon_deg(x[0:3])
    return math.radians(lat), math.radians(lon)


def altitude(server: DjiOpenServer, x: list) -> tuple:
    return (server.config.home.alt_m + x[2],)


def height(server: DjiOpenServer, x: list) -> tuple:
    return (x[2] - server.fc.config.ground_z_m,)


@_state_free
def home_altitude(server: DjiOpenServer, x: list) -> tuple:
    return (server.config.home.alt_m + server.fc.config.ground_z_m,)


def gps_fused(server: DjiOpenServer, x: list) -> tuple:
    lat, lon = _lat_lon_rad(server, x)
    return lon, lat, altitude(server, x)[0], SATELLITES


def gps_position(server: DjiOpenServer, x: list) -> tuple:
    lat, lon = server.telemetry.lat_lon_deg(x[0:3])
    return round(lon * 1e7), round(lat * 1e7), round(altitude(server, x)[0] * 1000)


def gps_velocity(server: DjiOpenServer, x: list) -> tuple:
    return x[4] * 100.0, x[3] * 100.0, -x[5] * 100.0  # NED (cm/s)


@_state_free
def gps_details(server: DjiOpenServer, x: list) -> tuple:
    return 0.8, 1.2, 3.0, 0.0, 500.0, 10.0, SATELLITES, 0, SATELLITES, 0


@_state_free
def rc(server: DjiOpenServer, x: list) -> tuple:
    return 0, 0, 0, 0, _RC_MODE[server.config.rc_mode], RC_GEAR_DOWN


@_state_free
def battery(server: DjiOpenServer, x: list) -> tuple:
    volts, pct = server.telemetry.battery(server.now_s)
    current = HOVER_CURRENT_MA if server.fc.machine.state.armed else 0
    return BATTERY_CAPACITY_MAH * pct // 100, round(volts * 1000), current, pct


def position(server: DjiOpenServer, x: list) -> tuple:
    """The broadcast's position block: latitude, longitude (rad), altitude, height (m), GPS health;
    then the obstacle distances (none sensed: 0) and their flags."""
    lat, lon = _lat_lon_rad(server, x)
    return (lat, lon, altitude(server, x)[0], height(server, x)[0], GPS_HEALTH) + (0.0,) * 6 + (0,)


def gps(server: DjiOpenServer, x: list) -> tuple:
    lon, lat, alt_mm = gps_position(server, x)
    return (0, 0, lon, lat, alt_mm, *gps_velocity(server, x), *gps_details(server, x))


def status(server: DjiOpenServer, x: list) -> tuple:
    return flight_status(server), display_mode(server), 0, 0


def _zeros(n: int) -> Values:
    return _state_free(lambda server, x: (0,) * n)


def _one(fn: Callable[[DjiOpenServer], int]) -> Values:
    return _state_free(lambda server, x: (fn(server),))


#: the broadcast items' values in `dj.BROADCAST_ITEMS` order (the time item takes the time too: `_time`)
BROADCAST_VALUES: tuple[Values, ...] = (
    _zeros(5),  # (replaced by `_time`)
    quaternion, acceleration_ground, velocity, angular_rate, position, gps,
    lambda server, x: (0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0),  # rtk: no receiver
    _zeros(3), rc, lambda server, x: (0.0, 0.0, 0.0, 0), status, battery,
    lambda server, x: control_device(server),
)

#: the subscription topics the emulated N3 serves, by name (`dj.TOPICS`); others are refused
TOPIC_VALUES: dict[str, Values] = {
    "quaternion": quaternion,
    "acceleration_ground": acceleration_ground,
    "acceleration_body": acceleration_body,
    "acceleration_raw": acceleration_body,
    "velocity": velocity,
    "angular_rate_fusioned": angular_rate,
    "angular_rate_raw": angular_rate,
    "altitude_fusioned": altitude,
    "altitude_barometer": altitude,
    "height_homepoint": home_altitude,
    "height_fusion": height,
    "gps_fused": gps_fused,
    "gps_date": _zeros(1),
    "gps_time": _zeros(1),
    "gps_position": gps_position,
    "gps_velocity": gps_velocity,
    "gps_details": gps_details,
    "compass": _zeros(3),
    "rc": rc,
    "gimbal_angles": _state_free(lambda server, x: (0.0, 0.0, 0.0)),
    "gimbal_status": _zeros(1),  # no gimbal mounted
    "status_flight": _one(flight_status),
    "status_displaymode": _one(display_mode),
    "status_landinggear": _zeros(1),
    "status_motor_start_error": _zeros(1),
    "battery_info": battery,
    "control_device": _state_free(lambda server, x: control_device(server)),
    "gps_signal_level": _state_free(lambda server, x: (GPS_HEALTH,)),
    "gps_control_level": _state_free(lambda server, x: (GPS_HEALTH,)),
    "home_point_set_status": _state_free(lambda server, x: (int(server.home_en_m is not None),)),
    "home_point_info": _state_free(lambda server, x: _home_rad(server)),
}


def _home_rad(server: DjiOpenServer) -> tuple:
    """Latitude, longitude (rad) of the home point (where the motors last started; before that, the
    flat Earth's origin)."""
    e, n = server.home_en_m or (0.0, 0.0)
    lat, lon = server.telemetry.lat_lon_deg((e, n, 0.0))
    return math.radians(lat), math.radians(lon)


def flight_data(server: DjiOpenServer, now_s: float, flags: int) -> bytes:
    """The flight-data payload (0x02 0x00) of the items in ``flags`` at ``now_s`` (s)."""
    parts = [flags.to_bytes(dj.BROADCAST_FLAG_BYTES, "little")]
    x = server.vehicle.state_vector().tolist()
    structs = dj.BROADCAST_STRUCTS
    for i, fn in enumerate(BROADCAST_VALUES):
        if flags >> i & 1:
            values = _time(server, x, now_s) if i == 0 else fn(server, x)
            parts.append(structs[i].pack(*values))
    return b"".join(parts)


def package_data(server: DjiOpenServer, package_id: int, uids: tuple[int, ...], timestamp: bool,
                 now_s: float) -> bytes:
    """A subscription package's push (0x02 0x05): its id, the time stamp (ms, ns) when asked, its
    topics, packed in one call; the state vector read only for topics that need it."""
    pack, topics, reads_state = _package_form(uids, timestamp)
    x = server.vehicle.state_vector().tolist() if reads_state else None
    fields: list = [package_id]
    if timestamp:
        fields += _time(server, x, now_s)[:2]  # type: ignore[arg-type]
    for values in topics:
        fields += values(server, x)  # type: ignore[arg-type]
    return pack(*fields)


@functools.cache
def _package_form(uids: tuple[int, ...], timestamp: bool
                  ) -> tuple[Callable[..., bytes], tuple[Values, ...], bool]:
    """The ``pack`` of a push of topics ``uids`` (known UIDs; package id, time stamp when asked, the
    topics' structs in order, one little-endian struct), their value functions, and whether any of them
    reads the state vector: made once per package's topics."""
    formats = "".join(dj.TOPIC_STRUCTS[uid].format.lstrip("<") for uid in uids)
    pack = struct.Struct("<B" + ("II" if timestamp else "") + formats).pack
    topics = tuple(TOPIC_VALUES[dj.TOPICS[uid][0]] for uid in uids)
    return pack, topics, any(fn not in _STATE_FREE for fn in topics)
