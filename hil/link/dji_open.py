"""DJI's OPEN protocol (Onboard SDK 3.x, the N3/A3's UART protocol): frames, CRCs, a streaming parser,
sessions, ACKs, and the command sets and ids this project speaks. One module owns the protocol: the
emulator's server (`emulator.servers.dji_open_server`) and the onboard client (`policies.onboard`) both
frame and read through it. Layout and codes: docs/dji-open-link.md.

A frame: a 12-byte header (SOF 0xAA; LEN, 10 bits: the whole frame's length; VER, 6 bits, 0; SESSION,
5 bits; ACK flag; 2 reserved bits; PADDING, 5 bits; ENC, 3 bits; 3 reserved bytes; SEQ, u16; CRC16 over
bytes 0-9), the data (a command: command set, command id, payload; an ACK: the ACK value), and a CRC32
over everything before it. Both CRCs are DJI's: reflected (CRC-16/ARC's polynomial 0x8005, CRC-32's
0x04C11DB7), started from 0x3AA3, no final XOR; all fields little endian.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

from fastcrc import crc16 as _fastcrc16

from hil.link.clock import Clock
from hil.link.mavlink import FrameSplitter as _Splitter
from hil.link.transport import Transport

SOF = 0xAA
HEADER_BYTES = 12
CRC32_BYTES = 4
MIN_FRAME_BYTES = HEADER_BYTES + CRC32_BYTES  # a frame with no data
COMMAND_FRAME_BYTES = MIN_FRAME_BYTES + 2  # a command frame with no payload (command set and id)
MAX_FRAME_BYTES = 1023  # LEN is 10 bits (12 header + 1007 data + 4 CRC32)
MAX_DATA_BYTES = MAX_FRAME_BYTES - MIN_FRAME_BYTES
CRC_INIT = 0x3AA3
#: CRC-16/ARC (reflected 0x8005, no final XOR) of ``data`` continued from ``crc``: fastcrc's
_ARC = _fastcrc16.arc


def crc16(data: bytes) -> int:
    """DJI's CRC16 of ``data`` (reflected 0x8005, init 0x3AA3, no final XOR): CRC-16/ARC from 0x3AA3."""
    return _ARC(data, CRC_INIT)


#: zlib's CRC-32 is the same reflected polynomial, its register complemented on the way in and out: DJI's
#: CRC32 is zlib's started from the complement of 0x3AA3, its result complemented back (`crc32`)
_ZLIB_CRC32 = binascii.crc32
_CRC32_SEED = CRC_INIT ^ 0xFFFFFFFF
#: zlib's CRC-32 (from `_CRC32_SEED`) of a frame whose own CRC32 closes it: DJI's CRC32 of it is 0
_CRC32_CLOSED = 0xFFFFFFFF


def crc32(data: bytes) -> int:
    """DJI's CRC32 of ``data`` (reflected 0x04C11DB7, init 0x3AA3, no final XOR)."""
    return _ZLIB_CRC32(data, _CRC32_SEED) ^ 0xFFFFFFFF

# sessions: 0 no ACK; 1 ACK wanted, loss tolerated; 2-31 reliable (a retry resends SESSION and SEQ)
SESSION_NO_ACK = 0
SESSION_ACK_ONCE = 1
RELIABLE_SESSIONS = range(2, 32)
ENC_NONE, ENC_AES = 0, 1

# --- command sets and ids (Onboard SDK 3.x, as an N3 answers them) --------------------------------
SET_ACTIVATION = 0x00
CMD_VERSION = 0x00  # payload: one arbitrary byte; ACK: `version_value`
CMD_ACTIVATE = 0x01  # payload: u32 app id, u32 reserved, u32 FC version, 32-byte bundle id; ACK u16
CMD_BROADCAST_FREQ = 0x10  # payload: 16 bytes, one rate code per broadcast item; ACK u16
SET_CONTROL = 0x01
CMD_CONTROL_AUTHORITY = 0x00  # payload: 1 obtain, 0 release; ACK u16
CMD_TASK = 0x01  # payload: one task code; ACK u16
CMD_SETPOINT = 0x03  # payload: control flag + 4 float32 (17 bytes), or the advanced form (26); no ACK
CMD_ARM = 0x05  # payload: 1 arm, 0 disarm; ACK u16 (the M100's; an N3 client starts motors by task)
SET_BROADCAST = 0x02
CMD_FLIGHT_DATA = 0x00  # the pushed flight data (`BROADCAST_ITEMS`)
CMD_CONTROL_LOST = 0x01  # pushed when the onboard device loses control authority; payload 0x04
CMD_SUBSCRIPTION_DATA = 0x05  # a subscribed package: u8 package id, then its topics' values
SET_SUBSCRIBE = 0x0B  # telemetry by subscription (N3 FC firmware 3.2.36 on); ACKs: one `SUB_*` byte
CMD_SUB_VERSION = 0x00  # payload: u32 topic database version (`SUB_DB_VERSION`)
CMD_SUB_ADD = 0x01  # payload: `SUB_PACKAGE_HEAD` (package id, u16 Hz, config, topic count), u32 UIDs
CMD_SUB_RESET = 0x02  # payload: one byte; removes every package
CMD_SUB_REMOVE = 0x03  # payload: u8 package id
CMD_SUB_FREQ = 0x04  # (not answered: 0xFF02)
CMD_SUB_PAUSE = 0x05  # (not answered: 0xFF02)
CMD_SUB_CONFIG = 0x06  # (not answered: 0xFF02)
#: the harness's lockstep ticks (`hil.link.lockstep`): a command set DJI does not use, so an Onboard SDK
#: program never sees one (its protocol layer drops frames of sets it does not know)
SET_HIL = 0xFE
CMD_HIL_TICK = 0x00  # the tick request and the mocap byte total (layout: `hil.link.lockstep`)
CMD_HIL_ANSWER = 0x01  # the answer

