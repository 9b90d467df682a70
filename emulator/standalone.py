"""The standalone FC's own parts (`hil fc`): its built-in gaps, and what its real-time loop polls besides
the vehicle: the FC's server, a watch of the gap (crossings and collisions told as status texts) and the
mocap-over-UWB link fed with the true poses."""

from __future__ import annotations

import math

from emulator.assembly import Emulator
from emulator.mocap_link import MocapLinkServer
from emulator.servers.registry import FcServer
from emulator.vehicle import EmulatedVehicle
from emulator.world import CrossingTracker, Gap, World
from hil.link.mavlink import mav

#: built-in gaps and where the vehicle starts (x, y on the ground, m): the paper's test case (centre
#: (0, 0.5, 2.1) m, rolled -60 deg, start (-2, -1)), or a level gap at (0, 0, 1.5) m
GAPS: dict[str, tuple[Gap, tuple[float, float]]] = {
    "paper": (Gap(centre_m=(0.0, 0.5, 2.1), roll_rad=math.radians(-60.0)), (-2.0, -1.0)),
    "level": (Gap(), (-2.0, 0.0)),
}
GAP_SAMPLE_S = 0.01  # collision and crossing checks at 100 Hz


class MocapPoll:
    """Feeds the true vehicle and gap poses to the mocap-over-UWB link when it has something due."""

    def __init__(self, vehicle: EmulatedVehicle, server: MocapLinkServer, gap: Gap | None) -> None:
        self.vehicle, self.server, self.gap = vehicle, server, gap

    def poll(self, now_s: float) -> None:
        if now_s >= self.server.next_event_s():
            self.server.update(now_s, self.vehicle.state, self.gap)


class GapWatch:
    """Samples the vehicle against the gap world and reports crossings and collisions as status texts."""

    def __init__(self, vehicle: EmulatedVehicle, world: World, server: FcServer) -> None:
        self.vehicle, self.server = vehicle, server
        self.tracker = CrossingTracker(world)
        self._next_s = 0.0
        self._reported_collision = False

    def poll(self, now_s: float) -> None:
        if now_s < self._next_s:
            return
        self._next_s = now_s + GAP_SAMPLE_S
        if self.vehicle.fc.landed:  # resting on the ground is no collision
            return
        s = self.vehicle.state
        crossing = self.tracker.update(s.time_s + 1e-9 * self.tracker.samples, s.pos_m, s.quat_wxyz)
        if crossing is not None:
            where = "through the gap" if crossing.through_opening else "outside the gap"
            self.server.statustext(mav.MAV_SEVERITY_INFO, f"Crossed the wall {where}", now_s, key="crossing")
        hit = self.tracker.first_collision
        if hit is not None and not self._reported_collision:
            self._reported_collision = True
            self.server.statustext(mav.MAV_SEVERITY_CRITICAL, f"Collision: {hit.obstacle}", now_s)


def loop_links(emu: Emulator, gap: Gap | None) -> list:
    """What the standalone FC's real-time loop polls: the FC's server, the gap's watch (with a world), the
    mocap link (with one)."""
    links: list = [emu.server]
    if emu.world is not None:
        links.append(GapWatch(emu.vehicle, emu.world, emu.server))
    if emu.mocap is not None:
        links.append(MocapPoll(emu.vehicle, emu.mocap, gap))
    return links
