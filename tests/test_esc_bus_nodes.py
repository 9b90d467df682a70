"""The emulated DroneCAN nodes as a DroneCAN tool sees them (a dronecan node of its own on the loopback
multicast bus): GetNodeInfo from every one, GetTransportStats, RestartNode honoured or refused, an
outside node heard and one that takes an emulated node's id reported as a conflict; and esc.Status
carrying the power train's voltage, current, temperature and power as the model states them."""

from __future__ import annotations

import math
import os

import can
import dronecan
import numpy as np
import pytest
from dronecan import uavcan
from test_esc_bus import decode, flying_bench, take_off
from test_fc_mavlink import HOVER

from emulator.esc.bus import Bridge, EscBus, EscBusConfig
from emulator.esc.kernels import AMBIENT_K, ESC_THERMAL_K_PER_W
from emulator.esc.services import ESC_NAME, FC_NAME, NodeIdentity
from hil.link.can_dronecan import McastDriver
from hil.link.mavlink import mav

DT_S = 0.0025  # the FC's motor tick


class Tool:
    """A dronecan node on the bus beside an `EscBus`, both stepped in simulated time (loopback delivery
    is done when a send returns: no waiting)."""

    def __init__(self, spec: str, esc: EscBus, node_id: int) -> None:
        self.esc, self.t = esc, 0.0
        self.nodes = [dronecan.node.Node(McastDriver(spec), node_id=node_id)]
        self.node = self.nodes[0]

    def run(self, seconds: float) -> None:
        end = self.t + seconds
        while self.t < end:
            self.t += DT_S
            self.esc.bus.take_external(self.t)
            self.esc.command(np.full(4, 0.2), self.t)
            self.esc.poll(self.t, np.full(4, 400.0), False)
            for n in self.nodes:
                n.spin(0)

    def ask(self, request: object, node_id: int) -> object:
        """The response payload to ``request`` from ``node_id`` (None: none came)."""
        got: list = []
        self.node.request(request, node_id, lambda e: got.append(e and e.response), timeout=5.0)
        for _ in range(100):
            self.run(DT_S * 4)
            if got:
                return got[0]
        return None

    def close(self) -> None:
        for n in self.nodes:
            n.close()
        self.esc.close()


@pytest.fixture
def tool():
    spec = f"mcast:{os.getpid() % 200 + 30}"
    reports: list[tuple[str, str]] = []
    esc = EscBus(EscBusConfig(), np.random.default_rng(0), 0.0,
                 lambda sev, text, t: reports.append((sev, text)), lambda action, t: None,
                 Bridge(spec, 1_000_000))
    esc.command(np.zeros(4), 0.0)
    tl = Tool(spec, esc, node_id=100)
    tl.reports, tl.spec = reports, spec
    yield tl
    tl.close()


def test_every_emulated_node_answers_getnodeinfo(tool):
    tool.run(1.5)
    infos = {nid: tool.ask(uavcan.protocol.GetNodeInfo.Request(), nid) for nid in (10, 20, 21, 22, 23)}
    assert infos[10].name.decode() == FC_NAME
    for nid in (20, 21, 22, 23):
        assert infos[nid].name.decode() == ESC_NAME
    for nid, r in infos.items():  # its own unique id, the same run after run; its uptime and health
        assert bytes(r.hardware_version.unique_id) == NodeIdentity(nid, r.name.decode()).unique_id
        assert r.status.uptime_sec in (1, 2) and r.status.health == 0  # (asked at 1.5-1.6 s)
        assert (r.software_version.major, r.software_version.minor) == (0, 1)
    assert len({bytes(r.hardware_version.unique_id) for r in infos.values()}) == 5
    # the tool's node was heard (and is no conflict), reported once
    assert not tool.esc.bus.outside_nodes[100].conflict
    assert tool.reports.count(("info", "DroneCAN node 100 heard on the bus")) == 1