# the setpoint's control flag byte: horizontal (bits 7:6) | vertical (5:4) | yaw (3) | frame (2:1) |
# stable (0)
HORIZONTAL_ANGLE = 0x00
HORIZONTAL_VELOCITY = 0x40
HORIZONTAL_POSITION = 0x80
HORIZONTAL_ANGULAR_RATE = 0xC0
VERTICAL_VELOCITY = 0x00
VERTICAL_POSITION = 0x10
VERTICAL_THRUST = 0x20
YAW_ANGLE = 0x00
YAW_RATE = 0x08
FRAME_GROUND = 0x00
FRAME_BODY = 0x02
STABLE_DISABLE = 0x00
STABLE_ENABLE = 0x01
#: the flags of the paper's flights: roll/pitch angle, thrust %, yaw angle (or rate), ground frame
ATTITUDE_THRUST_YAW_ANGLE = HORIZONTAL_ANGLE | VERTICAL_THRUST | YAW_ANGLE | FRAME_GROUND
ATTITUDE_THRUST_YAW_RATE = HORIZONTAL_ANGLE | VERTICAL_THRUST | YAW_RATE | FRAME_GROUND
#: OSDK's positionAndYawCtrl: position offset (m, ground frame), height (m), yaw angle, stable
POSITION_YAW_ANGLE = HORIZONTAL_POSITION | VERTICAL_POSITION | YAW_ANGLE | FRAME_GROUND | STABLE_ENABLE
#: OSDK's velocityAndYawRateCtrl (and, in the advanced form with zeros, its emergency brake)
VELOCITY_YAW_RATE = HORIZONTAL_VELOCITY | VERTICAL_VELOCITY | YAW_RATE | FRAME_GROUND

# ACK codes (u16)
ACK_SUCCESS = 0x0000
# activation (0x00 0x01)
ACTIVATE_SUCCESS = 0x0000
ACTIVATE_BAD_PARAMETERS = 0x0001
ACTIVATE_ENCRYPTION_ERROR = 0x0002
ACTIVATE_NEW_APP = 0x0003
ACTIVATE_SERVER_REFUSED = 0x0006
ACTIVATE_ACCESS_LEVEL = 0x0007
ACTIVATE_SDK_VERSION = 0x0008
# control authority (0x01 0x00)
CONTROL_NEEDS_F_MODE = 0x0000
CONTROL_RELEASED = 0x0001
CONTROL_OBTAINED = 0x0002
CONTROL_OBTAIN_FAILED = 0x0003
CONTROL_RELEASE_FAILED = 0x0004
# arm/disarm (0x01 0x05)
ARM_SUCCESS = 0x0000
ARM_NEEDS_CONTROL = 0x0001
ARM_ALREADY = 0x0002
ARM_CANNOT = 0x0003
# flight tasks (0x01 0x01), the N3/A3's codes, and their ACKs (OSDK 3.9 counts only 0x0000 a success)
TASK_TAKEOFF = 1
TASK_LAND = 2
TASK_GO_HOME = 6
TASK_START_MOTORS = 7
TASK_STOP_MOTORS = 8
TASK_SUCCESS = 0x0000
TASK_MOTOR_ON = 0x0001  # the motors already run
TASK_MOTOR_OFF = 0x0002  # the motors do not run
TASK_IN_AIR = 0x0003
TASK_NOT_IN_AIR = 0x0004
TASK_NO_HOME_POINT = 0x0005
TASK_ALREADY_RUNNING = 0x0008
TASK_INVALID_COMMAND = 0x000A
# common codes (any command)
ACK_KEY_ERROR = 0xFF00  # an encrypted frame the FC cannot read
ACK_NO_AUTHORISATION = 0xFF01  # not activated
ACK_NO_RIGHTS = 0xFF02  # a command set or id this FC does not answer
ACK_NO_RESPONSE = 0xFFFF
# subscription (0x0B) ACKs: one byte
SUB_SUCCESS = 0x00
SUB_ILLEGAL_DATA_LENGTH = 0x01
SUB_VERSION_MISMATCH = 0x02
SUB_PACKAGE_OUT_OF_RANGE = 0x03
SUB_PACKAGE_EXISTS = 0x04
SUB_PACKAGE_MISSING = 0x05
SUB_ILLEGAL_FREQUENCY = 0x06
SUB_PACKAGE_TOO_LARGE = 0x07
SUB_PACKAGE_EMPTY = 0x20
SUB_BAD_TOPIC_COUNT = 0x21
SUB_ILLEGAL_UID = 0x22
SUB_MULTIPLE_SUBSCRIBE = 0x24
SUB_SOURCE_OFFLINE = 0x25
SUB_DB_VERSION = 0x00000100  # the topic database version OSDK 3.9 checks
SUB_MAX_PACKAGES = 5
SUB_MAX_PACKAGE_BYTES = 242  # a package's topic data (DJI's subscription rules)
SUB_FREQUENCIES_HZ = (1, 5, 10, 20, 50, 100, 200, 400)
SUB_PACKAGE_HEAD = struct.Struct("<BHBB")  # package id, frequency (Hz), config (bit 0: timestamp), topics
SUB_TIMESTAMP_BYTES = 8  # with config bit 0: u32 ms, u32 ns within the ms, before the topics

