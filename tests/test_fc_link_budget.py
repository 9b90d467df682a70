"""`hil fc --link serial:DEV:BAUD` keeps its telemetry within the line: over a socat pty pair (the radio's
stand-in) the reader gets no more than the baud carries, the heartbeat at 1 Hz, parameter answers within
100 ms of line queue, MAVProxy's whole table while the streams run, and a rate the line cannot carry is
capped and said so; the same for DJI's OPEN protocol at 230400 (its broadcast and subscription pushes
within the line, the command ACKs first, a broadcast rate it cannot carry capped and said)."""

from __future__ import annotations

import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from test_fc_mavsdk import start_fc, stop_fc, wait_for
from test_fc_params_clients import MAVPROXY, Lines, stop_gcs

from emulator.params import PARAMS
from emulator.profile import load_profile
from emulator.servers.dji_open_server import DjiOpenServer, DjiServerConfig
from emulator.vehicle import EmulatedVehicle
from hil.link import SerialTransport, SimClock, WallClock
from hil.link import dji_open as dj
from hil.link.channel import BITS_PER_BYTE
from hil.link.dji_open import OpenCodec
from hil.link.mavlink import MavlinkCodec, mav
from hil.link.uart import UartTransport

ANSWER_LIMIT_S = 0.1  # a PARAM_SET's answer: line queue in front of it plus its own bytes


