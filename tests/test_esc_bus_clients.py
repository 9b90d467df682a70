"""`hil fc --esc-bus` with a separate process on the cross-process bus (dronecan's multicast driver):
its own dronecan node sees RawCommand, esc.Status and NodeStatus, and, standing in for ESC 3, receives
that ESC's commands and drives its motor."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_fc_mavsdk import start_fc, stop_fc

from emulator.fc import FcConfig, FlightController
from emulator.profile import load_profile
from hil.link import SerialTransport, WallClock
from hil.link.mavlink import MavlinkCodec, mav

PROFILE = load_profile("n3_tx2")
NODE = Path(__file__).with_name("esc_node_external.py")


def test_a_dronecan_node_in_another_process_replaces_esc_3_and_drives_its_motor():
    bus = f"mcast:{40 + os.getpid() % 200}"  # (a bus of its own: tests may run side by side)
    w_max = PROFILE.max_rotor_speed_rad_s
    ext = subprocess.Popen([sys.executable, str(NODE), bus, "23", "3", "60", str(w_max)],
                           stdout=subprocess.PIPE, text=True)
    assert ext.stdout.readline().strip() == "ready"
    proc, dev = start_fc("--esc-bus", bus, "--external-esc", "23", "--mocap-link", "none", "--gap", "none")
    link = SerialTransport(dev, 921600)
    codec = MavlinkCodec(link, WallClock(), 255, 190)
    try:
        arm = mav.MAV_CMD_COMPONENT_ARM_DISARM
        codec.send(codec.mav.command_long_encode(1, 1, arm, 0, 1, 0, 0, 0, 0, 0, 0))
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            codec.receive(0.05)
    finally:
        link.close()
        summary = stop_fc(proc)
        ext.terminate()
        seen = json.loads(ext.communicate(timeout=20)[0].strip().splitlines()[-1])
    esc = summary["esc_bus"]
    # the other process's node saw the FC's commands (at a good part of their 400 Hz: it is Python, on
    # a shared machine), the emulated ESCs' status and every node's NodeStatus
    assert seen["raw_commands"] > 0.25 * esc["commands_sent"] > 200
    assert all(seen["status_from"].get(str(i), 0) > 20 for i in range(3)) and "3" not in seen["status_from"]
    assert set(seen["node_status_from"]) >= {10, 20, 21, 22}
    # ... and, as ESC 3, drove its motor: armed on the ground, the FC idles every motor, and motor 3 runs
    # at the idle the outside node reported (its rpm back to a throttle, within an rpm's rounding)
    idle = FlightController(PROFILE, FcConfig()).gains.inner.idle_throttle
    assert esc["escs"][3]["external"] and esc["bus"]["external_in"] > 100
    assert esc["throttle"][:3] == pytest.approx([idle] * 3, abs=2e-4)
    assert esc["throttle"][3] == pytest.approx(idle, abs=2e-3)