#: subscription topics by UID: (name, struct layout, largest frequency (Hz)), as OSDK 3.9's topic table
TOPICS: dict[int, tuple[str, str, int]] = {
    0xA493281F: ("quaternion", "<4f", 200),  # w, x, y, z: body FRD -> ground NED
    0x8696C85B: ("acceleration_ground", "<3f", 200),  # north, east, up (m/s^2)
    0xBB17D5FE: ("acceleration_body", "<3f", 200),  # body FRD (m/s^2)
    0xC3503A6E: ("acceleration_raw", "<3f", 400),
    0x18FB271D: ("velocity", "<3fB", 200),  # north, east, up (m/s), health (bit 0)
    0x3599C4BE: ("angular_rate_fusioned", "<3f", 200),  # body FRD (rad/s)
    0x700389EE: ("angular_rate_raw", "<3f", 400),
    0x11E9C81A: ("altitude_fusioned", "<f", 200),  # m above sea level
    0x27396A39: ("altitude_barometer", "<f", 200),
    0x252C164B: ("height_homepoint", "<f", 1),  # the home point's altitude (m)
    0x87CF419D: ("height_fusion", "<f", 100),  # m above the ground
    0x4B19A8C7: ("gps_fused", "<ddfH", 50),  # longitude, latitude (rad), altitude (m), satellites
    0x598F79BC: ("gps_date", "<I", 5),
    0xD48912C9: ("gps_time", "<I", 5),
    0x0C949E94: ("gps_position", "<3i", 5),
    0x7AC7EB80: ("gps_velocity", "<3f", 5),
    0x81FED54E: ("gps_details", "<6f2I2H", 5),
    0x1DF9A6B6: ("rtk_position", "<ddf", 5),
    0x763D13C3: ("rtk_velocity", "<3f", 5),
    0xF45D73FD: ("rtk_yaw", "<h", 5),
    0xDA4A57B5: ("rtk_position_info", "<B", 5),
    0xCB72B9E3: ("rtk_yaw_info", "<B", 5),
    0xDF3D72B7: ("compass", "<3h", 100),
    0x739F7FE4: ("rc", "<6h", 50),  # roll, pitch, yaw, throttle, mode, gear
    0x01F71678: ("gimbal_angles", "<3f", 50),
    0x8B6CD45C: ("gimbal_status", "<I", 50),  # bit 0: mounted
    0x20CFB02A: ("status_flight", "<B", 50),  # `FLIGHT_*`
    0x1A67D6A1: ("status_displaymode", "<B", 50),  # `MODE_*`
    0x772D6E22: ("status_landinggear", "<B", 50),
    0x3A41E909: ("status_motor_start_error", "<H", 50),
    0x69779DD9: ("battery_info", "<IiiB", 50),  # capacity (mAh), voltage (mV), current (mA), percent
    0x667BA86A: ("control_device", "<BB", 50),  # control mode, device (bits 0-2) | SDK on (bit 3)
    0xA6A0395F: ("gps_signal_level", "<B", 50),
    0xE30B17B0: ("gps_control_level", "<B", 50),
    0xB5C2211F: ("home_point_set_status", "<B", 50),
    0xBFE4B520: ("home_point_info", "<dd", 50),  # latitude, longitude (rad)
}
TOPIC_UID = {name: uid for uid, (name, _, _) in TOPICS.items()}
TOPIC_STRUCTS = {uid: struct.Struct(layout) for uid, (_, layout, _) in TOPICS.items()}
#: topics an N3 without an RTK receiver refuses with `SUB_SOURCE_OFFLINE`
RTK_TOPICS = frozenset(uid for uid, (name, _, _) in TOPICS.items() if name.startswith("rtk_"))

