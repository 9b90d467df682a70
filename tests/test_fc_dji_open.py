"""The FC's DJI OPEN-protocol endpoint over an in-memory link in lockstep, driven by a client written here
from DJI's public protocol description (its own encoder and decoder, not the project's codec):
activation (and a refusal), control authority and the RC's mode switch, arming, a 50 Hz attitude-thrust
stream that climbs, the broadcast at the rates asked for, the setpoint-loss failsafe, encrypted and
unknown commands, retries answered once, and 100k hostile frames after which the setpoints still fly."""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest

from emulator.fc import FcConfig, FcState
from emulator.params import PARAMS, ParamError
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.servers.dji_open_server import DjiOpenServer, DjiServerConfig
from emulator.vehicle import EmulatedVehicle
from hil.link import MemoryTransport, SimClock
from hil.link.dji_open import OpenCodec

PROFILE = load_profile("n3_tx2")
HOVER_PERCENT = 100.0 * PROFILE.mass_kg * GRAVITY_M_S2 / PROFILE.n3_full_thrust_n


# --- a client from the public description (OPENProtocol.md, Appendix.md) -----------------------------
def _crc(data: bytes, poly: int) -> int:
    crc = 0x3AA3
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ poly if crc & 1 else crc >> 1
    return crc


def frame(session: int, seq: int, data: bytes, ack: bool = False, enc: int = 0) -> bytes:
    n = 12 + len(data) + 4
    head = bytes([0xAA, n & 0xFF, n >> 8, session | (0x20 if ack else 0), enc << 5, 0, 0, 0,
                  seq & 0xFF, seq >> 8])
    head += struct.pack("<H", _crc(head, 0xA001))
    body = head + data
    return body + struct.pack("<I", _crc(body, 0xEDB88320))


def unframe(buf: bytearray) -> list[tuple[int, bool, int, bytes]]:
    """(session, is ACK, seq, data) of the complete good frames at the front of ``buf`` (consumed)."""
    out = []
    while True:
        i = buf.find(b"\xaa")
        if i < 0:
            buf.clear()
            return out
        del buf[:i]
        if len(buf) < 12:
            return out
        n = (buf[1] | buf[2] << 8) & 0x3FF
        if _crc(bytes(buf[:12]), 0xA001) != 0 or n < 16:
            del buf[:1]
            continue
        if len(buf) < n:
            return out
        f = bytes(buf[:n])
        if _crc(f, 0xEDB88320) != 0:
            del buf[:1]
            continue
        del buf[:n]
        out.append((f[3] & 0x1F, bool(f[3] & 0x20), f[8] | f[9] << 8, f[12:-4]))


class Client:
    """An onboard device: commands on reliable session 2, setpoints on session 0, the flight data read."""

    def __init__(self, end: MemoryTransport) -> None:
        self.end, self.buf, self.seq = end, bytearray(), 100
        self.acks: dict[int, bytes] = {}  # seq -> ACK value
        self.flight_data: list[tuple[int, bytes]] = []  # (flags, items)
        self.control_lost = 0

    def command(self, cmd_set: int, cmd_id: int, payload: bytes, session: int = 2) -> int:
        self.seq += 1
        self.end.send(frame(session, self.seq, bytes((cmd_set, cmd_id)) + payload))
        return self.seq

    def setpoint(self, flag: int, roll: float, pitch: float, thrust: float, yaw: float) -> None:
        self.seq += 1
        self.end.send(frame(0, self.seq, b"\x01\x03" + struct.pack("<B4f", flag, roll, pitch, thrust, yaw)))

    def read(self) -> None:
        self.buf += self.end.recv(0.0)
        for _session, ack, seq, data in unframe(self.buf):
            if ack:
                self.acks[seq] = data
            elif data[:2] == b"\x02\x00":
                self.flight_data.append((struct.unpack_from("<H", data, 2)[0], data[4:]))
            elif data[:2] == b"\x02\x01":
                self.control_lost += 1

    def code(self, seq: int) -> int:
        return struct.unpack_from("<H", self.acks[seq])[0]

    def latest(self, bit: int, layout: str) -> tuple:
        """The item of flag ``bit`` in the latest flight data that has it (items before it skipped)."""
        sizes = [15, 16, 12, 13, 12, 50, 68, 44, 6, 12, 13, 4, 13, 2]  # the N3's items
        for flags, items in reversed(self.flight_data):
            if flags >> bit & 1:
                off = sum(sizes[i] for i in range(bit) if flags >> i & 1)
                return struct.unpack_from(layout, items, off)
        raise AssertionError(f"no flight data with item {bit}")


