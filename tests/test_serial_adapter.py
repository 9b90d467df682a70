"""The path a real TX2 takes: `hil fc` on a serial device at 921600 baud, the onboard side on the other
end of a USB-serial cable. socat's pair of linked pseudo-terminals stands in for the cable; killing
socat unplugs it (both ends hang up), starting it again with the same names plugs it back in.

Unplugged, the FC sees its setpoints stop and fails safe (hover); plugged back in, its side of the link
opens the device again by itself and the two ends talk again: the FC's heartbeat reaches the client,
the client's commands reach the FC."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

from test_fc_mavsdk import HOVER, start_fc, stop_fc, wait_for

from hil.link import SerialTransport, WallClock
from hil.link.mavlink import PX4_MAIN_OFFBOARD, MavlinkCodec, mav, px4_custom_mode, quat_from_euler

SOCAT = shutil.which("socat")


def plug(folder: Path) -> subprocess.Popen:
    """The cable: two linked ptys, ``folder/fc`` (the emulator's end) and ``folder/tx2``."""
    assert SOCAT, "socat is needed (make setup installs it: apt-get install socat)"
    for end in ("fc", "tx2"):
        (folder / end).unlink(missing_ok=True)
    ends = [f"pty,raw,echo=0,link={folder / end}" for end in ("fc", "tx2")]
    proc = subprocess.Popen([SOCAT, *ends], stderr=subprocess.DEVNULL)
    wait_for(lambda: (folder / "fc").exists() and (folder / "tx2").exists(), 5.0, "socat's ptys")
    return proc


def unplug(cable: subprocess.Popen) -> None:
    cable.terminate()
    cable.wait(5)


def offboard_stream(codec: MavlinkCodec, seconds: float) -> bool:
    """Arm, stream attitude setpoints at 50 Hz, switch to OFFBOARD; True once the FC's heartbeat says so."""
    codec.send(codec.mav.command_long_encode(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    q = list(quat_from_euler(0.0, 0.0, 0.0))
    offboard, end = False, time.monotonic() + seconds
    while time.monotonic() < end:
        codec.send(codec.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, 1.05 * HOVER))
        if time.monotonic() > end - seconds + 0.3:
            codec.send(codec.mav.command_long_encode(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 129, PX4_MAIN_OFFBOARD,
                                                     0, 0, 0, 0, 0))
        for m in codec.receive(0.02):
            if m.get_type() == "HEARTBEAT":
                offboard = offboard or m.custom_mode == px4_custom_mode(PX4_MAIN_OFFBOARD)
    return offboard


def heartbeats(codec: MavlinkCodec, seconds: float) -> list:
    """The FC's heartbeats heard within ``seconds``, our own sent at 10 Hz meanwhile."""
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        hb = codec.mav.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        codec.send(hb)
        out += [m for m in codec.receive(0.1) if m.get_type() == "HEARTBEAT"]
    return out


def test_a_usb_serial_cable_unplugged_and_plugged_back_in(tmp_path):
    cable = plug(tmp_path)
    proc, path = start_fc("--link", f"serial:{tmp_path / 'fc'}:921600", "--mocap-link", "none",
                          "--failsafe-timeout", "0.5")
    link = None
    try:
        assert path == str(tmp_path / "fc")
        link = SerialTransport(str(tmp_path / "tx2"), 921600)
        codec = MavlinkCodec(link, WallClock(), 255, 190)
        assert offboard_stream(codec, 1.5), "never reached OFFBOARD over the cable"
        unplug(cable)  # mid-flight: the setpoints stop reaching the FC
        time.sleep(1.5)  # the FC fails safe after 0.5 s, and keeps running meanwhile
        assert proc.poll() is None, "hil fc ended when its cable was unplugged"
        link.close()
        cable = plug(tmp_path)  # the same device names again
        link = SerialTransport(str(tmp_path / "tx2"), 921600)
        codec = MavlinkCodec(link, WallClock(), 255, 190)
        heard = heartbeats(codec, 1.5)
        assert heard, "no heartbeat from the FC after the cable came back"
        assert heard[-1].system_status == mav.MAV_STATE_CRITICAL  # still in its failsafe, and says so
        assert heard[-1].custom_mode != px4_custom_mode(PX4_MAIN_OFFBOARD)
        assert offboard_stream(codec, 1.5), "the client could not take control again after the replug"
    finally:
        if link is not None:
            link.close()
        summary = stop_fc(proc)
        unplug(cable)
    states = [e["to"] for e in summary["events"]]
    assert "failsafe_hover" in states and states.index("failsafe_hover") > states.index("offboard")
    assert states[-1] == "offboard"  # taken back after the replug
    assert summary["realtime"]["serial"] == {"disconnects": 1, "reconnects": 1}
    gap = summary["realtime"]["setpoints_at_fc"]["max_gap_ms"]
    assert gap > 1500  # the unplugged interval, as the FC's wire saw it