#: broadcast rate codes (0x00 0x10) -> Hz; 5 keeps the item's rate (6, 7: OSDK's 200 and 400 Hz)
BROADCAST_RATES_HZ: dict[int, float] = {0: 0.0, 1: 1.0, 2: 10.0, 3: 50.0, 4: 100.0, 6: 200.0, 7: 400.0}
BROADCAST_KEEP = 5
#: the N3's broadcast items (0x02 0x00) in flag-bit order: (name, struct layout after the flag word)
BROADCAST_ITEMS: tuple[tuple[str, str], ...] = (
    ("time", "<IIIHB"),  # ms, ns within the ms; sync: 2.5 ms ticks, tag, flag
    ("quaternion", "<4f"),  # q0..q3 (w, x, y, z): body FRD -> ground NED
    ("acceleration", "<3f"),  # ground frame north, east, up (m/s^2)
    ("velocity", "<3fB"),  # ground frame north, east, up (m/s), health (bit 0: valid)
    ("angular_rate", "<3f"),  # body FRD (rad/s)
    ("position", "<ddffB6fB"),  # lat, lon (rad), altitude, height (m), GPS health 0-5; obstacles (m), flags
    ("gps", "<2I3i3f6f2I2H"),  # date, time, lon, lat (1e-7 deg), HFSL (mm), NED (cm/s), details
    ("rtk", "<2Iddf3fhBB"),  # date, time, lon, lat (deg), HFSL, NED velocity, yaw, health flags
    ("magnetometer", "<3h"),
    ("rc", "<6h"),  # roll, pitch, yaw, throttle, mode, gear (-10000..10000; mode P -8000, A 0, F 8000)
    ("gimbal", "<3fB"),
    ("status", "<4B"),  # flight status (`FLIGHT_*`), display mode (`MODE_*`), landing gear, error
    ("battery", "<IiiB"),  # capacity (mAh), voltage (mV), current (mA), percent
    ("control_device", "<BB"),  # API control mode, device (bits 0-2: 0 RC, 1 app, 2 onboard) | flags
)
BROADCAST_STRUCTS = tuple(struct.Struct(layout) for _, layout in BROADCAST_ITEMS)
BROADCAST_FLAG_BYTES = 2  # the u16 flag word before the items
BROADCAST_BIT = {name: i for i, (name, _) in enumerate(BROADCAST_ITEMS)}
RC_MODE_P, RC_MODE_A, RC_MODE_F = -8000, 0, 8000
#: flight status (broadcast and subscription), the N3's: motors stopped, on the ground, in the air
FLIGHT_STOPPED, FLIGHT_ON_GROUND, FLIGHT_IN_AIR = 0, 1, 2
#: display modes (the flight phase of an N3): those the emulated N3 reports
MODE_ATTITUDE = 1
MODE_P_GPS = 6
MODE_AUTO_TAKEOFF = 11
MODE_AUTO_LANDING = 12
MODE_NAVI_GO_HOME = 15
MODE_NAVI_SDK_CTRL = 17
MODE_ENGINE_START = 41
DEVICE_RC, DEVICE_APP, DEVICE_ONBOARD = 0, 1, 2
DEVICE_MASK = 0x07
DEVICE_SDK_ON = 0x08
#: the identity the emulated N3 reports (0x00 0x00): hardware, FC firmware, serial number
FC_HARDWARE = "N3"
FC_FIRMWARE = (3, 3, 8, 47)
FC_SERIAL = b"EMU0N3000000001"


def fc_version_word(firmware: tuple[int, int, int, int] = FC_FIRMWARE) -> int:
    """The firmware version as OSDK packs it in a u32 (one byte each, major first)."""
    a, b, c, d = firmware
    return a << 24 | b << 16 | c << 8 | d


def version_value(code: int, serial: bytes = FC_SERIAL, hardware: str = FC_HARDWARE,
                  firmware: tuple[int, int, int, int] = FC_FIRMWARE) -> bytes:
    """The version query's ACK value as an N3 with FC firmware 3.2 or later sends it: u16 code, the
    serial number ending in NUL (at most 16 characters), then the 32-byte name
    "SDK-v1.0 BETA <hardware>-aa.bb.cc.dd" padded with NUL."""
    if len(serial) > 16 or b"\0" in serial:
        raise ValueError("the serial number is at most 16 bytes, none of them NUL")
    name = f"SDK-v1.0 BETA {hardware}-" + ".".join(f"{v:02d}" for v in firmware)
    return _U16.pack(code) + serial + b"\0" + name.encode().ljust(32, b"\0")


def read_version(value: bytes) -> tuple[int, bytes, str] | None:
    """(code, serial, name) of a version ACK value as `version_value` lays it out; None if it is not."""
    end = value.find(b"\0", 2)
    if len(value) < 3 or end < 0 or end > 18:
        return None
    name = value[end + 1 : end + 33].split(b"\0", 1)[0].decode("ascii", "replace")
    return _U16.unpack_from(value)[0], value[2:end], name


_SETPOINT = struct.Struct("<B4f")
_ADVANCED_SETPOINT = struct.Struct("<BB6f")  # flag, advanced flag (1), x, y, z, yaw, x and y feed-forward
_U16 = struct.Struct("<H")
_HEAD = struct.Struct("<BHBB3xH")  # SOF, LEN | VER << 10, SESSION | ACK << 5, PADDING | ENC << 5, SEQ
_CRC16 = struct.Struct("<H")
_CRC32 = struct.Struct("<I")
#: a header's first eight bytes as one little-endian number (`frame_size`): SOF (bits 0-7), LEN (8-17), VER
#: (18-23), SESSION (24-28), ACK (29), 2 reserved bits (30-31), PADDING and ENC (32-39), 3 reserved bytes
#: (40-63)
_HEAD_WORD = struct.Struct("<Q")
#: the bits of that number a good header fixes: SOF (0xAA), VER and the reserved bits and bytes (all 0)
_HEAD_FIXED_BITS = 0xFFFFFF << 40 | 0xC0 << 24 | 0xFC << 16 | 0xFF