ACTIVATION = struct.pack("<III", 1069806, 0, 0x03010A00) + b"12345678901234567890123456789012"


class Rig:
    def __init__(self, config: DjiServerConfig | None = None, fc: FcConfig | None = None) -> None:
        self.clock = SimClock()
        fc_end, ob_end = MemoryTransport.pair(capacity_bytes=1 << 22)
        self.vehicle = EmulatedVehicle(PROFILE, config=fc)
        self.server = DjiOpenServer(self.vehicle, OpenCodec(fc_end, self.clock), config)
        self.client = Client(ob_end)

    def run(self, duration_s: float, setpoint: tuple | None = None, rate_hz: float = 50.0) -> None:
        end = self.clock.now_s() + duration_s
        next_sp = self.clock.now_s()
        while self.clock.now_s() < end - 1e-9:
            self.clock.advance_to(round(self.clock.now_s() + 0.001, 6))
            now = self.clock.now_s()
            if setpoint is not None and now >= next_sp - 1e-9:
                self.client.setpoint(*setpoint)
                next_sp += 1.0 / rate_hz
            self.server.poll(now)
            self.vehicle.step_to(now)
            self.client.read()

    def ask(self, cmd_set: int, cmd_id: int, payload: bytes) -> int:
        seq = self.client.command(cmd_set, cmd_id, payload)
        self.run(0.02)
        return self.client.code(seq)

    def activate(self) -> None:
        assert self.ask(0x00, 0x01, ACTIVATION) == 0x0000


def test_a_public_protocol_client_activates_obtains_control_arms_climbs_and_sees_the_failsafe():
    rig = Rig(fc=FcConfig(failsafe_timeout_s=0.5))
    c = rig.client
    assert rig.ask(0x00, 0x00, b"\x00") == 0xFF01  # version query before activation: not activated
    rig.activate()
    v = rig.client.command(0x00, 0x00, b"\x00")
    rig.run(0.02)
    # after the code: the serial number and its NUL, then the name OSDK parses (hardware N3, firmware)
    serial, name = c.acks[v][2:].split(b"\x00", 1)
    assert c.code(v) == 0 and 0 < len(serial) <= 16 and name.startswith(b"SDK-v1.0 BETA N3-03.03.08.47\x00")
    # broadcast (the N3's items): status and control device at 50 Hz, position (height) at 10 Hz
    assert rig.ask(0x00, 0x10, bytes([0, 0, 0, 3, 0, 2, 0, 0, 0, 0, 0, 3, 0, 3, 7, 7])) == 0
    c.flight_data.clear()
    rig.run(1.0)
    counts = {b: sum(1 for f, _ in c.flight_data if f >> b & 1) for b in range(14)}
    assert counts[11] == pytest.approx(50, abs=2) and counts[13] == pytest.approx(50, abs=2)
    assert counts[5] == pytest.approx(10, abs=1) and counts[3] == pytest.approx(50, abs=2)
    assert counts[1] == counts[0] == 0
    assert c.latest(11, "<4B")[0] == 0  # motors stopped
    assert rig.ask(0x01, 0x05, b"\x01") == 0x0001  # arm before obtaining control: refused
    assert rig.ask(0x01, 0x00, b"\x01") == 0x0002  # control obtained
    rig.run(0.05)
    assert c.latest(13, "<BB")[1] & 0x07 == 2  # the onboard device holds control
    assert rig.ask(0x01, 0x05, b"\x01") == 0x0000  # armed
    assert rig.ask(0x01, 0x05, b"\x01") == 0x0002  # already armed
    h0 = c.latest(5, "<ddffB")[3]
    rig.run(2.0, setpoint=(0x20, 0.0, 0.0, HOVER_PERCENT * 1.25, 0.0))
    assert rig.vehicle.fc.state is FcState.OFFBOARD
    h1 = c.latest(5, "<ddffB")[3]
    assert h1 > h0 + 0.5, f"no climb seen in the broadcast: {h0:.2f} -> {h1:.2f} m"
    assert c.latest(11, "<4B")[:2] == (2, 17)  # in the air, SDK control
    assert c.latest(3, "<3fB")[2] > 0.2  # climbing (ground frame, up)
    rig.run(1.0)  # the stream stops
    assert rig.vehicle.fc.state is FcState.FAILSAFE_HOVER
    # the FC hovers (P-GPS) and, as an N3, leaves the authority with the onboard device
    assert c.control_lost == 0 and c.latest(13, "<BB")[1] & 0x07 == 2 and c.latest(11, "<4B")[1] == 6


