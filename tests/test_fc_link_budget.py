"""`hil fc --link serial:DEV:BAUD` keeps its telemetry within the line: over a socat pty pair (the radio's
stand-in) the reader gets no more than the baud carries, the heartbeat at 1 Hz, parameter answers within
100 ms of line queue, MAVProxy's whole table while the streams run, and a rate the line cannot carry is
capped and said so."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from test_fc_mavsdk import start_fc, stop_fc, wait_for
from test_fc_params_clients import MAVPROXY, Lines, stop_gcs

from emulator.fc.params import PARAMS
from hil.link import SerialTransport, WallClock
from hil.link.channel import BITS_PER_BYTE
from hil.link.mavlink import MavlinkCodec, mav

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