class Frame(NamedTuple):
    """One good frame: its header fields and its data (a command's set, id and payload, or an ACK's
    value). (A named tuple: one is made per frame received.)"""

    session: int
    is_ack: bool
    seq: int
    data: bytes
    enc: int = ENC_NONE
    padding: int = 0

    @property
    def cmd_set(self) -> int:
        return self.data[0] if self.data else -1

    @property
    def cmd_id(self) -> int:
        return self.data[1] if len(self.data) > 1 else -1

    @property
    def payload(self) -> bytes:
        return self.data[2:]

    @property
    def wants_ack(self) -> bool:
        return not self.is_ack and self.session != SESSION_NO_ACK


def encode(session: int, seq: int, data: bytes, *, is_ack: bool = False, enc: int = ENC_NONE,
           padding: int = 0) -> bytes:
    """One frame of ``data``; ValueError for a field out of range."""
    if not 0 <= session <= 31:
        raise ValueError(f"session must be 0..31, got {session}")
    size = len(data)
    if size > MAX_DATA_BYTES:
        raise ValueError(f"data of {size} bytes: at most {MAX_DATA_BYTES} fit a frame")
    if (enc or padding) and not (0 <= enc <= 7 and 0 <= padding <= 31):  # (commands: both 0)
        raise ValueError(f"ENC must be 0..7 and PADDING 0..31, got {enc}, {padding}")
    head = _HEAD.pack(SOF, MIN_FRAME_BYTES + size, session | is_ack << 5, padding | enc << 5, seq & 0xFFFF)
    body = head + _CRC16.pack(_ARC(head, CRC_INIT)) + data  # (`crc16`, inline)
    return body + _CRC32.pack(_ZLIB_CRC32(body, _CRC32_SEED) ^ 0xFFFFFFFF)  # (`crc32`, inline)


def encode_command(cmd_set: int, cmd_id: int, payload: bytes, session: int, seq: int) -> bytes:
    """A command frame."""
    return encode(session, seq, bytes((cmd_set, cmd_id)) + payload)


def encode_ack(session: int, seq: int, value: bytes) -> bytes:
    """The ACK frame that answers the command of ``session`` and ``seq``."""
    return encode(session, seq, value, is_ack=True)


def ack_code(code: int) -> bytes:
    """An ACK value of one u16 return code."""
    return _U16.pack(code)


def read_ack_code(value: bytes) -> int | None:
    """The u16 return code an ACK value starts with (None: too short)."""
    return _U16.unpack_from(value)[0] if len(value) >= 2 else None


def setpoint_payload(flag: int, x: float, y: float, z: float, yaw: float) -> bytes:
    """The flight-control setpoint (0x01 0x03): control flag, roll/x, pitch/y, thrust/z, yaw (float32)."""
    return _SETPOINT.pack(flag, x, y, z, yaw)


def read_setpoint(payload: bytes) -> tuple[int, float, float, float, float] | None:
    """(flag, x, y, z, yaw) of a setpoint payload: the 17-byte form, or OSDK's 26-byte advanced form
    (its feed-forward terms are not flown); None when it is neither."""
    if len(payload) == _SETPOINT.size:
        return _SETPOINT.unpack(payload)
    if len(payload) == _ADVANCED_SETPOINT.size:
        flag, _adv, x, y, z, yaw, _xf, _yf = _ADVANCED_SETPOINT.unpack(payload)
        return flag, x, y, z, yaw
    return None


#: what `frame_size` says of bytes that start no frame: no SOF or a bad header, or a good header whose LEN
#: is under `MIN_FRAME_BYTES`
NO_FRAME, SHORT_FRAME = -1, -2


def frame_size(buf: bytes | bytearray, i: int) -> int:
    """The LEN of the frame that starts at ``buf[i]``, by its header: 0 when the header is not complete
    in ``buf``; below 0 when ``buf[i]`` starts no frame: `NO_FRAME` (no SOF, or a header whose CRC16 is
    bad, whose VER is not 0 or whose reserved bits and bytes are not 0), `SHORT_FRAME` (a good header, a
    LEN under 16). The one check of a header: the parser and the splitter both ask it."""
    if buf[i] != SOF:
        return NO_FRAME
    if i + HEADER_BYTES > len(buf):
        return 0
    (head,) = _HEAD_WORD.unpack_from(buf, i)  # (the header's first eight bytes, one number: one call)
    # VER 0, the reserved bits and bytes 0; `crc16` of the header with its CRC: 0
    if head & _HEAD_FIXED_BITS != SOF or _ARC(buf[i : i + HEADER_BYTES], CRC_INIT):
        return NO_FRAME
    size = head >> 8 & 0x3FF  # LEN (bits 8-17)
    return size if size >= MIN_FRAME_BYTES else SHORT_FRAME


@dataclass
class OpenStats:
    """What a parser and codec saw on the wire (counts)."""

    frames_received: int = 0
    frames_sent: int = 0
    acks_received: int = 0
    garbage_bytes: int = 0  # bytes skipped while looking for a frame start
    bad_header: int = 0  # a CRC16 that does not match, a VER that is not 0, reserved bits set
    bad_length: int = 0  # LEN shorter than a header and CRC32
    bad_crc: int = 0  # a good header, a CRC32 that does not match
    encrypted: int = 0  # good frames with ENC set (the FC has no key: answered, not read)
    retries: int = 0  # reliable commands sent again (same SESSION and SEQ)
    timeouts: int = 0  # reliable commands given up on

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @property
    def errors(self) -> int:
        return self.garbage_bytes + self.bad_header + self.bad_length + self.bad_crc