def test_activation_refused_as_configured_and_commands_before_it_are_unauthorised():
    rig = Rig(DjiServerConfig(activation_code=0x0006))
    assert rig.ask(0x00, 0x01, ACTIVATION) == 0x0006
    assert rig.ask(0x01, 0x00, b"\x01") == 0xFF01
    rig.run(0.2)
    assert rig.client.flight_data == []  # nothing pushed to an unactivated device
    old = Rig()
    assert old.ask(0x00, 0x01, ACTIVATION[:8] + struct.pack("<I", 0x02000000) + ACTIVATION[12:]) == 0x0008
    assert old.ask(0x00, 0x01, ACTIVATION[:20]) == 0x0001


def test_control_needs_the_rc_in_f_mode_and_release_hands_back_to_the_fc():
    rig = Rig(DjiServerConfig(rc_mode="P"))
    rig.activate()
    assert rig.ask(0x01, 0x00, b"\x01") == 0x0000  # not in F mode
    rig = Rig()
    rig.activate()
    assert rig.ask(0x01, 0x00, b"\x01") == 0x0002
    rig.ask(0x01, 0x05, b"\x01")
    rig.run(0.5, setpoint=(0x20, 0.0, 0.0, HOVER_PERCENT * 1.2, 0.0))
    assert rig.vehicle.fc.state is FcState.OFFBOARD
    assert rig.ask(0x01, 0x00, b"\x00") == 0x0001
    assert rig.vehicle.fc.state is FcState.HOLD
    rig.run(0.5, setpoint=(0x20, 20.0, 0.0, 80.0, 0.0))
    assert rig.server.stats.setpoints_without_control >= 24  # no authority: not flown
    assert rig.vehicle.fc.state is FcState.HOLD
    assert abs(rig.vehicle.state.vel_m_s[2]) < 0.3  # the FC holds; 80 % thrust is not flown


def test_tasks_land_and_stop_motors():
    rig = Rig()
    rig.activate()
    rig.ask(0x01, 0x00, b"\x01")
    assert rig.ask(0x01, 0x01, b"\x07") == 0x0000  # start motors (an N3's success: 0)
    assert rig.vehicle.fc.state.armed
    assert rig.ask(0x01, 0x01, b"\x07") == 0x0001  # the motors already run
    assert rig.ask(0x01, 0x01, b"\x08") == 0x0000  # stop motors (on the ground)
    assert not rig.vehicle.fc.state.armed
    assert rig.ask(0x01, 0x01, b"\x08") == 0x0002  # the motors do not run
    assert rig.ask(0x01, 0x01, b"\x02") == 0x0004  # land on the ground: not in the air
    assert rig.ask(0x01, 0x01, b"\x63") == 0x000A  # no such task


