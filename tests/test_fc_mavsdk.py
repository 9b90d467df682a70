"""`hil fc` in real time, driven by real clients: MAVSDK over a pseudo-terminal and over UDP (with a
.tlog that mavlogdump reads), and a pymavlink client that stops its setpoints to see the failsafe."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import time
from pathlib import Path

from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action import Action
from mavsdk.plugins.offboard import Attitude, Offboard
from mavsdk.plugins.telemetry import FlightMode, Telemetry

from emulator.profile import GRAVITY_M_S2, load_profile
from hil.link import SerialTransport, WallClock
from hil.link.mavlink import PX4_MAIN_OFFBOARD, MavlinkCodec, mav, px4_custom_mode, quat_from_euler

PROFILE = load_profile("n3_tx2")
HOVER = PROFILE.mass_kg * GRAVITY_M_S2 / PROFILE.n3_full_thrust_n


def start_fc(*args: str) -> tuple[subprocess.Popen, str]:
    """Start `hil fc` and return it with its command-link endpoint (from its first JSON line)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil.cli", "fc", "--duration", "40", *args],
        stdout=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline()
    assert line, "hil fc printed no endpoint line"
    return proc, json.loads(line)["command_link"]


def free_udp_port() -> int:
    """A UDP port free on the loopback now (s)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop_fc(proc: subprocess.Popen) -> dict:
    """SIGTERM, then the summary line; the process must exit cleanly."""
    proc.terminate()
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0
    return json.loads(out.strip().splitlines()[-1])


def wait_for(predicate, timeout_s: float, what: str):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def mavsdk_climb(url: str) -> None:
    """Connect, arm, offboard attitude with thrust above hover, and see the climb in MAVSDK's telemetry."""
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
    try:
        sdk.add_any_connection(url)
        system = sdk.first_autopilot(10.0)
        assert system is not None, f"MAVSDK found no autopilot on {url}"
        telemetry, action, offboard = Telemetry(system), Action(system), Offboard(system)
        start_down = wait_for(
            lambda: [d for d in [telemetry.position_velocity_ned().position.down_m] if math.isfinite(d)],
            5.0,
            "local position",
        )[0]
        action.arm()
        wait_for(telemetry.armed, 3.0, "armed in telemetry")
        offboard.set_attitude(Attitude(0.0, 0.0, 0.0, 1.4 * HOVER))
        time.sleep(0.3)  # PX4 rule: the stream must run before the switch
        offboard.start()
        wait_for(lambda: telemetry.flight_mode() == FlightMode.OFFBOARD, 3.0, "OFFBOARD flight mode")
        assert offboard.is_active()
        climbed = wait_for(
            lambda: start_down - telemetry.position_velocity_ned().position.down_m > 1.0, 5.0, "a 1 m climb"
        )
        assert climbed and telemetry.position_velocity_ned().velocity.down_m_s < -1.0
        offboard.stop()
        wait_for(lambda: telemetry.flight_mode() == FlightMode.HOLD, 3.0, "HOLD after offboard stop")
    finally:
        sdk.destroy()


def test_mavsdk_over_a_pty_arms_takes_offboard_and_climbs():
    proc, path = start_fc()
    try:
        assert path.startswith("/dev/")
        mavsdk_climb(f"serial://{path}:921600")
    finally:
        summary = stop_fc(proc)
    assert [e["to"] for e in summary["events"]][:3] == ["hold", "offboard", "hold"]
    assert summary["link"]["bad_crc"] == 0 and summary["server"]["setpoints_applied"] > 10