class FrameParser:
    """Cuts a byte stream into good frames, counting the rest in ``stats``.

    It resynchronises on the next SOF after garbage, a bad header or a bad CRC32, one byte after the
    start it gave up on: a frame that follows a bad one, even inside the bad one's claimed length, is
    found. It waits for a frame's bytes only once its header (and so its LEN) has checked out."""

    def __init__(self, stats: OpenStats | None = None) -> None:
        self.stats = stats or OpenStats()
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        """The good frames (as bytes) of what has come so far, in order."""
        held = self._buf
        if held:
            held += data
            buf = held
        else:  # (the usual case: read from ``data`` itself, keep only what is left of it)
            buf = data
        out: list[bytes] = []
        st = self.stats
        i, n = 0, len(buf)
        while i < n:
            size = frame_size(buf, i)
            if size <= 0:
                if size == 0:  # (a header not complete yet)
                    break
                if buf[i] != SOF:
                    j = buf.find(SOF, i + 1)
                    j = n if j < 0 else j
                    st.garbage_bytes += j - i
                    i = j
                    continue
                if size == SHORT_FRAME:
                    st.bad_length += 1
                else:
                    st.bad_header += 1
                i += 1
                continue
            if i + size > n:
                break
            frame = buf[i : i + size]
            if frame.__class__ is not bytes:
                frame = bytes(frame)
            if _ZLIB_CRC32(frame, _CRC32_SEED) != _CRC32_CLOSED:  # (`crc32` of the frame with its own CRC: 0)
                st.bad_crc += 1
                i += 1
                continue
            out.append(frame)
            i += size
        if buf is held:
            del held[:i]
        elif i < n:
            held += buf[i:]
        return out

    @property
    def pending_bytes(self) -> int:
        return len(self._buf)


def FrameSplitter() -> _Splitter:
    """Cuts an OPEN-protocol byte stream into frames by their checked headers and LEN (no CRC32 check:
    a codec does that); bytes that start no frame are passed on as they are."""
    return _Splitter(frame_size, bytes((SOF,)))


_new_tuple = tuple.__new__  # (what a named tuple's own constructor calls, without its Python frame)


def decode(frame: bytes) -> Frame:
    """The fields of one good frame (as `FrameParser` hands them over)."""
    flags, coding = frame[3], frame[4]
    # Frame(session, is_ack, seq, data, enc, padding)
    return _new_tuple(Frame, (flags & 0x1F, bool(flags & 0x20), frame[8] | frame[9] << 8,
                              frame[HEADER_BYTES:-CRC32_BYTES], coding >> 5, coding & 0x1F))


@dataclass
class _Pending:
    """A reliable command waiting for its ACK."""

    key: tuple[int, int]  # (command set, command id)
    frame: bytes
    seq: int
    next_try_s: float
    tries: int