def test_the_n3_tasks_take_off_to_a_hover_go_home_and_land_in_simulated_time():
    rig = Rig()
    rig.activate()
    fc, v = rig.vehicle.fc, rig.vehicle
    assert rig.ask(0x01, 0x01, b"\x01") == 0xFF02  # a task needs control authority
    rig.ask(0x01, 0x00, b"\x01")
    assert rig.ask(0x01, 0x01, b"\x06") == 0x0004  # go home on the ground: not in the air
    assert rig.ask(0x01, 0x01, b"\x01") == 0x0000  # take off
    assert rig.ask(0x01, 0x01, b"\x01") == 0x0008  # already taking off
    rig.run(0.5)
    assert fc.landed and fc.state is FcState.TAKEOFF and v.state.pos_m[2] < fc.rest_height_m + 0.01  # spin-up
    rig.run(4.0)
    assert fc.state is FcState.HOLD and not fc.landed
    z = v.state.pos_m[2]
    assert fc.rest_height_m + 1.15 < z < fc.rest_height_m + 1.5  # 1.2 m above the resting height
    rig.run(2.0)
    assert abs(v.state.pos_m[2] - z) < 0.1 and abs(v.state.vel_m_s).max() < 0.1  # hovering
    assert rig.ask(0x01, 0x01, b"\x01") == 0x0003  # take off in the air
    assert rig.ask(0x01, 0x01, b"\x08") == 0x0003  # stop the motors in the air
    # away with a velocity setpoint (north 1 m/s, ground frame, yaw rate 0), then home
    rig.run(3.0, setpoint=(0x48, 1.0, 0.0, 0.0, 0.0))
    assert fc.state is FcState.OFFBOARD and v.state.pos_m[1] > 2.0  # (ENU y: north)
    assert rig.ask(0x01, 0x01, b"\x06") == 0x0000
    rig.run(0.5, setpoint=(0x48, 1.0, 0.0, 0.0, 0.0))
    assert fc.state is FcState.GO_HOME  # the onboard setpoints do not interrupt it
    assert rig.ask(0x01, 0x00, b"\x00") == 0x0001  # nor does a release
    rig.run(15.0)
    assert fc.state is FcState.DISARMED and np.hypot(*v.state.pos_m[:2]) < 0.4  # landed at home


def test_encrypted_unknown_and_resent_commands_get_their_documented_answers():
    rig = Rig()
    rig.activate()
    c = rig.client
    c.seq += 1
    c.end.send(frame(3, c.seq, bytes(16), enc=1))
    rig.run(0.02)
    assert c.code(c.seq) == 0xFF00  # encrypted: the emulator holds no key
    assert rig.ask(0x07, 0x00, b"") == 0xFF02  # unknown command set
    assert rig.ask(0x01, 0x7F, b"") == 0xFF02  # unknown id
    seq = c.command(0x01, 0x00, b"\x01", session=5)
    rig.run(0.02)
    del c.acks[seq]
    c.end.send(frame(5, seq, b"\x01\x00\x01"))  # the same SESSION and SEQ again: the ACK was lost
    rig.run(0.02)
    assert c.code(seq) == 0x0002 and rig.server.stats.retries_answered == 1
    assert rig.server.stats.encrypted_refused == 1 and rig.server.stats.commands_unknown == 2
    assert rig.server.codec.stats.encrypted == 1


_LONG = frame(0, 1, b"\x01\x03" + bytes(1003))[:-7]  # a good header of LEN 1023, the frame cut short
_NAN = frame(0, 2, b"\x01\x03" + struct.pack("<B4f", 0x20, float("nan"), 0.0, 50.0, 0.0))
_UNKNOWN = {(s, i): frame(0, 3, bytes((s, i))) for s in (0x03, 0x7E, 0xFF) for i in (0x00, 0x42)}


def _hostile(rng: np.random.Generator, good: bytes) -> bytes:
    """One hostile frame of the kinds the issue names."""
    kind = int(rng.integers(0, 8))
    if kind == 0:
        return rng.bytes(int(rng.integers(1, 64)))
    b = bytearray(good)
    if kind == 1:  # bit flips
        for _ in range(int(rng.integers(1, 4))):
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
        return bytes(b)
    if kind == 2:  # bad CRC16
        b[10] ^= 0xFF
        return bytes(b)
    if kind == 3:  # bad CRC32
        b[-1] ^= 0x5A
        return bytes(b)
    if kind == 4:  # a LEN of 1023 on a short frame, and a frame of 1100 bytes claiming 1023
        return _LONG + rng.bytes(int(rng.integers(0, 200)))
    if kind == 5:  # wrong version (header CRC made good)
        b[2] |= 0x08
        b[10:12] = struct.pack("<H", _crc(bytes(b[:10]), 0xA001))
        return bytes(b)
    if kind == 6:  # NaN floats in a setpoint
        return _NAN
    keys = list(_UNKNOWN)
    return _UNKNOWN[keys[int(rng.integers(0, len(keys)))]]


