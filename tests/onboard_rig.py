"""An in-process bench for the onboard program built from the real parts: the FC emulator and its MAVLink
server, the mocap system with its UWB link, the gap world, joined to the program by in-memory links.
Simulated time advances in 1 ms steps; the program is stepped by time (or by TIMESYNC ticks)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from emulator.fc import EmulatedVehicle, FcState, MavlinkServer, resting_state
from emulator.mocap_link import MocapLinkServer
from emulator.profile import load_profile
from emulator.world import CrossingTracker, Gap, LabVolume, World
from hil.link import MemoryTransport, SimClock
from hil.link.mavlink import MavlinkCodec, mav
from policies.onboard import OnboardProgram, ProgramConfig

#: the test gap: the program's (and the scenario files') default opening, 0.8 m x 0.45 m
TEST_GAP_SIZE_M = (ProgramConfig.gap_width_m, ProgramConfig.gap_height_m)
GAP_CENTRE_M = (0.0, 0.5, 2.1)
START_XY_M = (-2.0, -1.0)


@dataclass
class RigResult:
    """What a run left behind: the program, the vehicle, the crossing record and the FC's ticks."""

    program: OnboardProgram
    vehicle: EmulatedVehicle
    tracker: CrossingTracker
    lab: LabVolume
    sim_time_s: float
    tick_answers: list[tuple[int, int]] = field(default_factory=list)

    @property
    def event_names(self) -> list[str]:
        return [e["event"] for e in self.program.events.events]

    def event(self, name: str) -> dict[str, Any]:
        return next(e for e in self.program.events.events if e["event"] == name)


def run_mission(roll_deg: float = 0.0, speed_m_s: float = 2.0, *, t_end_s: float = 20.0,
                gap_size_m: tuple[float, float] = TEST_GAP_SIZE_M, lockstep_period_s: float | None = None,
                mocap_cut_s: float | None = None, seed: int = 1, after_s: float = 0.0,
                probe: Callable[[float, EmulatedVehicle, OnboardProgram], None] | None = None,
                **config: Any) -> RigResult:
    """Fly one mission; ``mocap_cut_s``: stop the mocap stream at that simulated time (s);
    ``lockstep_period_s``: drive the program by TIMESYNC ticks at that period instead of `step`;
    ``after_s``: keep the emulator running this long after the program ends (the FC on its own);
    ``probe(t, vehicle, program)``: called every 10 ms of simulated time while the program runs."""
    profile = load_profile("n3_tx2")
    gap = Gap(centre_m=GAP_CENTRE_M, roll_rad=math.radians(roll_deg), width_m=gap_size_m[0],
              height_m=gap_size_m[1])
    lab = LabVolume()
    clock = SimClock()
    fc_cmd, ob_cmd = MemoryTransport.pair()
    fc_moc, ob_moc = MemoryTransport.pair()
    vehicle = EmulatedVehicle(profile, initial_state=resting_state(profile, *START_XY_M))
    fc_codec = MavlinkCodec(fc_cmd, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    server = MavlinkServer(vehicle, fc_codec)
    mocap = MocapLinkServer(fc_moc, clock, np.random.default_rng(seed))
    tracker = CrossingTracker(World.for_profile(gap, lab, profile))
    cfg = ProgramConfig(approach_speed_m_s=speed_m_s, gap_width_m=gap_size_m[0], gap_height_m=gap_size_m[1],
                        **config)
    program = OnboardProgram(ob_cmd, ob_moc, cfg)
    answers: list[tuple[int, int]] = []
    t, k = 0.0, 0
    next_tick = lockstep_period_s or 0.0
    while t < t_end_s and not program.finished:
        k += 1
        t = k * 1e-3
        clock.advance_to(t)
        vehicle.step_to(t)
        server.poll(t)
        if mocap_cut_s is None or t < mocap_cut_s:
            mocap.update(t, vehicle.state, gap)
        if k % 10 == 0 and not vehicle.fc.landed:
            tracker.update(t, vehicle.state.pos_m, vehicle.state.quat_wxyz)
        if probe is not None and k % 10 == 0:
            probe(t, vehicle, program)
        if lockstep_period_s is None:
            program.step(t)
        elif t >= next_tick - 1e-9:
            next_tick += lockstep_period_s
            fc_codec.send(fc_codec.mav.timesync_encode(0, round(t * 1e9)))
            program.lockstep_poll()
            for m in fc_codec.receive():  # the program's answer and its outputs, at this tick
                if m.get_type() == "TIMESYNC":
                    answers.append((m.tc1, m.ts1))
                server.handle(m, t)
    end = t + after_s
    while t < end:
        k += 1
        t = k * 1e-3
        vehicle.step_to(t)
        server.poll(t)
        if k % 10 == 0 and not vehicle.fc.landed:
            tracker.update(t, vehicle.state.pos_m, vehicle.state.quat_wxyz)
    return RigResult(program, vehicle, tracker, lab, t, answers)


def fc_holding(vehicle: EmulatedVehicle) -> bool:
    return vehicle.fc.state is FcState.HOLD