class OpenCodec:
    """OPEN-protocol frames over a byte-stream Transport, stamped by a Clock.

    Sending: `send_command` frames a command on a session: 0 (no ACK), 1 (ACK wanted, not resent), or a
    free reliable session 2-31, kept until its ACK comes and resent with the same SESSION and SEQ every
    ``retry_s`` up to ``tries`` times (`service`). `receive` hands back the good frames that are not
    ACKs and keeps the ACKs' values, by (command set, command id), in ``acks``."""

    def __init__(self, transport: Transport, clock: Clock, *, recorder: object | None = None,
                 retry_s: float = 0.1, tries: int = 3, keep_acks: bool = False) -> None:
        if not (math.isfinite(retry_s) and retry_s > 0 and tries >= 1):
            raise ValueError(f"retries need retry_s > 0 and tries >= 1, got {retry_s}, {tries}")
        self.transport = transport
        self.clock = clock
        self.recorder = recorder
        self.stats = OpenStats()
        self.parser = FrameParser(self.stats)
        self.retry_s, self.tries = retry_s, tries
        self.keep_acks = keep_acks  # see `feed`
        self._seq = 0
        self._pending: dict[int, _Pending] = {}  # session -> command waiting for its ACK
        self._once: dict[int, tuple[int, int]] = {}  # seq -> command of a session-1 frame
        #: ACK values received, by (command set, command id), with the clock time (s) they came
        self.acks: dict[tuple[int, int], tuple[bytes, float]] = {}

    def next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFFFF
        return self._seq

    def pack_command(self, cmd_set: int, cmd_id: int, payload: bytes, session: int = SESSION_NO_ACK) -> bytes:
        """A command frame on ``session`` (0 or 1) with the next SEQ, counted and recorded as sent."""
        # (`next_seq`, `encode_command` and `_sent` without their calls: two or three frames a tick)
        self._seq = seq = (self._seq + 1) & 0xFFFF
        if session == SESSION_ACK_ONCE:
            self._once[seq] = (cmd_set, cmd_id)
            if len(self._once) > 64:
                self._once.pop(next(iter(self._once)))
        frame = encode(session, seq, bytes((cmd_set, cmd_id)) + payload)
        self.stats.frames_sent += 1
        rec = self.recorder
        if rec is not None:
            rec.record(frame, self.clock.now_s())  # type: ignore[attr-defined]
        return frame

    def send_command(self, cmd_set: int, cmd_id: int, payload: bytes, *, reliable: bool = True,
                     session: int | None = None) -> bytes:
        """Frame and write a command; ``reliable``: on a free session 2-31, resent until ACKed (a
        command of the same set and id still waiting is replaced). Returns the frame."""
        if not reliable:
            sess = SESSION_NO_ACK if session is None else session
            frame = self.pack_command(cmd_set, cmd_id, payload, sess)
        else:
            frame = self.pack_reliable(cmd_set, cmd_id, payload, session)
        self.transport.send(frame)
        return frame

    def pack_reliable(self, cmd_set: int, cmd_id: int, payload: bytes, session: int | None = None) -> bytes:
        """`send_command`'s reliable frame, kept for its ACK and retries, not written (the caller
        writes it)."""
        key = (cmd_set, cmd_id)
        self.acks.pop(key, None)
        for s, p in list(self._pending.items()):
            if p.key == key:
                del self._pending[s]
        sess = session if session is not None else self._free_session()
        seq = self.next_seq()
        frame = self._sent(encode_command(cmd_set, cmd_id, payload, sess, seq))
        self._pending[sess] = _Pending(key, frame, seq, self.clock.now_s() + self.retry_s, 1)
        return frame

    def _free_session(self) -> int:
        for s in RELIABLE_SESSIONS:
            if s not in self._pending:
                return s
        oldest = min(self._pending, key=lambda s: self._pending[s].next_try_s)
        del self._pending[oldest]
        self.stats.timeouts += 1
        return oldest

    def send_ack(self, session: int, seq: int, value: bytes) -> bytes:
        frame = self._sent(encode_ack(session, seq, value))
        self.transport.send(frame)
        return frame

    def _sent(self, frame: bytes) -> bytes:
        self.stats.frames_sent += 1
        rec = self.recorder
        if rec is not None:
            rec.record(frame, self.clock.now_s())  # type: ignore[attr-defined]
        return frame

    def service(self, now_s: float) -> list[bytes]:
        """Resend the reliable commands whose ACK is overdue (same SESSION, SEQ, bytes); those out of
        tries are dropped (``stats.timeouts``). Returns the frames to write (the caller writes them)."""
        out: list[bytes] = []
        if not self._pending:  # (the usual case: nothing waits)
            return out
        for s, p in list(self._pending.items()):
            if now_s < p.next_try_s:
                continue
            if p.tries >= self.tries:
                del self._pending[s]
                self.stats.timeouts += 1
                continue
            p.tries += 1
            p.next_try_s = now_s + self.retry_s
            self.stats.retries += 1
            out.append(p.frame)
        return out

    @property
    def waiting(self) -> int:
        """Reliable commands waiting for their ACK."""
        return len(self._pending)

    def receive(self, timeout_s: float = 0.0, time_s: float | None = None) -> list[Frame]:
        data = self.transport.recv(timeout_s)
        return self.feed(data, time_s) if data else []

    def feed(self, data: bytes, time_s: float | None = None) -> list[Frame]:
        """Parse ``data``: the good frames that are not ACKs (ACKs are matched into ``acks`` at once);
        with ``keep_acks``, the ACK frames too, in stream order, for the caller to `match_ack` when it
        acts on them (a lockstep reader acts on what came before a tick only). The recorder stamps the
        frames ``time_s`` (s, clock time): when the receiver acts on them (an FC's poll), so that its log
        and its timers agree however late the read came; the clock's time of the read by default."""
        keep_acks = self.keep_acks
        out = []
        now = self.clock.now_s() if time_s is None else time_s
        rec, stats = self.recorder, self.stats
        for raw in self.parser.feed(data):
            stats.frames_received += 1
            if rec is not None:
                rec.record(raw, now)  # type: ignore[attr-defined]
            f = decode(raw)
            if f.enc != ENC_NONE:
                stats.encrypted += 1
            if f.is_ack:
                stats.acks_received += 1
                if not keep_acks:
                    self.match_ack(f, now)
                    continue
            out.append(f)
        return out

    def match_ack(self, f: Frame, now_s: float) -> tuple[int, int] | None:
        """The (command set, id) the ACK ``f`` answers, its value kept in ``acks`` (None: it answers
        nothing this codec waits for)."""
        p = self._pending.get(f.session)
        if p is not None and p.seq == f.seq:
            del self._pending[f.session]
            key = p.key
        elif f.session == SESSION_ACK_ONCE and f.seq in self._once:
            key = self._once.pop(f.seq)
        else:
            return None
        self.acks[key] = (f.data, now_s)
        return key

    def is_waiting(self, cmd_set: int, cmd_id: int) -> bool:
        """Whether a reliable command of this set and id waits for its ACK."""
        return any(p.key == (cmd_set, cmd_id) for p in self._pending.values())