@contextmanager
def pty_pair(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """Two linked ptys (socat), as a radio pair would be."""
    a, b = str(tmp_path / "fc-end"), str(tmp_path / "gcs-end")
    proc = subprocess.Popen(["socat", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: Path(a).exists() and Path(b).exists(), 5.0, "socat's ptys")
        yield a, b
    finally:
        proc.terminate()
        proc.wait(timeout=5)


def heartbeat_in(msgs: list) -> bool:
    return any(m.get_type() == "HEARTBEAT" for m in msgs)


def answer_time_s(budget: dict, baud: int) -> float:
    """The longest an answer took on the line: the queue in front of it, then a PARAM_VALUE's bytes."""
    return budget["answer_wait_max_s"] + 37 * BITS_PER_BYTE / baud


@pytest.mark.parametrize("baud", [57600, 115200, 921600])
def test_telemetry_fits_the_line_with_heartbeat_and_answers_through(tmp_path: Path, baud: int):
    with pty_pair(tmp_path) as (fc_end, gcs_end):
        proc, _ = start_fc("--link", f"serial:{fc_end}:{baud}", "--mocap-link", "none")
        link = SerialTransport(gcs_end, baud)
        codec = MavlinkCodec(link, WallClock(), 255, 190)
        try:
            wait_for(lambda: heartbeat_in(codec.receive(0.1)), 20.0, "a heartbeat")
            while codec.receive(0.0):  # (what waited in the pty before the window opens is not counted)
                pass
            start, got0, beats, answers, sets = time.monotonic(), link.stats.bytes_received, 0, 0, 0
            while time.monotonic() - start < 4.0:
                for m in codec.receive(0.05):
                    beats += m.get_type() == "HEARTBEAT"
                    answers += m.get_type() == "PARAM_VALUE"
                since = time.monotonic() - start
                if sets < since / 0.5 and since < 3.5:  # a PARAM_SET every 0.5 s
                    sets += 1
                    codec.send(codec.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5 + sets % 2 / 4,
                                                          mav.MAV_PARAM_TYPE_REAL32))
            elapsed = time.monotonic() - start
            bytes_s = (link.stats.bytes_received - got0) / elapsed
        finally:
            link.close()
            summary = stop_fc(proc)
    budget = summary["link_budget"]
    assert bytes_s <= 1.05 * baud / BITS_PER_BYTE  # (5 %: the window's edges)
    assert budget["bytes_written_per_s"] <= baud / BITS_PER_BYTE
    assert 3 <= beats <= 5 and answers >= 7 and summary["server"]["params_set"] == sets
    assert budget["answers_dropped"] == 0 and answer_time_s(budget, baud) <= ANSWER_LIMIT_S
    if baud == 57600:  # the default streams (about 9,700 bytes/s) scaled to half the line
        assert budget["stream_budget_bytes_s"] == 2880.0 and bytes_s <= 0.6 * baud / BITS_PER_BYTE


def test_mavproxy_fetches_the_table_at_57600_while_the_streams_run(tmp_path: Path):
    with pty_pair(tmp_path) as (fc_end, gcs_end):
        proc, _ = start_fc("--link", f"serial:{fc_end}:57600", "--mocap-link", "none")
        gcs = subprocess.Popen(
            [sys.executable, MAVPROXY, f"--master={gcs_end},57600", "--non-interactive",
             f"--state-basedir={tmp_path}", "--cmd=repeat add 1 param set COM_OF_LOSS_T 0.5"],
            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        out = Lines(gcs)
        try:
            wait_for(lambda: out.seen(f"Received {len(PARAMS)} parameters"), 30.0, "the parameter download")
            time.sleep(2.0)  # a few sets of COM_OF_LOSS_T, answered
        finally:
            stop_gcs(gcs)
            summary = stop_fc(proc)
    budget = summary["link_budget"]
    assert summary["server"]["params_set"] >= 1 and budget["answers_dropped"] == 0
    assert answer_time_s(budget, 57600) <= ANSWER_LIMIT_S
    assert budget["bytes_written_per_s"] <= 5760


def test_a_rate_the_line_cannot_carry_is_capped_and_said(tmp_path: Path):
    with pty_pair(tmp_path) as (fc_end, gcs_end):
        proc, _ = start_fc("--link", f"serial:{fc_end}:57600", "--mocap-link", "none")
        link = SerialTransport(gcs_end, 57600)
        codec = MavlinkCodec(link, WallClock(), 255, 190)
        try:
            wait_for(lambda: heartbeat_in(codec.receive(0.1)), 20.0, "a heartbeat")
            codec.send(codec.mav.command_long_encode(1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                     mav.MAVLINK_MSG_ID_HIGHRES_IMU, 5000, 0, 0, 0, 0, 0))
            got: list = []
            wait_for(lambda: got.extend(codec.receive(0.1)) or (
                any(m.get_type() == "STATUSTEXT" and "capped" in m.text for m in got)
                and any(m.get_type() == "COMMAND_ACK" for m in got)), 5.0, "the cap said, and the ACK")
        finally:
            link.close()
            summary = stop_fc(proc)
    [ack] = [m for m in got if m.get_type() == "COMMAND_ACK"]
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    [text] = [m.text for m in got if m.get_type() == "STATUSTEXT" and "capped" in m.text]
    assert text.startswith("HIGHRES_IMU 200Hz capped")
    [cap] = summary["link_budget"]["caps"]
    assert cap["message"] == "HIGHRES_IMU" and cap["requested_hz"] == 200 and cap["granted_hz"] < 200
    assert summary["link_budget"]["rates_capped"] == 1


# --- DJI's OPEN protocol at 230400 (an N3's API UART): broadcast and subscription within the line ------
OPEN_BAUD = 230400
#: a package of 100 Hz topics (91 bytes with its time stamp): 11 kB/s asked, beside the default
#: broadcast's 8 kB/s, where the line's streams get 11.5 kB/s
FAST_TOPICS = ("quaternion", "acceleration_ground", "acceleration_body", "velocity", "angular_rate_fusioned",
               "altitude_fusioned", "altitude_barometer", "height_fusion", "compass")
ACTIVATION = struct.pack("<III", 1, 2, 0x0303082F) + b"0" * 32


@contextmanager
def open_fc(tmp_path: Path) -> Iterator[tuple[OpenCodec, SerialTransport, dict]]:
    """`hil fc --protocol dji-open` at `OPEN_BAUD` over a pty pair, activated: the onboard end's codec and
    line, and a dict that holds the FC's summary and stderr once it has stopped."""
    out: dict = {}
    err = tmp_path / "fc-stderr.txt"
    with pty_pair(tmp_path) as (fc_end, ob_end), err.open("w") as sink:
        proc = subprocess.Popen(
            [sys.executable, "-m", "hil.cli", "fc", "--duration", "40", "--protocol", "dji-open",
             "--link", f"serial:{fc_end}:{OPEN_BAUD}", "--mocap-link", "none"],
            stdout=subprocess.PIPE, stderr=sink, text=True)
        link = SerialTransport(ob_end, OPEN_BAUD)
        codec = OpenCodec(link, WallClock())
        try:
            assert proc.stdout.readline(), "hil fc printed no endpoint line"
            assert ask(codec, dj.SET_ACTIVATION, dj.CMD_ACTIVATE, ACTIVATION) == dj.ack_code(dj.ACK_SUCCESS)
            yield codec, link, out
        finally:
            link.close()
            out["summary"] = stop_fc(proc)
    out["stderr"] = err.read_text()


def ask(codec: OpenCodec, cmd_set: int, cmd_id: int, payload: bytes) -> bytes:
    """Send a reliable command and wait for its ACK value (other frames read and dropped)."""
    codec.send_command(cmd_set, cmd_id, payload)
    wait_for(lambda: (codec.receive(0.05), (cmd_set, cmd_id) in codec.acks)[1], 10.0,
             f"the ACK of {cmd_set:#04x} {cmd_id:#04x}")
    return codec.acks[(cmd_set, cmd_id)][0]


def stream_window(codec: OpenCodec, link: SerialTransport, seconds: float, every: float = 0.0,
                  act=None) -> tuple[float, dict[bytes, int]]:
    """Read for ``seconds`` from an empty pty (calling ``act(n)`` every ``every`` s): the bytes/s read
    and the frames by command (set, id)."""
    while codec.receive(0.0):
        pass
    start, got0, frames, n = time.monotonic(), link.stats.bytes_received, {}, 0
    while (since := time.monotonic() - start) < seconds:
        for f in codec.receive(0.05):
            frames[f.data[:2]] = frames.get(f.data[:2], 0) + 1
        if every and n < since / every and since < seconds - 0.5:
            n += 1
            act(n)
    return (link.stats.bytes_received - got0) / (time.monotonic() - start), frames


def test_open_pushes_fit_the_line_and_commands_are_answered_at_once(tmp_path: Path):
    uids = [dj.TOPIC_UID[name] for name in FAST_TOPICS]
    package = dj.SUB_PACKAGE_HEAD.pack(0, 100, 1, len(uids)) + struct.pack(f"<{len(uids)}I", *uids)
    sent: list[tuple[int, int]] = []

    def command(n: int) -> None:  # obtain control, then arm and disarm in turn
        key = (dj.SET_CONTROL, dj.CMD_CONTROL_AUTHORITY) if n % 2 else (dj.SET_CONTROL, dj.CMD_ARM)
        codec.send_command(*key, b"\x01" if n % 2 else bytes((n // 2 % 2,)))
        sent.append(key)

    with open_fc(tmp_path) as (codec, link, out):
        version = struct.pack("<I", dj.SUB_DB_VERSION)
        assert ask(codec, dj.SET_SUBSCRIBE, dj.CMD_SUB_VERSION, version) == b"\0"
        assert ask(codec, dj.SET_SUBSCRIBE, dj.CMD_SUB_ADD, package) == b"\0"  # (granted less: below)
        acks0 = codec.stats.acks_received
        bytes_s, frames = stream_window(codec, link, 4.0, 0.25, command)
    budget = out["summary"]["link_budget"]
    line_bytes_s = OPEN_BAUD / BITS_PER_BYTE
    assert bytes_s <= 1.05 * line_bytes_s and budget["bytes_written_per_s"] <= line_bytes_s
    assert bytes_s <= 0.6 * line_bytes_s  # the streams (19 kB/s asked) scaled to half the line, ACKs aside
    assert frames[b"\x02\x00"] >= 4 * 20 and frames[b"\x02\x05"] >= 4 * 20  # both still flow, scaled alike
    assert len(sent) >= 10 and codec.stats.acks_received - acks0 == len(sent)  # every command answered
    assert codec.acks[(dj.SET_CONTROL, dj.CMD_CONTROL_AUTHORITY)][0] == dj.ack_code(dj.CONTROL_OBTAINED)
    assert codec.acks[(dj.SET_CONTROL, dj.CMD_ARM)][0] == dj.ack_code(dj.ARM_SUCCESS)
    # an ACK waited behind at most this much of the line's queue, then took its 18 bytes
    assert budget["answers_dropped"] == 0
    assert budget["answer_wait_max_s"] + 18 * BITS_PER_BYTE / OPEN_BAUD <= ANSWER_LIMIT_S
    [cap] = budget["caps"]
    assert cap["message"] == "package 0" and cap["requested_hz"] == 100 and 20 < cap["granted_hz"] < 100
    assert "package 0 100Hz capped" in out["stderr"]


def test_open_broadcast_rates_the_line_cannot_carry_are_capped_and_said(tmp_path: Path):
    with open_fc(tmp_path) as (codec, link, out):  # every item at 100 Hz: 30 kB/s, more than the line
        every_item_100_hz = bytes([4] * 14 + [0, 0])
        assert ask(codec, dj.SET_ACTIVATION, dj.CMD_BROADCAST_FREQ, every_item_100_hz) == dj.ack_code(0)
        bytes_s, frames = stream_window(codec, link, 3.0)
    budget = out["summary"]["link_budget"]
    line_bytes_s = OPEN_BAUD / BITS_PER_BYTE
    assert bytes_s <= 1.05 * line_bytes_s and budget["bytes_written_per_s"] <= line_bytes_s
    [cap] = budget["caps"]  # one line for the items asked at one rate and granted one
    names = ",".join(name for name, _ in dj.BROADCAST_ITEMS)
    assert cap["message"] == f"broadcast {names}"
    assert cap["requested_hz"] == 100 and cap["granted_hz"] < 100 and budget["rates_capped"] == 1
    assert frames[b"\x02\x00"] >= 3 * 0.9 * cap["granted_hz"]  # pushed at the rate granted
    assert "100Hz capped" in out["stderr"]


def test_open_broadcast_gets_its_rates_back_when_a_package_goes():
    """In simulated time over an in-process serial cable: a package squeezes the broadcast; removed, the
    broadcast is pushed at the rates asked again, and the line's bytes stay within the streams' half."""
    clock = SimClock()
    fc_end, ob_end = UartTransport.pair(OPEN_BAUD, clock)
    server = DjiOpenServer(EmulatedVehicle(load_profile("n3_tx2")), OpenCodec(fc_end, clock),
                           DjiServerConfig(link_baud=OPEN_BAUD))
    codec = OpenCodec(ob_end, clock)
    uids = [dj.TOPIC_UID[name] for name in FAST_TOPICS]
    steps = iter(range(10**6))

    def run(seconds: float) -> dict[bytes, int]:
        """Step the FC at 1 kHz for ``seconds``: the frames read by command (set, id)."""
        frames: dict[bytes, int] = {}
        for _ in range(round(seconds * 1000)):
            now = next(steps) * 0.001
            clock.advance_to(now)
            server.poll(now)
            for f in codec.receive(0.0):
                frames[f.data[:2]] = frames.get(f.data[:2], 0) + 1
        return frames

    codec.send_command(dj.SET_ACTIVATION, dj.CMD_ACTIVATE, ACTIVATION)
    codec.send_command(dj.SET_SUBSCRIBE, dj.CMD_SUB_ADD, dj.SUB_PACKAGE_HEAD.pack(0, 100, 1, len(uids))
                       + struct.pack(f"<{len(uids)}I", *uids))
    run(1.0)
    written0 = fc_end.uart.bytes_released
    squeezed = run(2.0)
    assert fc_end.uart.bytes_released - written0 <= 2.0 * OPEN_BAUD / BITS_PER_BYTE / 2
    assert 2.0 * 20 <= squeezed[b"\x02\x00"] < 2.0 * 40  # the 50 Hz items scaled down with the package
    codec.send_command(dj.SET_SUBSCRIBE, dj.CMD_SUB_REMOVE, b"\x00")
    run(0.1)
    alone = run(2.0)
    assert b"\x02\x05" not in alone
    assert alone[b"\x02\x00"] == 2.0 * 50  # back at 50 Hz, one frame each (the 10 and 1 Hz items ride along)
    assert codec.acks[(dj.SET_SUBSCRIBE, dj.CMD_SUB_REMOVE)][0] == b"\0"
