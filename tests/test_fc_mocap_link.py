"""`hil fc` serves the mocap-over-UWB stream on its own pty, as the pilot's dry run reads it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest

from policies.mocap_reader import MocapReader


def _roll_deg(q: np.ndarray) -> float:
    w, x, y, z = q
    return math.degrees(math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))


@pytest.mark.realtime  # (frames counted over one second of wall clock)
def test_hil_fc_serves_vehicle_and_gap_poses_on_its_mocap_pty() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil.cli", "fc", "--duration", "20", "--mocap-rate", "120", "--seed", "3"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        endpoints = json.loads(proc.stdout.readline())
        assert endpoints["mocap_link"].startswith("/dev/pts/")
        assert endpoints["mocap_link"] != endpoints["command_link"]
        reader = MocapReader.open(endpoints["mocap_link"], stale_after_s=0.2)
        start = time.monotonic()
        frames = 0
        while time.monotonic() - start < 1.0:
            frames += reader.poll(timeout_s=0.05)
        vehicle, gap = reader.latest("vehicle"), reader.latest("gap")
        assert vehicle is not None and gap is not None
        # the built-in "paper" gap: centre (0, 0.5, 2.1) m rolled -60 deg; the vehicle rests at (-2, -1)
        np.testing.assert_allclose(gap.pos_m, [0.0, 0.5, 2.1], atol=0.005)
        assert abs(_roll_deg(gap.quat_wxyz) + 60.0) < 1.0
        np.testing.assert_allclose(vehicle.pos_m[:2], [-2.0, -1.0], atol=0.005)
        # 120 Hz for about a second (start-up of the reader and the radio's 20 ms latency aside)
        assert 80 <= frames <= 130, frames
        assert reader.counters.bad_checksum == 0
        reader.close()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["mocap"]["radio_delivered"] > 0
