"""The emulated N3 as Onboard SDK 3.9 drives it, over a pty, from a client written here from DJI's public
facts (its own framer and CRCs with crcmod, not the project's codec): version, activation, subscription,
the take-off task climbing into the air, a position offset, landing, release; the setpoint-loss hover and
taking over again in either order; hostile subscription traffic refused with the documented codes."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
import time

import crcmod
import pytest

from hil.link import SerialTransport

_CRC16 = crcmod.mkCrcFun(0x18005, initCrc=0x3AA3, rev=True, xorOut=0)
_CRC32 = crcmod.mkCrcFun(0x104C11DB7, initCrc=0x3AA3, rev=True, xorOut=0)
# topic UIDs (OSDK 3.9's dji_telemetry.hpp)
STATUS_FLIGHT, DISPLAY_MODE, GPS_FUSED, HEIGHT_FUSION = 0x20CFB02A, 0x1A67D6A1, 0x4B19A8C7, 0x87CF419D
QUATERNION, CONTROL_DEVICE, RTK_POSITION = 0xA493281F, 0x667BA86A, 0x1DF9A6B6
EARTH_M = 6378137.0


def frame(session: int, seq: int, data: bytes) -> bytes:
    head = struct.pack("<BHBB3xH", 0xAA, 16 + len(data), session, 0, seq)
    head += struct.pack("<H", _CRC16(head))
    return head + data + struct.pack("<I", _CRC32(head + data))


class Osdk:
    """A small OSDK-like client: reliable commands on session 2, setpoints on session 0, the pushed
    subscription packages kept by package id."""

    def __init__(self, link: SerialTransport) -> None:
        self.link, self.buf, self.seq = link, bytearray(), 0
        self.acks: dict[int, bytes] = {}
        self.packages: dict[int, bytes] = {}

    def pump(self, seconds: float = 0.0) -> None:
        end = time.monotonic() + seconds
        while True:
            self.buf += self.link.recv(0.01)
            while len(self.buf) >= 16:
                if self.buf[0] != 0xAA:
                    del self.buf[0]
                    continue
                n = (self.buf[1] | self.buf[2] << 8) & 0x3FF
                if _CRC16(bytes(self.buf[:12])) != 0 or n < 16:
                    del self.buf[0]
                    continue
                if len(self.buf) < n:
                    break
                raw = bytes(self.buf[:n])
                del self.buf[:n]
                assert _CRC32(raw) == 0
                data = raw[12:-4]
                if raw[3] & 0x20:
                    self.acks[raw[8] | raw[9] << 8] = data
                elif data[:2] == b"\x02\x05":
                    self.packages[data[2]] = data[3:]
            if time.monotonic() >= end:
                return

    def ask(self, cmd_set: int, cmd_id: int, payload: bytes) -> bytes:
        self.seq += 1
        seq = self.seq
        self.link.send(frame(2, seq, bytes((cmd_set, cmd_id)) + payload))
        deadline = time.monotonic() + 3.0
        while seq not in self.acks and time.monotonic() < deadline:
            self.pump(0.02)
        return self.acks[seq]

    def code(self, cmd_set: int, cmd_id: int, payload: bytes) -> int:
        value = self.ask(cmd_set, cmd_id, payload)
        return value[0] if cmd_set == 0x0B else struct.unpack_from("<H", value)[0]

    def setpoint(self, flag: int, x: float, y: float, z: float, yaw: float) -> None:
        self.seq += 1
        self.link.send(frame(0, self.seq, b"\x01\x03" + struct.pack("<B4f", flag, x, y, z, yaw)))

    def subscribe(self, pkg: int, hz: int, uids: tuple[int, ...]) -> int:
        return self.code(0x0B, 0x01, struct.pack("<BHBB", pkg, hz, 0, len(uids)) + struct.pack(
            f"<{len(uids)}I", *uids))

    def state(self) -> tuple[int, int, float, float, float, float]:
        """(flight status, display mode, longitude, latitude (rad), altitude, height (m))."""
        status, mode = self.packages[0][0], self.packages[0][1]
        lon, lat, alt, _sats, height = struct.unpack_from("<ddfHf", self.packages[1])
        return status, mode, lon, lat, alt, height

    def wait(self, what, seconds: float, stream=None) -> bool:
        """Pump until ``what(state)`` (True) or ``seconds`` pass (False), sending ``stream`` (a setpoint,
        or a function of the state giving one) every cycle."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if stream is not None:
                sp = stream(self.state()) if callable(stream) else stream
                self.setpoint(*sp)
            self.pump(0.02)
            if 0 in self.packages and 1 in self.packages and what(self.state()):
                return True
        return False