def test_100k_hostile_frames_are_counted_and_answered_and_the_setpoints_still_fly():
    rig = Rig()
    rig.activate()
    rig.ask(0x01, 0x00, b"\x01")
    rig.ask(0x01, 0x05, b"\x01")
    rng = np.random.default_rng(15)
    good = frame(0, 9, b"\x01\x03" + struct.pack("<B4f", 0x20, 0.0, 0.0, HOVER_PERCENT, 0.0))
    sent = 0
    while sent < 100_000:
        burst = b"".join(_hostile(rng, good) for _ in range(50))
        rig.client.end.send(burst)
        sent += 50
        for _ in range(3):  # (a poll reads up to 64 KiB)
            rig.server.poll(rig.clock.now_s())
        rig.client.end.recv(0.0)  # the answers: read and dropped
    st, cs = rig.server.stats, rig.server.codec.stats
    assert cs.bad_header > 10_000 and cs.bad_crc > 10_000 and cs.garbage_bytes > 0
    assert st.setpoints_rejected > 10_000 and st.commands_unknown > 10_000 and st.handler_errors == 0
    # and a 50 Hz stream after all that still climbs
    z0 = rig.vehicle.state.pos_m[2]
    rig.run(1.5, setpoint=(0x20, 0.0, 0.0, HOVER_PERCENT * 1.25, 0.0))
    assert rig.vehicle.fc.state is FcState.OFFBOARD and rig.vehicle.state.pos_m[2] > z0 + 0.3


def test_hil_fc_answers_the_open_protocol_on_a_pty_and_hil_decode_prints_its_capture(tmp_path):
    import json
    import subprocess
    import sys
    import time

    from hil.link import SerialTransport

    capture = tmp_path / "fc.tlog"
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil.cli", "fc", "--protocol", "dji-open", "--rc-mode", "A", "--gap", "none",
         "--mocap-link", "none", "--duration", "20", "--tlog", str(capture)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        first = json.loads(proc.stdout.readline())
        assert first["protocol"] == "dji_open"
        link = SerialTransport(first["command_link"], 921600)
        client = Client(link)
        deadline = time.monotonic() + 10.0
        seq = client.command(0x00, 0x01, ACTIVATION)
        while seq not in client.acks and time.monotonic() < deadline:
            client.read()
            time.sleep(0.01)
        assert client.code(seq) == 0x0000
        seq = client.command(0x01, 0x00, b"\x01")
        while (seq not in client.acks or not client.flight_data) and time.monotonic() < deadline:
            client.read()
            time.sleep(0.01)
        assert client.code(seq) == 0x0000  # the RC is in A mode: not in F mode
        assert client.latest(9, "<6h")[4] == 0  # the RC item's mode channel: A
        link.close()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["server"]["commands_denied"] == 1 and summary["link"]["bad_crc"] == 0
    decoded = subprocess.run([sys.executable, "-m", "hil.cli", "decode", str(capture)], capture_output=True,
                             text=True, check=True).stdout.splitlines()
    assert "0x00 0x01 activation" in decoded[0] and "ACK 0x0000" in decoded[1]
    assert any("0x01 0x00 control authority: 01" in line for line in decoded)
    assert any("flight data: time, quaternion" in line for line in decoded)


def test_the_fc_parameters_apply_over_the_open_protocol_but_mavlink_telemetry_rates_do_not():
    rig = Rig()
    params = rig.server.params
    assert params.set("COM_OF_LOSS_T", 0.5) == pytest.approx(0.5)
    assert rig.vehicle.fc.config.failsafe_timeout_s == pytest.approx(0.5)
    before = params.get("N3_RATE_ATT")  # read as its default: no MAVLink telemetry here
    with pytest.raises(ParamError, match="no MAVLink telemetry"):
        params.set("N3_RATE_ATT", 10.0)
    assert params.get("N3_RATE_ATT") == before
    assert len(list(params.items())) == len(PARAMS)  # the whole table still reads


def test_hil_fc_over_the_open_protocol_refuses_telemetry_rates_and_an_esc_bus(tmp_path):
    rates = tmp_path / "rates.params"
    rates.write_text("N3_RATE_ATT 10\n")
    for extra, words in ((["--params", str(rates)], "N3_RATE_ATT"), (["--esc-bus", "sim"], "--esc-bus")):
        p = subprocess.run([sys.executable, "-m", "hil.cli", "fc", "--protocol", "dji-open", "--gap", "none",
                            "--mocap-link", "none", "--duration", "0.2", *extra],
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 2 and words in p.stderr, p.stderr
