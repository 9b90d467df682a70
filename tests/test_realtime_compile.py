"""A real-time loop compiles nothing once it runs: on a fresh install (numba's cache empty) the FC's,
the physics', the world's and the ESC bus's kernels compile while the loop is set up, not in flight, where
a compile of seconds would stall the FC and starve the onboard program of mocap (it aborted, seen in a
fresh clone)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

FLIGHT = r"""
import json, math
import numpy as np
from numba.core import event

from emulator.fc import N3Setpoint
from emulator.loops.realtime_runner import RealtimeRunner
from emulator.vehicle import EmulatedVehicle
from emulator.fc.n3 import ATTITUDE_THRUST_YAW_ANGLE
from emulator.physics.native import hover_state
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.world import CrossingTracker, Gap, LabVolume, World
from hil.link import SimClock

profile = load_profile("n3_tx2")
start = hover_state(profile, (0.0, 0.0, 1.5))
vehicle = EmulatedVehicle(profile, initial_state=start)
tracker = CrossingTracker(World.for_profile(Gap(centre_m=(0.0, 2.0, 1.5)), LabVolume(), profile))
RealtimeRunner(vehicle, [], clock=SimClock())  # the set-up a real-time loop has: it compiles now
# and `hil fc --esc-bus`'s: the motors behind the compiled DroneCAN bus model
from emulator.esc.bus import EscBusConfig, attach
from emulator.servers.mavlink_server import MavlinkServer
from hil.link import MemoryTransport
from hil.link.mavlink import MavlinkCodec

on_bus = EmulatedVehicle(profile, initial_state=start)
fc_end, _ = MemoryTransport.pair()
attach(on_bus, MavlinkServer(on_bus, MavlinkCodec(fc_end, SimClock(), 1, 1)), EscBusConfig(),
       np.random.default_rng(0))
RealtimeRunner(on_bus, [], clock=SimClock())

compiled = []

class Count(event.Listener):
    def on_start(self, e): pass
    def on_end(self, e): compiled.append(str(e.data.get("dispatcher")))

event.register("numba:compile", Count())
hover_pct = profile.force_to_thrust_percent(profile.mass_kg * GRAVITY_M_S2)
hover = N3Setpoint(ATTITUDE_THRUST_YAW_ANGLE, 5.0, 0.0, hover_pct, 0.0)
flown = {}
for name, v in (("direct", vehicle), ("esc_bus", on_bus)):
    fc = v.fc
    fc.set_setpoint(hover, 0.0)
    fc.set_setpoint(hover, 0.0)
    assert fc.arm(0.0).accepted  # in the air: the FC's own hold (velocity hold, inner loop)
    v.step(50)
    assert fc.request_offboard(v.time_s).accepted  # the setpoint through the inner loop
    for _ in range(20):
        fc.set_setpoint(hover, v.time_s)
        v.step(10)
        s = v.state
        if v is vehicle:  # (the world's checks, as a real-time run makes them)
            tracker.update(s.time_s, s.pos_m, s.quat_wxyz)
    flown[name] = {"state": fc.state.value, "z": float(v.state.pos_m[2])}
print(json.dumps({"compiled": compiled, "flown": flown}))
"""


def test_a_real_time_loop_compiles_nothing_once_it_runs(tmp_path):
    env = {**os.environ, "HIL_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    env.pop("NUMBA_CACHE_DIR", None)  # (the empty cache of this test, not the machine's)
    p = subprocess.run([sys.executable, "-c", FLIGHT], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    for flight in out["flown"].values():  # it flew: hold, then the setpoints (motors direct, on the bus)
        assert flight["state"] == "offboard" and flight["z"] > 1.0
    assert out["compiled"] == []


def test_hil_fc_on_an_empty_cache_says_it_compiles_and_still_flies_its_whole_duration(tmp_path):
    env = {**os.environ, "HIL_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    env.pop("NUMBA_CACHE_DIR", None)
    cmd = [sys.executable, "-m", "hil.cli", "fc", "--duration", "1"]
    first = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "hil fc: compiling the emulator's kernels once" in first.stderr
    summary = json.loads(first.stdout.strip().splitlines()[-1])
    assert summary["sim_time_s"] > 0.9  # the compile came before the clock, not out of the duration
    again = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "compiling" not in again.stderr  # cached now: said only once