@pytest.fixture
def n3(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil.cli", "fc", "--protocol", "dji-open", "--gap", "none", "--mocap-link",
         "none", "--duration", "120", "--failsafe-timeout", "0.5"], stdout=subprocess.PIPE, text=True)
    link = None
    try:
        link = SerialTransport(json.loads(proc.stdout.readline())["command_link"], 230400)
        client = Osdk(link)
        version = client.ask(0x00, 0x00, b"\x00")
        serial, name = version[2:].split(b"\x00", 1)
        assert len(serial) <= 16 and name.startswith(b"SDK-v1.0 BETA N3-03.03.08.47\x00")
        fw = 0x0303082F
        assert client.code(0x00, 0x01, struct.pack("<III", 1069806, 2, fw) + b"0" * 32) == 0
        assert client.code(0x0B, 0x00, struct.pack("<I", 0x100)) == 0x00  # the topic database matches
        assert client.subscribe(0, 50, (STATUS_FLIGHT, DISPLAY_MODE, CONTROL_DEVICE)) == 0x00
        assert client.subscribe(1, 50, (GPS_FUSED, HEIGHT_FUSION)) == 0x00
        yield client
    finally:
        if link is not None:
            link.close()
        proc.terminate()
        proc.communicate(timeout=20)


def _offset_m(a: tuple, b: tuple) -> tuple[float, float]:
    """(north, east) of state ``b`` from state ``a`` (m), as OSDK's sample computes it."""
    return (b[3] - a[3]) * EARTH_M, (b[2] - a[2]) * EARTH_M * math.cos(b[3])


def test_an_osdk_client_takes_off_moves_by_an_offset_lands_and_releases(n3):
    assert n3.wait(lambda s: s[0] == 0, 2.0)  # motors stopped
    assert n3.code(0x01, 0x00, b"\x01") == 0x0002  # control obtained
    assert n3.code(0x01, 0x01, b"\x01") == 0x0000  # take off: an N3's success is 0
    assert n3.wait(lambda s: s[0] == 1 and s[1] == 41, 2.0)  # on the ground, engine start
    assert n3.wait(lambda s: s[0] == 2, 11.0)  # in the air within OSDK's 11 s
    assert n3.wait(lambda s: s[1] == 6 and s[5] > 1.2, 10.0)  # take-off done: hovering (P-GPS)
    start = n3.state()
    goal = (3.0, -2.0)

    def offset_left(s: tuple) -> tuple:  # OSDK's positionAndYawCtrl: the offset still to go, the height
        north, east = _offset_m(start, s)
        return 0x91, goal[0] - north, goal[1] - east, start[5], 0.0

    ok = n3.wait(lambda s: math.dist(_offset_m(start, s), goal) < 0.2, 20.0, stream=offset_left)
    assert ok, _offset_m(start, n3.state())
    assert abs(n3.state()[5] - start[5]) < 0.2  # at the height asked
    assert n3.code(0x01, 0x01, b"\x02") == 0x0000  # land
    assert n3.wait(lambda s: s[1] == 12, 2.0)  # auto landing
    assert n3.code(0x01, 0x00, b"\x00") == 0x0001  # released during the landing: it goes on
    assert n3.wait(lambda s: s[0] == 0, 20.0)  # landed and disarmed
    assert n3.code(0x01, 0x01, b"\x02") == 0xFF02  # a task without authority: no rights
    assert n3.code(0x01, 0x00, b"\x01") == 0x0002
    assert n3.code(0x01, 0x01, b"\x02") == 0x0004  # land on the ground: not in the air