def test_mavsdk_over_udp_and_mavlogdump_reads_the_tlog(tmp_path: Path):
    tlog = tmp_path / "flight.tlog"
    # MAVSDK listens on the loopback and the FC sends to it (MAVSDK's own udpout socket would be bound
    # to every interface)
    port = free_udp_port()
    proc, endpoint = start_fc("--link", f"udpout:127.0.0.1:{port}", "--tlog", str(tlog))
    try:
        assert endpoint == f"udpout:127.0.0.1:{port}"
        mavsdk_climb(f"udpin://127.0.0.1:{port}")
    finally:
        stop_fc(proc)
    dump = subprocess.run(
        [
            sys.executable,
            str(Path(sys.executable).parent / "mavlogdump.py"),
            "--types",
            "SET_ATTITUDE_TARGET,HEARTBEAT,COMMAND_ACK",
            str(tlog),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    assert dump.count("SET_ATTITUDE_TARGET") > 10  # received by the FC
    assert "COMMAND_ACK" in dump and "HEARTBEAT" in dump  # sent by the FC


def test_failsafe_seen_in_heartbeat_and_statustext_within_timeout_plus_100ms():
    timeout_s = 0.5
    proc, path = start_fc("--failsafe-timeout", str(timeout_s))
    link = SerialTransport(path, 921600)
    codec = MavlinkCodec(link, WallClock(), 255, 190)
    try:
        codec.send(
            codec.mav.command_long_encode(
                1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mav.MAVLINK_MSG_ID_ATTITUDE, 4000, 0, 0, 0, 0, 0
            )
        )
        codec.send(
            codec.mav.command_long_encode(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        )
        q = list(quat_from_euler(0.0, 0.0, 0.0))
        last_att_ms = 0
        end = time.monotonic() + 1.5
        requested = offboard = False
        while time.monotonic() < end:  # stream 1.5 s at 50 Hz, offboard after 0.3 s
            codec.send(codec.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, 1.1 * HOVER))
            if not requested and time.monotonic() > end - 1.2:
                codec.send(
                    codec.mav.command_long_encode(
                        1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 129, PX4_MAIN_OFFBOARD, 0, 0, 0, 0, 0
                    )
                )
                requested = True
            for m in codec.receive(0.02):
                if m.get_type() == "ATTITUDE":
                    last_att_ms = m.time_boot_ms
                elif m.get_type() == "HEARTBEAT":
                    offboard = m.custom_mode == px4_custom_mode(PX4_MAIN_OFFBOARD)
        assert offboard, "never reached OFFBOARD"
        stop_ms = last_att_ms  # FC time when the stream stopped (at most one ATTITUDE period late)
        text_ms = hb_ms = None
        att_ms = stop_ms
        end = time.monotonic() + 3.0
        while time.monotonic() < end and (text_ms is None or hb_ms is None):
            for m in codec.receive(0.05):
                t = m.get_type()
                if t == "ATTITUDE":
                    att_ms = m.time_boot_ms
                elif t == "STATUSTEXT" and "Failsafe" in m.text and text_ms is None:
                    text_ms = att_ms
                elif t == "HEARTBEAT" and m.system_status == mav.MAV_STATE_CRITICAL and hb_ms is None:
                    hb_ms = att_ms
                    assert m.custom_mode != px4_custom_mode(PX4_MAIN_OFFBOARD)
        assert text_ms is not None and hb_ms is not None, "no failsafe seen"
        for seen_ms in (text_ms, hb_ms):  # FC time of the last ATTITUDE before each announcement
            assert timeout_s - 0.05 <= (seen_ms - stop_ms) / 1000 <= timeout_s + 0.1
    finally:
        link.close()
        summary = stop_fc(proc)
    assert [e["to"] for e in summary["events"]][-2:] == ["offboard", "failsafe_hover"]


def test_hil_fc_refuses_bad_options_with_a_message(capsys):
    from hil.cli import main

    assert main(["fc", "--link", "bogus:1"]) == 2
    assert "unknown link kind" in capsys.readouterr().err
    assert main(["fc", "--signing-key", "00ff"]) == 2
    assert "32 bytes" in capsys.readouterr().err
    assert main(["fc", "--failsafe-timeout", "-1"]) == 2
    assert "COM_OF_LOSS_T: -1 outside 0.1..60 s" in capsys.readouterr().err


def test_a_killed_fc_loses_at_most_the_last_100ms_of_its_tlog(tmp_path: Path):
    tlog = tmp_path / "killed.tlog"
    proc, _ = start_fc("--tlog", str(tlog))
    time.sleep(1.5)
    proc.kill()
    killed_at = time.time()
    proc.communicate(timeout=10)
    from hil.link.tlog import read_tlog

    frames = read_tlog(tlog)
    assert len(frames) > 100  # telemetry was recorded while it ran
    last_s = frames[-1][0] / 1e6
    # 100 ms flush interval, plus scheduling slack on a busy machine; an unflushed 8 KiB buffer would lose
    # most of a second of this ~10 kB/s telemetry
    assert killed_at - last_s < 0.3