def test_transport_stats_and_restart_node(tool):
    tool.run(1.2)
    stats = tool.ask(uavcan.protocol.GetTransportStats.Request(), 21)
    iface = stats.can_iface_stats[0]
    bus = tool.esc.bus.stats
    assert 0 < iface.frames_tx <= bus.external_out and 0 < iface.frames_rx <= bus.external_in
    assert stats.transfers_tx > 1.2 / DT_S and stats.transfers_rx >= 1 and stats.transfer_errors == 0
    magic = uavcan.protocol.RestartNode.Request().MAGIC_NUMBER
    restart = uavcan.protocol.RestartNode.Request
    assert not tool.ask(restart(magic_number=magic + 1), 22).ok  # (not DroneCAN's magic number)
    assert not tool.ask(restart(magic_number=magic), 10).ok  # (the FC restarts with its process)
    assert tool.ask(restart(magic_number=magic), 22).ok  # (an ESC, the motors disarmed)
    assert ("info", "ESC node 22 restarted on request") in tool.reports
    tool.run(1.0)
    up = {nid: tool.ask(uavcan.protocol.GetNodeInfo.Request(), nid).status.uptime_sec for nid in (21, 22)}
    assert up[22] < up[21] and up[22] <= 1
    tool.esc.armed = lambda: True
    assert not tool.ask(restart(magic_number=magic), 23).ok  # (armed: refused)


def test_an_outside_node_with_an_emulated_nodes_id_is_heard_and_reported_as_a_conflict(tool):
    impostor = dronecan.node.Node(McastDriver(tool.spec), node_id=21)
    tool.nodes.append(impostor)
    logs: list[tuple[int, str]] = []
    tool.node.add_handler(uavcan.protocol.debug.LogMessage,
                          lambda e: logs.append((e.transfer.source_node_id, e.message.text.decode())))
    tool.run(0.3)
    impostor.broadcast(uavcan.equipment.esc.Status(esc_index=1, rpm=4321, voltage=11.0, error_count=7))
    tool.run(0.3)
    node = tool.esc.bus.outside_nodes[21]
    assert node.conflict and node.frames >= 1  # heard, not taken for this process's own echo
    text = "node id 21 conflict: another node on the bus uses it"
    assert ("warning", "DroneCAN node id 21 used by two nodes") in tool.reports and (10, text) in logs
    # ... and what it said reached the FC's node, as it would on a real bus (the two cannot be told apart)
    assert ("warning", "ESC 1 errors: 7") in tool.reports


def test_esc_status_carries_the_power_train_of_the_motors():
    bridge = Bridge("virtual:escs-power", 1_000_000)
    listener = can.Bus(interface="virtual", channel="escs-power")
    try:
        b, stepper = flying_bench(bridge=bridge)
        take_off(b, thrust=1.2 * HOVER)
        climbing = [m for m in iter(lambda: listener.recv(0), None)]
        b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)  # (forced: in the air)
        b.run(0.3)
        stopped = [m for m in iter(lambda: listener.recv(0), None)]
    finally:
        listener.shutdown()
        stepper.esc.close()
    p = b.vehicle.profile
    status = [t.payload for t in decode(climbing) if t.payload._type is uavcan.equipment.esc.Status][-8:]
    last = {s.esc_index: s for s in status}
    full_w = p.drag_torque_coeff_nm_s2 * p.max_rotor_speed_rad_s**3 / p.motor_efficiency
    for s in last.values():
        w = s.rpm * 2 * math.pi / 60
        draw_w = p.drag_torque_coeff_nm_s2 * w**3 / p.motor_efficiency  # k_m w^3 over the efficiency
        assert s.rpm > 3000 and s.voltage * s.current == pytest.approx(draw_w, rel=0.01)
        lost_w = (1 - p.motor_efficiency) * draw_w
        assert s.temperature == pytest.approx(AMBIENT_K + ESC_THERMAL_K_PER_W * lost_w, abs=0.3)
        assert s.power_rating_pct == pytest.approx(100 * draw_w / full_w, abs=1)
    total_a = sum(s.current for s in last.values())
    for s in last.values():  # the pack's voltage sags under the four ESCs' draw
        assert s.voltage == pytest.approx(p.battery_voltage_v - p.battery_resistance_ohm * total_a, abs=0.02)
    assert 5 < total_a < 15  # (a 0.9 kg quadrotor climbing on a 4S pack)
    rest = [t.payload for t in decode(stopped) if t.payload._type is uavcan.equipment.esc.Status][-4:]
    assert all(s.current == 0 and s.voltage == pytest.approx(p.battery_voltage_v, abs=0.01)
               and s.temperature == pytest.approx(AMBIENT_K, abs=0.3) for s in rest)
