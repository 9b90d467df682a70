"""The onboard reader as a pilot uses it: `python -m policies.mocap_reader DEVICE` printing live poses
from a pty fed in real time, and clear errors for devices that are not there."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import numpy as np
import pytest

from emulator.mocap import MocapConfig
from emulator.mocap_link import MocapLinkServer
from emulator.physics.state import VehicleState
from emulator.uwb import UwbConfig
from emulator.world.geometry import Gap
from hil.link.clock import WallClock
from hil.link.pty import PtyTransport
from policies.mocap_reader import main


def test_module_prints_vehicle_and_gap_poses_live():
    clock = WallClock()
    gap = Gap(centre_m=(0.0, 0.5, 2.1), roll_rad=-np.pi / 3)
    with PtyTransport.create(921600) as transport:
        server = MocapLinkServer(transport, clock, np.random.default_rng(0), MocapConfig(rate_hz=120),
                                 UwbConfig(latency_s=0.002, jitter_s=0.0))
        proc = subprocess.Popen(
            [sys.executable, "-m", "policies.mocap_reader", transport.endpoint,
             "--count", "3", "--rate", "10"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        deadline = time.monotonic() + 20.0
        while proc.poll() is None and time.monotonic() < deadline:
            now = clock.now_s()
            server.update(now, VehicleState(time_s=now, pos_m=[-2.0, -1.0, 0.5]), gap)
            time.sleep(0.002)
        if proc.poll() is None:
            proc.kill()
        out, err = proc.communicate(timeout=5)
    assert proc.returncode == 0, err
    lines = out.splitlines()
    vehicle = [ln for ln in lines if ln.strip().startswith("vehicle")]
    gap_lines = [ln for ln in lines if ln.strip().startswith("gap")]
    assert len(vehicle) == 3 and len(gap_lines) == 3
    # the last lines show the poses (m, deg) once frames have arrived (mocap noise: 0.2 mm, 1 mrad)
    assert _numbers(vehicle[-1]) == pytest.approx([-2.0, -1.0, 0.5, 0.0, 0.0, 0.0], abs=0.2)
    assert _numbers(gap_lines[-1]) == pytest.approx([0.0, 0.5, 2.1, -60.0, 0.0, 0.0], abs=0.2)


def _numbers(line: str) -> list[float]:
    m = re.search(r"pos=\(\s*(\S+)\s+(\S+)\s+(\S+)\) m\s+rpy=\(\s*(\S+)\s+(\S+)\s+(\S+)\) deg", line)
    assert m, f"no pose in {line!r}"
    return [float(x) for x in m.groups()]


def test_missing_device_is_a_clear_error(capsys):
    assert main(["/dev/does-not-exist-mocap"]) == 1
    assert "cannot open" in capsys.readouterr().err
    assert main(["udp:127.0.0.1:notaport"]) == 1
    assert "bad link spec" in capsys.readouterr().err