#: the commands' names, by (command set, command id), for decoders and logs
COMMAND_NAMES: dict[tuple[int, int], str] = {
    (SET_ACTIVATION, CMD_VERSION): "version query",
    (SET_ACTIVATION, CMD_ACTIVATE): "activation",
    (SET_ACTIVATION, CMD_BROADCAST_FREQ): "flight data rates",
    (SET_CONTROL, CMD_CONTROL_AUTHORITY): "control authority",
    (SET_CONTROL, CMD_TASK): "flight task",
    (SET_CONTROL, CMD_SETPOINT): "setpoint",
    (SET_CONTROL, CMD_ARM): "arm/disarm",
    (SET_BROADCAST, CMD_FLIGHT_DATA): "flight data",
    (SET_BROADCAST, CMD_CONTROL_LOST): "control lost",
    (SET_BROADCAST, CMD_SUBSCRIPTION_DATA): "subscription data",
    (SET_SUBSCRIBE, CMD_SUB_VERSION): "subscription version match",
    (SET_SUBSCRIBE, CMD_SUB_ADD): "subscription add package",
    (SET_SUBSCRIBE, CMD_SUB_RESET): "subscription reset",
    (SET_SUBSCRIBE, CMD_SUB_REMOVE): "subscription remove package",
    (SET_SUBSCRIBE, CMD_SUB_FREQ): "subscription package frequency",
    (SET_SUBSCRIBE, CMD_SUB_PAUSE): "subscription pause/resume",
    (SET_SUBSCRIBE, CMD_SUB_CONFIG): "subscription configuration",
    (SET_HIL, CMD_HIL_TICK): "hil tick",
    (SET_HIL, CMD_HIL_ANSWER): "hil tick answer",
}


#: frames the FC sends (besides every ACK): pushed flight data, and the lockstep's tick
FC_SENT: frozenset[tuple[int, int]] = frozenset(
    {(SET_BROADCAST, CMD_FLIGHT_DATA), (SET_BROADCAST, CMD_CONTROL_LOST),
     (SET_BROADCAST, CMD_SUBSCRIPTION_DATA), (SET_HIL, CMD_HIL_TICK)}
)


def good_frame_at(data: bytes, j: int) -> bytes | None:
    """The whole, CRC-checked frame that starts at ``data[j]``, or None."""
    size = frame_size(data, j)
    frame = data[j : j + size]
    return frame if size > 0 and len(frame) == size and crc32(frame) == 0 else None


def describe_frame(frame: bytes) -> tuple[str, str, str, dict[str, Any]]:
    """A captured (CRC-checked) frame read for a person: its kind (ACK, or the command's name in capitals),
    sender ('fc' for ACKs and what the FC pushes; else 'peer'), one line (`describe`) and the fields."""
    f = decode(frame)
    if f.is_ack:
        kind, sender = "ACK", "fc"
    else:
        name = COMMAND_NAMES.get((f.cmd_set, f.cmd_id))
        kind = name.upper().replace(" ", "_").replace("/", "_") if name else \
            f"0X{f.cmd_set:02X}_0X{f.cmd_id:02X}"
        sender = "fc" if (f.cmd_set, f.cmd_id) in FC_SENT else "peer"
    fields = {"session": f.session, "seq": f.seq, "ack": f.is_ack, "enc": f.enc, "data": f.data.hex()}
    return kind, sender, "DJI " + describe(frame), fields


def describe(frame: bytes) -> str:
    """One line about a good frame: session, SEQ, what it is and its fields."""
    f = decode(frame)
    head = f"session {f.session:2d} seq {f.seq:5d} "
    if f.enc != ENC_NONE:
        return head + f"encrypted (ENC {f.enc}, {len(f.data)} bytes)"
    if f.is_ack:
        code = read_ack_code(f.data)
        extra = f" +{len(f.data) - 2} bytes" if len(f.data) > 2 else ""
        return head + (f"ACK 0x{code:04X}{extra}" if code is not None else f"ACK {f.data.hex()}")
    name = COMMAND_NAMES.get((f.cmd_set, f.cmd_id), "unknown")
    what = f"0x{f.cmd_set:02X} 0x{f.cmd_id:02X} {name}"
    p = f.payload
    if (f.cmd_set, f.cmd_id) == (SET_CONTROL, CMD_SETPOINT) and (sp := read_setpoint(p)) is not None:
        flag, x, y, z, yaw = sp
        if flag & 0xC0 == HORIZONTAL_ANGLE:
            return head + f"{what}: flag 0x{flag:02X} roll {x:.2f} pitch {y:.2f} thrust {z:.2f} yaw {yaw:.2f}"
        return head + f"{what}: flag 0x{flag:02X} x {x:.2f} y {y:.2f} z {z:.2f} yaw {yaw:.2f}"
    if (f.cmd_set, f.cmd_id) == (SET_BROADCAST, CMD_FLIGHT_DATA) and len(p) >= 2:
        flags = p[0] | p[1] << 8
        items = [n for i, (n, _) in enumerate(BROADCAST_ITEMS) if flags >> i & 1]
        return head + f"{what}: {', '.join(items)}"
    if (f.cmd_set, f.cmd_id) == (SET_SUBSCRIBE, CMD_SUB_ADD) and len(p) >= SUB_PACKAGE_HEAD.size:
        pkg, hz, config, n = SUB_PACKAGE_HEAD.unpack_from(p)
        uids = struct.unpack_from(f"<{min(n, (len(p) - 5) // 4)}I", p, SUB_PACKAGE_HEAD.size)
        names = [TOPICS[u][0] if u in TOPICS else f"0x{u:08X}" for u in uids]
        return head + f"{what}: package {pkg} at {hz} Hz (config {config}): {', '.join(names)}"
    return head + f"{what}: {p.hex(' ')}" if p else head + what