@pytest.mark.parametrize("obtain_first", [True, False])
def test_after_the_setpoint_loss_hover_the_onboard_device_takes_over_in_either_order(n3, obtain_first):
    assert n3.code(0x01, 0x00, b"\x01") == 0x0002
    assert n3.code(0x01, 0x01, b"\x01") == 0x0000
    assert n3.wait(lambda s: s[1] == 6 and s[0] == 2, 15.0)
    climb = (0x48, 0.0, 0.0, 0.5, 0.0)  # velocity, yaw rate: 0.5 m/s up
    assert n3.wait(lambda s: s[1] == 17, 2.0, stream=climb)  # SDK control
    assert n3.wait(lambda s: s[1] == 6, 2.0)  # the stream stops: the FC hovers (P-GPS)
    if obtain_first:
        assert n3.code(0x01, 0x00, b"\x01") == 0x0002
        assert n3.wait(lambda s: s[1] == 17, 2.0, stream=climb)
    else:
        for _ in range(5):
            n3.setpoint(*climb)
            n3.pump(0.02)
        assert n3.code(0x01, 0x00, b"\x01") == 0x0002
        assert n3.wait(lambda s: s[1] == 17, 2.0, stream=climb)
    h = n3.state()[5]
    assert n3.wait(lambda s: s[5] > h + 0.3, 3.0, stream=climb)  # the setpoints fly again


def test_hostile_subscription_traffic_is_refused_with_the_documented_codes(n3):
    pack = struct.pack
    assert n3.code(0x0B, 0x00, pack("<I", 0x200)) == 0x02  # another topic database: version mismatch
    assert n3.code(0x0B, 0x00, b"\x00") == 0x01  # data length
    assert n3.subscribe(2, 50, (0xDEADBEEF,)) == 0x22  # unknown topic UID
    assert n3.subscribe(2, 50, (QUATERNION,) * 2) == 0x24  # a topic twice
    assert n3.subscribe(2, 50, (STATUS_FLIGHT,)) == 0x24  # already in package 0
    assert n3.subscribe(2, 33, (QUATERNION,)) == 0x06  # not a subscription frequency
    assert n3.subscribe(2, 400, (QUATERNION,)) == 0x06  # above the topic's 200 Hz
    assert n3.subscribe(2, 5, (RTK_POSITION,)) == 0x25  # no RTK receiver
    assert n3.subscribe(7, 50, (QUATERNION,)) == 0x03  # package out of range
    assert n3.subscribe(0, 50, (QUATERNION,)) == 0x04  # package 0 exists
    assert n3.subscribe(2, 50, ()) == 0x20  # empty
    too_big = (QUATERNION, 0x8696C85B, 0xBB17D5FE, 0xC3503A6E, 0x18FB271D, 0x3599C4BE, 0x700389EE, 0x11E9C81A,
               0x27396A39, 0x0C949E94, 0x7AC7EB80, 0x81FED54E, 0xDF3D72B7, 0x739F7FE4, 0x01F71678, 0x69779DD9,
               0xBFE4B520, 0x598F79BC, 0xD48912C9, 0xA6A0395F, 0xE30B17B0, 0x772D6E22, 0x3A41E909, 0x8B6CD45C,
               0xB5C2211F, 0x252C164B)  # every other topic served: 238 bytes
    with_time = pack("<BHBB", 2, 1, 1, len(too_big)) + pack(f"<{len(too_big)}I", *too_big)
    assert n3.code(0x0B, 0x01, with_time) == 0x07  # with the 8-byte time stamp: 246 bytes, over 242
    assert n3.subscribe(2, 1, too_big) == 0x00  # without: fits
    assert n3.code(0x0B, 0x03, b"\x02") == 0x00
    assert n3.code(0x0B, 0x01, pack("<BHBB", 2, 50, 0, 3) + pack("<I", QUATERNION)) == 0x01  # length
    assert n3.code(0x0B, 0x03, b"\x04") == 0x05  # no package 4
    assert n3.code(0x0B, 0x03, b"\x09") == 0x03
    n3.pump(0.3)
    assert n3.wait(lambda s: s[0] == 0, 1.0)  # packages 0 and 1 still pushed
