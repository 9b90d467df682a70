"""`hil fc`'s parameters with real clients in real time: MAVProxy (from PyPI, headless) downloads the
whole table over UDP and sets COM_OF_LOSS_T, a pymavlink client behind MAVProxy's output sees the bad
sets refused and the failsafe fire at the new timeout, `--params FILE` over a pty, MAVProxy on a signed
FC, and a PARAM_SET storm over UDP with every loss counted."""

from __future__ import annotations

import hashlib
import shutil
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_fc_mavsdk import HOVER, free_udp_port, start_fc, stop_fc, wait_for
from test_fc_signing import Station, loopback_udpout, packer

from emulator.params import PARAMS, read_param_file
from hil.link import SerialTransport, WallClock
from hil.link.mavlink import PX4_MAIN_OFFBOARD, MavlinkCodec, decode_frame, mav, quat_from_euler
from hil.link.tlog import read_tlog

MAVPROXY = shutil.which("mavproxy.py") or str(Path(sys.executable).parent / "mavproxy.py")


class Lines:
    """A process's stdout lines, collected by a thread."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._t.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            self.lines.append(line.rstrip())

    def seen(self, text: str) -> bool:
        return any(text in line for line in self.lines)


def stop_gcs(gcs: subprocess.Popen) -> None:
    gcs.terminate()
    try:
        gcs.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        gcs.kill()


def test_mavproxy_downloads_the_table_sets_the_timeout_and_the_failsafe_follows(tmp_path: Path):
    tlog = tmp_path / "fc.tlog"
    # MAVProxy listens on the loopback and the FC sends to it (a pymavlink udpout socket would be bound
    # to every interface)
    port, out_port = free_udp_port(), free_udp_port()
    proc, _ = start_fc("--link", f"udpout:127.0.0.1:{port}", "--tlog", str(tlog), "--mocap-link", "none")
    gcs = subprocess.Popen(
        [sys.executable, MAVPROXY, f"--master=udpin:127.0.0.1:{port}", f"--out=udpin:127.0.0.1:{out_port}",
         "--non-interactive", f"--state-basedir={tmp_path}",
         "--cmd=repeat add 1 param set COM_OF_LOSS_T 0.5"],  # (each second: it waits for the table)
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    out = Lines(gcs)
    codec = None
    try:
        t0 = time.monotonic()
        wait_for(lambda: out.seen("Detected vehicle"), 15.0, "MAVProxy to see the FC")
        wait_for(lambda: out.seen(f"Received {len(PARAMS)} parameters"), 10.0, "the parameter download")
        download_s = time.monotonic() - t0
        # a pymavlink client on MAVProxy's output, as a second tool beside a ground station
        client = loopback_udpout("127.0.0.1", out_port, 254)
        codec = client

        def recv_all(seconds: float) -> list:
            got, end = [], time.monotonic() + seconds
            while time.monotonic() < end:
                m = client.recv_match(blocking=True, timeout=0.05)
                if m is not None:
                    got.append(m)
            return got

        def value_of(name: str, seconds: float = 3.0):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                client.mav.param_request_read_send(1, 1, name.encode(), -1)
                for m in recv_all(0.3):
                    if m.get_type() == "PARAM_VALUE" and m.param_id == name:
                        return m.param_value
            raise AssertionError(f"no PARAM_VALUE {name}")

        client.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        wait_for(lambda: value_of("COM_OF_LOSS_T") == 0.5, 10.0, "MAVProxy's set of COM_OF_LOSS_T")
        # bad sets are refused with the value in force echoed
        client.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 99.0, mav.MAV_PARAM_TYPE_REAL32)
        got = recv_all(0.5)
        echoed = [m.param_value for m in got
                  if m.get_type() == "PARAM_VALUE" and m.param_id == "COM_OF_LOSS_T"]
        assert echoed and echoed[0] == 0.5
        assert any(m.get_type() == "STATUSTEXT" and "outside" in m.text for m in got)
        # arm, stream, offboard, stop: the failsafe at the new timeout
        q = list(quat_from_euler(0.0, 0.0, 0.0))
        client.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        end = time.monotonic() + 1.2
        requested = False
        while time.monotonic() < end:
            client.mav.set_attitude_target_send(0, 1, 1, 7, q, 0, 0, 0, 1.1 * HOVER)
            if not requested and time.monotonic() > end - 0.9:
                client.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 129, PX4_MAIN_OFFBOARD,
                                             0, 0, 0, 0, 0)
                requested = True
            recv_all(0.02)
        got = recv_all(2.0)
        assert any(m.get_type() == "STATUSTEXT" and "Failsafe" in m.text for m in got)
    finally:
        stop_gcs(gcs)
        if codec is not None:
            codec.close()
        summary = stop_fc(proc)
    assert download_s < 10.0
    assert summary["server"]["ftp_nak"] >= 1  # MAVProxy asked by FTP first, and fell back
    # the whole table MAVProxy saved, with the value it set
    saved = read_param_file(tmp_path / "mav.parm")
    assert set(saved) == {p.name for p in PARAMS}
    # the failsafe, in the FC's own time (its .tlog): 0.5 s (+ 0.1 s) after the last setpoint
    frames = [(t / 1e6, decode_frame(f)) for t, f in read_tlog(tlog)]
    text_s = next(t for t, m in frames if m.get_type() == "STATUSTEXT" and "Failsafe" in m.text)
    last_sp_s = max(t for t, m in frames if m.get_type() == "SET_ATTITUDE_TARGET" and t < text_s)
    assert 0.5 <= text_s - last_sp_s <= 0.6
    assert [e["to"] for e in summary["events"]][-2:] == ["offboard", "failsafe_hover"]


def test_hil_fc_params_file_loads_and_is_written_back_over_a_pty(tmp_path: Path):
    path = tmp_path / "vehicle.params"
    path.write_text("COM_OF_LOSS_T 0.7\nN3_RATE_ATT 5\n")
    proc, dev = start_fc("--params", str(path), "--mocap-link", "none")
    link = SerialTransport(dev, 921600)
    codec = MavlinkCodec(link, WallClock(), 255, 190)
    try:
        codec.send(codec.mav.param_request_read_encode(1, 1, b"COM_OF_LOSS_T", -1))
        got = wait_for(lambda: [m for m in codec.receive(0.1) if m.get_type() == "PARAM_VALUE"
                                and m.param_id == "COM_OF_LOSS_T"], 5.0, "COM_OF_LOSS_T")
        assert got[0].param_value == pytest.approx(0.7)
        codec.send(codec.mav.param_set_encode(1, 1, b"MPC_LAND_SPEED", 0.4, mav.MAV_PARAM_TYPE_REAL32))
        codec.send(codec.mav.command_long_encode(1, 1, mav.MAV_CMD_PREFLIGHT_STORAGE, 0, 1, 0, 0, 0, 0, 0, 0))
        acks = wait_for(lambda: [m for m in codec.receive(0.1) if m.get_type() == "COMMAND_ACK"], 5.0, "ack")
        assert acks[0].result == mav.MAV_RESULT_ACCEPTED
    finally:
        link.close()
        stop_fc(proc)
    saved = read_param_file(path)
    assert saved["MPC_LAND_SPEED"] == pytest.approx(0.4) and saved["N3_RATE_ATT"] == 5.0
    assert len(saved) == len(PARAMS)


def test_hil_fc_refuses_a_bad_params_file(tmp_path: Path, capsys):
    from hil.cli import main

    path = tmp_path / "bad.params"
    path.write_text("COM_OF_LOSS_T 120\n")
    assert main(["fc", "--params", str(path)]) == 2
    assert "bad.params:1: COM_OF_LOSS_T: 120 outside 0.1..60 s" in capsys.readouterr().err
    assert main(["fc", "--params", str(tmp_path / "no" / "such" / "fc.params")]) == 2
    assert "no such file, nor a folder to write it in" in capsys.readouterr().err
    # a file to be written later is fine, and said (a mistyped name is noticed)
    assert main(["fc", "--params", str(tmp_path / "new.params"), "--mocap-link", "none",
                 "--duration", "0.2"]) == 0
    assert "does not exist yet: the defaults, written there" in capsys.readouterr().err


def test_mavproxy_fetches_loads_and_sets_parameters_on_a_signed_fc(tmp_path: Path):
    """MAVProxy with `signing key PASSPHRASE` (the key is the passphrase's SHA-256) against `hil fc
    --signing-key`: the table downloads, `param load` of INT32 and REAL32 values (the range's edge among
    them) and `param set` are all taken, echoed with each parameter's own type."""


    tlog = tmp_path / "fc.tlog"
    key = hashlib.sha256(b"bench").hexdigest()
    port = free_udp_port()  # (MAVProxy listens on the loopback, the FC sends to it: see above)
    proc, _ = start_fc("--link", f"udpout:127.0.0.1:{port}", "--signing-key", key, "--tlog", str(tlog),
                       "--mocap-link", "none")
    (tmp_path / "load.parm").write_text("COM_OBL_RC_ACT 4\nN3_ESC_FS_ACT 2\nCOM_OF_LOSS_T 0.5\n"
                                        "MPC_THR_HOVER 0.8\n")
    gcs = subprocess.Popen(
        [sys.executable, MAVPROXY, f"--master=udpin:127.0.0.1:{port}", f"--state-basedir={tmp_path}",
         "--cmd=signing key bench"],
        cwd=tmp_path, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    out = Lines(gcs)

    def command(text: str) -> None:
        gcs.stdin.write(text + "\n")
        gcs.stdin.flush()

    try:
        wait_for(lambda: out.seen(f"Received {len(PARAMS)} parameters"), 20.0, "the parameter download")
        command("param load load.parm")
        wait_for(lambda: out.seen("Loaded 4 parameters from load.parm (changed 4)"), 15.0, "param load")
        command("param set N3_FS_HOVER_T 7")

        def shown() -> bool:  # MAVProxy's table takes the value the FC echoes
            command("param show N3_FS_HOVER_T")
            time.sleep(0.3)
            return any(line.split()[-2:] == ["N3_FS_HOVER_T", "7.0"] for line in out.lines)

        wait_for(shown, 10.0, "the set echoed")
    finally:
        stop_gcs(gcs)
        summary = stop_fc(proc)
    assert not out.seen("timeout setting")
    assert summary["server"]["params_set"] == 5 and summary["server"]["params_refused"] == 0
    assert summary["link"]["unsigned_refused"] == summary["link"]["bad_signature"] == 0
    echoed = {m.param_id: m for _, m in _tlog_messages(tlog) if m.get_type() == "PARAM_VALUE"}
    ints = {n: struct.unpack("<i", struct.pack("<f", echoed[n].param_value))[0]
            for n in ("COM_OBL_RC_ACT", "N3_ESC_FS_ACT")}
    assert ints == {"COM_OBL_RC_ACT": 4, "N3_ESC_FS_ACT": 2}
    assert {echoed[n].param_type for n in ints} == {mav.MAV_PARAM_TYPE_INT32}
    assert echoed["COM_OF_LOSS_T"].param_value == 0.5
    assert echoed["MPC_THR_HOVER"].param_value == pytest.approx(0.8, rel=1e-7)


def _tlog_messages(path: Path) -> list:
    """(time, message) of every frame a .tlog holds so far (signed frames decoded without judging)."""
    parser = mav.MAVLink(None)
    return [(t, parser.decode(bytearray(f))) for t, f in read_tlog(path)]


def test_a_param_set_storm_over_udp_loses_nothing_uncounted():
    """2,000 PARAM_SETs at 1,000/s into `hil fc` over UDP, then 2,000 at once: each one is set, or counted
    where it was lost (the socket's kernel drops)."""
    proc, endpoint = start_fc("--link", "udp:127.0.0.1:0", "--mocap-link", "none")
    gcs = None
    sent = 0
    try:
        gcs = Station(endpoint)
        m = packer(None)
        start = time.monotonic()
        for i in range(2000):
            gcs.write(bytes(m.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5 + (i % 8) / 8,
                                               mav.MAV_PARAM_TYPE_REAL32).pack(m)))
            sent += 1
            lag = start + sent / 1000.0 - time.monotonic()
            if lag > 0:
                time.sleep(lag)
        burst = m.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5, mav.MAV_PARAM_TYPE_REAL32)
        for _ in range(2000):  # then as fast as they go: more than the socket holds
            gcs.write(bytes(burst.pack(m)))
            sent += 1
        gcs.drain(1.0)
    finally:
        if gcs is not None:
            gcs.conn.close()
        summary = stop_fc(proc)
    assert summary["server"]["params_set"] + summary["transport"]["datagrams_lost_in"] == sent
    assert summary["link"]["frames_received"] == summary["server"]["params_set"]
