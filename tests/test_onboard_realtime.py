"""`python -m policies.onboard` as its own process, in real time, on two pseudo-terminals: the FC
emulator with its MAVLink server and the mocap link run in this process on the master ends, as `hil fc`
does, and the program must fly the whole mission and say so in its JSON events."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from emulator.fc import FcState
from emulator.loops.realtime_runner import RealtimeRunner
from emulator.mocap_link import MocapLinkServer
from emulator.profile import load_profile
from emulator.servers.mavlink_server import MavlinkServer
from emulator.vehicle import EmulatedVehicle, resting_state
from emulator.world import CrossingTracker, Gap, LabVolume, World
from hil.link import PtyTransport, WallClock
from hil.link.mavlink import MavlinkCodec, mav


class _MocapPoller:
    """The mocap link and the crossing check, polled by the real-time loop."""

    def __init__(self, link: MocapLinkServer, vehicle: EmulatedVehicle, gap: Gap, tracker: CrossingTracker):
        self.link, self.vehicle, self.gap, self.tracker = link, vehicle, gap, tracker
        self._next_check_s = 0.0
        self._last_t = -1.0

    def poll(self, now_s: float) -> None:
        self.link.update(now_s, self.vehicle.state, self.gap)
        if now_s >= self._next_check_s and not self.vehicle.fc.landed:
            self._next_check_s = now_s + 0.01
            s = self.vehicle.state
            if s.time_s > self._last_t:  # the tracker wants increasing times
                self._last_t = s.time_s
                self.tracker.update(s.time_s, s.pos_m, s.quat_wxyz)


@pytest.mark.realtime
def test_onboard_process_flies_the_mission_over_ptys(tmp_path):
    profile = load_profile("n3_tx2")
    gap = Gap(centre_m=(0.0, 0.5, 2.1), roll_rad=math.radians(0.0), width_m=1.1, height_m=0.55)
    clock = WallClock()
    cmd, moc = PtyTransport.create(921600), PtyTransport.create(921600)
    vehicle = EmulatedVehicle(profile, initial_state=resting_state(profile, -2.0, -1.0))
    server = MavlinkServer(vehicle, MavlinkCodec(cmd, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1))
    tracker = CrossingTracker(World.for_profile(gap, LabVolume(), profile))
    mocap = _MocapPoller(MocapLinkServer(moc, clock, np.random.default_rng(3)), vehicle, gap, tracker)
    runner = RealtimeRunner(vehicle, [server, mocap], clock=clock, wait_fds=[cmd.fileno()]).start()
    log = tmp_path / "events.jsonl"
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "policies.onboard", "--command-link", f"serial:{cmd.endpoint}:921600",
             "--mocap-link", f"serial:{moc.endpoint}:921600", "--approach-speed", "1.5",
             "--gap-size", "1.1", "0.55", "--hover-time", "1", "--log-json", str(log),
             "--max-duration", "30",
             # on the wall clock beside the rest of the suite on two shared cores (lockstep runs poll
             # while they wait): a scheduling gap of 100 ms in this process is not what this tests
             "--stale-mocap-ms", "400"],
            capture_output=True, text=True, timeout=60)
    finally:
        runner.stop()
        cmd.close()
        moc.close()
    assert runner.error is None
    events = [json.loads(line) for line in log.read_text().splitlines()]
    names = [e["event"] for e in events]
    assert proc.returncode == 0, (proc.stderr[-2000:], names, events[-3:])  # the last ones say why
    assert names[:4] == ["start", "mocap_ok", "authority", "armed"]
    assert [e["segment"] for e in events if e["event"] == "segment"] == ["approach", "traverse", "recovery",
                                                                          "hover"]
    assert names[-2:] == ["done", "summary"] and events[-2]["hold"] is True
    # stdout carries the same events; the last, the summary, has the link counters
    out = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [e.get("event") for e in out] == names
    assert out[-1]["mavlink"]["bad_crc"] == 0 and out[-1]["mocap"]["bodies_non_finite"] == 0
    assert tracker.crossed_through_opening and tracker.first_collision is None
    assert vehicle.fc.state is FcState.HOLD
