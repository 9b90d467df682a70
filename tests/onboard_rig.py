"""An in-process bench for the onboard program built from the real parts: the FC emulator and its MAVLink
server, the mocap system with its UWB link, the gap world, joined to the program by in-memory links.
Simulated time advances in 1 ms steps; the program is stepped by time (or by TIMESYNC ticks)."""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from emulator.fc import FcState
from emulator.mocap_link import MocapLinkServer
from emulator.profile import load_profile
from emulator.servers.mavlink_server import MavlinkServer
from emulator.vehicle import EmulatedVehicle, resting_state
from emulator.world import CrossingTracker, Gap, LabVolume, World
from hil.link import MemoryTransport, SimClock
from hil.link.linktrack import BODY_VALUES, FrameDecoder, crc16_ccitt, encode_node_frame, unpack_mocap_payload
from hil.link.mavlink import MavlinkCodec, mav
from hil.link.transport import Transport
from policies.onboard import OnboardProgram, ProgramConfig
from policies.onboard.pilots import Pilot

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


class TamperedLink(Transport):
    """The sending end of a link whose bytes pass through ``tamper(time_s, data) -> data`` first."""

    def __init__(self, inner: Transport, clock: SimClock, tamper: Callable[[float, bytes], bytes]) -> None:
        super().__init__()
        self.inner, self.clock, self.tamper = inner, clock, tamper

    def _send_internal(self, data: bytes) -> int:
        self.inner.send(self.tamper(self.clock.now_s(), data))
        return len(data)

    def _recv_internal(self, max_bytes: int) -> bytes:
        return b""

    def _close_internal(self) -> None:
        self.inner.close()


def run_mission(roll_deg: float = 0.0, speed_m_s: float = 2.0, *, t_end_s: float = 20.0,
                gap_size_m: tuple[float, float] = TEST_GAP_SIZE_M, lockstep_period_s: float | None = None,
                mocap_cut_s: float | None = None, seed: int = 1, after_s: float = 0.0,
                probe: Callable[[float, EmulatedVehicle, OnboardProgram], None] | None = None,
                mocap_tamper: Callable[[float, bytes], bytes] | None = None, pilot: Pilot | None = None,
                **config: Any) -> RigResult:
    """Fly one mission; ``mocap_cut_s``: stop the mocap stream at that simulated time (s);
    ``lockstep_period_s``: drive the program by TIMESYNC ticks at that period instead of `step`;
    ``after_s``: keep the emulator running this long after the program ends (the FC on its own);
    ``probe(t, vehicle, program)``: called every 10 ms of simulated time while the program runs;
    ``mocap_tamper(t, data) -> data``: rewrites the mocap bytes sent at ``t`` (s); ``pilot``: flies the
    mission instead of the configured one."""
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
    mocap_out = fc_moc if mocap_tamper is None else TamperedLink(fc_moc, clock, mocap_tamper)
    mocap = MocapLinkServer(mocap_out, clock, np.random.default_rng(seed))
    tracker = CrossingTracker(World.for_profile(gap, lab, profile))
    cfg = ProgramConfig(approach_speed_m_s=speed_m_s, gap_width_m=gap_size_m[0], gap_height_m=gap_size_m[1],
                        **config)
    program = OnboardProgram(ob_cmd, ob_moc, cfg, pilot=pilot)
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


def rewrite_mocap(data: bytes, *, stamp_us: int | None = None, pos_m: Sequence[float] | None = None,
                  quat_wxyz: Sequence[float] | None = None, body_ids: Sequence[int] = (1, 2),
                  stamp_shift_us: int = 0, pos_shift_m: Sequence[float] = (0.0, 0.0, 0.0),
                  swap_poses: bool = False) -> bytes:
    """``data`` (whole LinkTrack mocap frames, as the emulator writes them) with the bodies of
    ``body_ids`` given this stamp (us, or their own moved by ``stamp_shift_us``), position (m, or their
    own moved by ``pos_shift_m``) or quaternion: values the emulator's encoder refuses to write (NaN, a
    stamp of 2^62 us), framed with good checksums; ``swap_poses``: the first two bodies' poses swapped
    first (a tracker that mixed up the rigid bodies). Anything that is not whole one-node frames passes
    as it is."""
    dec = FrameDecoder()
    frames = dec.feed(data)
    if not frames or dec.buffered or dec.stats.bytes_skipped or any(len(f.nodes) != 1 for f in frames):
        return data
    out = []
    for f in frames:
        node = f.nodes[0]
        values = list(unpack_mocap_payload(node.data))
        if swap_poses and values[3] >= 2:
            a, b = 4 + 3, 4 + BODY_VALUES + 3  # each body's position and quaternion
            values[a:a + 7], values[b:b + 7] = values[b:b + 7], values[a:a + 7]
        for k in range(4, len(values), BODY_VALUES):
            if values[k] in body_ids:
                values[k + 3:k + 6] = [v + d for v, d in zip(values[k + 3:k + 6], pos_shift_m, strict=True)]
                if stamp_us is not None:
                    values[k + 2] = stamp_us
                values[k + 2] += stamp_shift_us
                if pos_m is not None:
                    values[k + 3:k + 6] = pos_m
                if quat_wxyz is not None:
                    values[k + 6:k + 10] = quat_wxyz
        payload = struct.pack("<BBIB" + "BBQ3f4f" * values[3], *values)
        payload += struct.pack("<H", crc16_ccitt(payload))
        out.append(encode_node_frame(payload, f.role, f.module_id, node.role, node.node_id))
    return b"".join(out)


def rewrite_mocap_from(t0_s: float, frames: float = math.inf,
                       **values: Any) -> Callable[[float, bytes], bytes]:
    """A ``mocap_tamper``: the first ``frames`` writes at or after ``t0_s`` (s) get ``values`` (see
    `rewrite_mocap`); the others pass as they are."""
    left = [frames]

    def tamper(t: float, data: bytes) -> bytes:
        if t < t0_s or left[0] <= 0:
            return data
        left[0] -= 1
        return rewrite_mocap(data, **values)

    return tamper


def all_of(*tampers: Callable[[float, bytes], bytes]) -> Callable[[float, bytes], bytes]:
    """A ``mocap_tamper`` applying ``tampers`` one after the other."""

    def tamper(t: float, data: bytes) -> bytes:
        for f in tampers:
            data = f(t, data)
        return data

    return tamper
