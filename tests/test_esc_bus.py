"""The motors on a DroneCAN bus: RawCommand and esc.Status as dronecan encodes them, seen by a python-can
`virtual` bus in this process; the bus model's timing, loss, corruption and bus-off; a silent ESC
reported and failed safe; the lockstep run deterministic with the bus on and unchanged without it."""

from __future__ import annotations

import math
import os
import time

import can
import numpy as np
import pytest
from dronecan import uavcan
from dronecan.transport import Frame, Transfer, TransferManager
from test_fc_mavlink import HOVER, Bench, of_type

from emulator.esc.bus import (
    MAX_INTAKE_FRAMES,
    MIN_INTAKE_FRAMES,
    RAW_COMMAND_MAX,
    Bridge,
    CanBus,
    EscBusConfig,
    EscBusStepper,
    Message,
    attach,
    frame_bits,
    parse_bus_spec,
)
from emulator.fc import FcState
from emulator.loops.batched_steps import FastStepper
from hil.link.can_multicast import McastCanSocket
from hil.link.mavlink import PX4_MAIN_OFFBOARD, mav


def flying_bench(config: EscBusConfig | None = None, bridge: Bridge | None = None
                 ) -> tuple[Bench, EscBusStepper]:
    b = Bench()
    stepper = attach(b.vehicle, b.server, config or EscBusConfig(), np.random.default_rng(1), bridge)
    return b, stepper


def take_off(b: Bench, thrust: float = 1.3 * HOVER) -> None:
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    b.stream(0.3, thrust=thrust)
    b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD)
    b.stream(1.0, thrust=thrust)


def decode(frames: list[can.Message] | list[tuple[int, bytes]]) -> list[Transfer]:
    tm, out = TransferManager(), []
    for m in frames:
        can_id, data = (m.arbitration_id, m.data) if isinstance(m, can.Message) else m
        got = tm.receive_frame(Frame(can_id, data))
        if got:
            tr = Transfer()
            tr.from_frames(got)
            out.append(tr)
    return out


def test_a_python_can_virtual_bus_sees_rawcommand_and_esc_status_at_their_rates():
    bridge = Bridge("virtual:escs-test-1", 1_000_000)
    listener = can.Bus(interface="virtual", channel="escs-test-1")
    try:
        b, stepper = flying_bench(bridge=bridge)
        take_off(b)
        frames = []
        while (m := listener.recv(0)) is not None:
            frames.append(m)
    finally:
        listener.shutdown()
        stepper.esc.close()
    transfers = decode(frames)
    raw = [t for t in transfers if t.payload._type is uavcan.equipment.esc.RawCommand]
    status = [t for t in transfers if t.payload._type is uavcan.equipment.esc.Status]
    nodes = [t for t in transfers if t.payload._type is uavcan.protocol.NodeStatus]
    sim_s = b.clock.now_s()
    assert len(raw) == pytest.approx(400 * sim_s, rel=0.02)  # the FC's motor rate
    assert {t.source_node_id for t in raw} == {10} and len(raw[-1].payload.cmd) == 4
    assert all(0 <= c <= RAW_COMMAND_MAX for c in raw[-1].payload.cmd)
    by_index = {i: [t for t in status if t.payload.esc_index == i] for i in range(4)}
    for i, got in by_index.items():
        assert len(got) == pytest.approx(50 * sim_s, rel=0.05), i
        assert {t.source_node_id for t in got} == {20 + i}
    last = by_index[0][-1].payload
    assert last.rpm > 1000 and 10 < last.voltage < 17 and last.current > 0 and last.temperature > 290
    assert {t.source_node_id for t in nodes} == {10, 20, 21, 22, 23}  # NodeStatus at 1 Hz, every node
    assert len(nodes) == pytest.approx(5 * sim_s, abs=5)


def test_python_can_udp_multicast_carries_the_frames_out_and_an_outside_status_in():
    group = f"239.74.{os.getpid() % 200 + 20}.7"  # (a group of its own: tests may run side by side)
    bridge = Bridge(f"udp_multicast:{group}", 1_000_000)
    other = McastCanSocket("udp_multicast", group)  # another process's node: python-can's datagrams
    try:
        b, stepper = flying_bench(EscBusConfig(external=(23,)), bridge=bridge)
        b.run(0.2)
        time.sleep(0.05)
        frames, _ = other.receive(10_000)
        raw = [t for t in decode(frames) if t.payload._type is uavcan.equipment.esc.RawCommand]
        assert len(raw) == pytest.approx(80, abs=8)  # 0.2 s at 400 Hz
        # ESC 3 answers from outside: its status reaches the FC, and its motor follows the rpm
        w = 0.5 * b.vehicle.profile.max_rotor_speed_rad_s
        status = uavcan.equipment.esc.Status(rpm=int(w * 60 / (2 * math.pi)), esc_index=3)
        for frame in Transfer(payload=status, source_node_id=23, transfer_id=0).to_frames():
            other.send(frame.message_id, frame.bytes)
        time.sleep(0.1)
        b.run(0.01)
        assert stepper.esc.bus.stats.external_in >= 2
        assert stepper.esc.throttle[3] == pytest.approx(0.25, abs=1e-3)
        assert bridge.mcast.stats.own > 80  # (its own frames came back through the loop: not taken in)
    finally:
        other.close()
        stepper.esc.close()


def test_two_benches_on_two_multicast_groups_do_not_hear_each_other():
    """Two `hil fc --esc-bus udp_multicast:GROUP` on one host, on two groups, on python-can's one port:
    each bench's bus hears its own group only (it binds to its group), and never its own frames."""
    mine, theirs = (f"239.74.{os.getpid() % 200 + 20}.{n}" for n in (11, 12))
    bridge, other_bench = (Bridge(f"udp_multicast:{g}", 1_000_000) for g in (mine, theirs))
    peer = McastCanSocket("udp_multicast", mine)  # another node on this bench's group
    try:
        other_bench.send(0x1234, b"theirs")
        peer.send(0x5678, b"mine")
        time.sleep(0.1)
        assert bridge.receive(10) == ([(0x5678, b"mine")], False)  # (not the other group's frame)
        assert other_bench.receive(10) == ([], False)  # (its own came back, and was known for its own)
        assert other_bench.mcast.stats.own == 1
    finally:
        peer.close()
        bridge.close()
        other_bench.close()


def test_the_vehicle_flies_on_its_escs_throttles():
    b, stepper = flying_bench()
    take_off(b)
    assert b.vehicle.state.pos_m[2] > 0.5 and b.vehicle.fc.state is FcState.OFFBOARD
    # each motor runs at the throttle its ESC took from the last RawCommand (int14 steps)
    np.testing.assert_allclose(stepper.esc.throttle, b.vehicle.fc.motor_cmd, atol=2.0 / RAW_COMMAND_MAX)
    assert stepper.fc_steps == pytest.approx(400 * b.clock.now_s(), abs=2)  # the FC at the motor rate
    assert b.vehicle.steps == pytest.approx(1000 * b.clock.now_s(), abs=2)  # physics at 1 kHz


def test_the_fcs_quiet_motor_ticks_fly_as_its_own_update_does():
    """While the FC flies an offboard target with nothing timed due, the stepper runs its inner loop on
    the state's rows instead of `update`: the flight is the same to the bit, and the setpoint-loss
    failsafe still fires through `update`."""
    runs = []
    for quiet in (True, False):
        b, stepper = flying_bench()
        if not quiet:
            stepper.quiet_commands = False  # every motor tick through the FC's own update
        take_off(b)
        b.stream(0.3, thrust=HOVER)
        b.run(1.0)  # no setpoints: the failsafe
        runs.append((b.vehicle.state_vector(), [(e.time_s, e.reason) for e in b.vehicle.fc.events],
                     stepper.fc_quiet_steps))
    (x_quiet, events_quiet, n_quiet), (x_update, events_update, n_update) = runs
    assert n_update == 0 and n_quiet > 0.8 * 400 * 1.6
    np.testing.assert_array_equal(x_quiet, x_update)
    assert events_quiet == events_update and any("setpoints lost" in r for _, r in events_quiet)


def test_a_silent_esc_is_reported_its_motor_stops_and_the_fc_lands_when_told():
    b, stepper = flying_bench()
    b.send(b.client.mav.param_set_encode(1, 1, b"N3_ESC_FS_ACT", _int_wire(1), mav.MAV_PARAM_TYPE_INT32))
    take_off(b)
    assert stepper.esc.config.failsafe_action == "land"
    stepper.esc.set_silent(2, True)
    t_silent = b.clock.now_s()
    got = b.stream(0.3, thrust=1.3 * HOVER)
    texts = [m.text for m in of_type(got, "STATUSTEXT")]
    assert "ESC 2 silent for 0.1 s" in texts and any("ESC failed: land" in t for t in texts)
    assert stepper.esc.throttle[2] == 0.0
    [ev] = [e for e in b.vehicle.fc.events if e.to_state is FcState.FAILSAFE_LAND]
    # the timeout after its last esc.Status, which came up to one status period (20 ms) before
    assert 0.1 - 0.021 <= ev.time_s - t_silent <= 0.1 + 0.003


def test_report_only_by_default_and_the_timeout_is_a_parameter():
    b, stepper = flying_bench()
    b.send(b.client.mav.param_set_encode(1, 1, b"N3_ESC_TOUT", 0.05, mav.MAV_PARAM_TYPE_REAL32))
    take_off(b)
    assert stepper.esc.config.status_timeout_s == pytest.approx(0.05)
    stepper.esc.set_silent(1, True)
    got = b.stream(0.2, thrust=1.3 * HOVER)
    assert "ESC 1 silent for 0.05 s" in [m.text for m in of_type(got, "STATUSTEXT")]
    assert b.vehicle.fc.state is FcState.OFFBOARD  # told, not acted on
    stepper.esc.set_silent(1, False)
    got = b.stream(0.2, thrust=1.3 * HOVER)
    assert "ESC 1 answers again" in [m.text for m in of_type(got, "STATUSTEXT")]


def test_the_bus_model_times_frames_and_counts_loss_corruption_and_bus_off():
    assert frame_bits(8) == 67 + 64 + (54 + 64) // 5
    cfg = EscBusConfig()
    bus = CanBus(cfg, np.random.default_rng(0))
    seen: list[float] = []
    bus.attach(99, lambda tr, t: seen.append(t))
    msg = Message(uavcan.equipment.esc.RawCommand, 10, {"cmd": [1, 2, 3, 4]})
    bus.send(msg, 0, 8, 0.0)
    bus.send(msg, 1, 8, 0.0)  # queued behind the first
    bus.advance_to(1.0)
    bits = frame_bits(8)
    assert seen == pytest.approx([bits * 1e-6, 2 * bits * 1e-6])
    assert bus.load(1.0) == pytest.approx(2 * bits * 1e-6)
    lossy = CanBus(EscBusConfig(loss=0.2, corruption=0.1), np.random.default_rng(0))
    got: list[float] = []
    lossy.attach(99, lambda tr, t: got.append(t))
    for i in range(2000):
        lossy.send(msg, i & 31, 8, i * 1e-3)
    lossy.advance_to(10.0)
    assert len(got) == 2000 - lossy.stats.lost and lossy.stats.lost == pytest.approx(400, rel=0.15)
    assert lossy.stats.error_frames == pytest.approx(222, rel=0.2)  # 0.1 / 0.9 per frame, resent
    lossy.bus_off_until_s = 11.0
    lossy.send(msg, 0, 8, 10.5)
    assert lossy.stats.bus_off_dropped == 1


def test_bad_bus_specs_and_configs_are_refused():
    for spec in ("can0", "virtual", "socketcan"):
        with pytest.raises(ValueError, match="expected one of"):
            parse_bus_spec(spec)
    with pytest.raises(ValueError, match="external ESC node 5"):
        EscBusConfig(external=(5,))
    with pytest.raises(ValueError, match="bitrate"):
        EscBusConfig(bitrate_bps=5_000_000)


def test_the_default_path_has_no_bus():
    b = Bench()
    assert b.vehicle.motor_path is None and isinstance(FastStepper.for_vehicle(b.vehicle), FastStepper)
    assert math.isfinite(b.server.params.get("N3_ESC_TOUT"))  # the bus's parameters exist all the same


def _int_wire(value: int) -> float:
    import struct

    return struct.unpack("<f", struct.pack("<i", value))[0]


def test_hil_fc_refuses_bad_esc_bus_options(capsys):
    from hil.cli import main

    assert main(["fc", "--external-esc", "23"]) == 2
    assert "--external-esc needs --esc-bus" in capsys.readouterr().err
    assert main(["fc", "--esc-bus", "sim", "--external-esc", "23", "--mocap-link", "none"]) == 2
    assert "needs a bus other processes reach" in capsys.readouterr().err
    assert main(["fc", "--esc-bus", "can0", "--mocap-link", "none"]) == 2
    assert "--esc-bus: ESC bus 'can0': expected one of" in capsys.readouterr().err
    assert main(["fc", "--esc-bus", "mcast:0", "--external-esc", "5", "--mocap-link", "none"]) == 2
    assert "external ESC node 5" in capsys.readouterr().err
    assert main(["fc", "--esc-bus", "mcast:0@lab", "--mocap-link", "none"]) == 2
    assert "an interface's IPv4 address" in capsys.readouterr().err
    assert main(["fc", "--esc-bus", "virtual:x@127.0.0.1", "--mocap-link", "none"]) == 2
    assert "@ADDR (a network interface) is for mcast and udp_multicast" in capsys.readouterr().err
    # buses that cannot be opened (192.0.2.77: no interface of this machine has it)
    for spec in ("udp_multicast:999.1.1.1", "udp_multicast:10.1.1.1", "socketcan:nosuchcan0",
                 "mcast:0@192.0.2.77"):
        assert main(["fc", "--esc-bus", spec, "--mocap-link", "none"]) == 2
        assert f"--esc-bus: cannot open the CAN bus '{spec}'" in capsys.readouterr().err


def test_a_silent_esc_does_not_make_the_stepper_poll_every_step():
    b, stepper = flying_bench()
    take_off(b)
    stepper.esc.set_silent(0, True)
    n0 = stepper.polls
    b.stream(0.5, thrust=1.3 * HOVER)
    # three ESCs at 50 Hz and the bus's deliveries: a few hundred polls in 0.5 s, not one a step (500)
    assert stepper.polls - n0 < 400


def test_a_multi_frame_status_takes_dronecans_frames_and_a_lost_frame_loses_the_transfer():
    status = {"error_count": 0, "voltage": 15.0, "current": 2.0, "temperature": 300.0, "rpm": 9000,
              "power_rating_pct": 40, "esc_index": 2}
    msg = Message(uavcan.equipment.esc.Status, 22, status)
    cut = [len(data) for _, data in msg.encode(0, 16)]  # dronecan's own cut: 14 bytes and the CRC
    assert cut == [8, 8, 3]
    bus = CanBus(EscBusConfig(), np.random.default_rng(0))
    got: list[Message] = []
    bus.attach(10, lambda m, t: got.append(m))
    bus.send(msg, 0, 16, 0.0)
    bus.advance_to(1.0)
    assert bus.stats.bits == sum(frame_bits(n) for n in cut) and bus.stats.frames == 3
    assert got == [msg] and got[0].fields["rpm"] == 9000
    lossy = CanBus(EscBusConfig(loss=0.5), np.random.default_rng(3))
    kept: list[Message] = []
    lossy.attach(10, lambda m, t: kept.append(m))
    for i in range(400):
        lossy.send(msg, i & 31, 16, i * 1e-3)
    lossy.advance_to(1.0)
    # a transfer needs all three frames: about 1/8 of them complete, and every lost frame counts
    assert len(kept) == pytest.approx(50, rel=0.35) and lossy.stats.lost + lossy.stats.frames == 1200


def test_the_fc_hands_each_command_on_as_sent_later_commands_do_not_change_it():
    _, stepper = flying_bench()
    fc_node = stepper.esc.fc_node
    seen: list[list[int]] = []
    stepper.esc.bus.attach(99, lambda m, t: seen.append(list(m.fields["cmd"])) if "cmd" in m.fields else None)
    fc_node.send_command([0.1, 0.2, 0.3, 0.4], 100.0)
    fc_node.send_command([0.5, 0.6, 0.7, 0.8], 100.0)  # queued behind the first, sent before it arrives
    stepper.esc.bus.advance_to(101.0)
    assert seen == [[round(u * RAW_COMMAND_MAX) for u in (0.1, 0.2, 0.3, 0.4)],
                    [round(u * RAW_COMMAND_MAX) for u in (0.5, 0.6, 0.7, 0.8)]]


def test_garbage_from_a_real_bus_is_dropped_and_the_vehicle_flies_on():
    """Random frames from another node (random ids and lengths, a third of them claiming the id of a
    node of this process) reach the bus model through python-can: nothing raises, frames that decode to
    nothing are dropped, and the ESCs go on taking only the FC's commands."""
    bridge = Bridge("virtual:escs-garbage", 1_000_000)
    other = can.Bus(interface="virtual", channel="escs-garbage")
    rng = np.random.default_rng(7)
    try:
        b, stepper = flying_bench(bridge=bridge)
        take_off(b)
        z0 = b.vehicle.state.pos_m[2]
        for i in range(3000):
            can_id = int(rng.integers(0, 1 << 29))
            if i % 3 == 0:
                can_id = (can_id & ~0x7F) | int(rng.choice([10, 20, 21, 99]))
            data = rng.integers(0, 256, int(rng.integers(0, 9)), dtype=np.uint8).tobytes()
            other.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))
            if i % 50 == 49:
                b.stream(0.02, thrust=1.3 * HOVER)
        b.stream(0.1, thrust=1.3 * HOVER)
    finally:
        other.shutdown()
        stepper.esc.close()
    assert stepper.esc.bus.stats.external_in > 1500  # taken in, and dropped as they decode to nothing
    assert b.vehicle.fc.state is FcState.OFFBOARD and b.vehicle.state.pos_m[2] > z0 + 0.3
    np.testing.assert_allclose(stepper.esc.throttle, b.vehicle.fc.motor_cmd, atol=2.0 / RAW_COMMAND_MAX)


def test_an_overloaded_bus_queues_its_frames_in_order_and_a_hopeless_frame_is_given_up():
    # 10 kbit/s cannot carry RawCommand at 400 Hz and four esc.Status at 50 Hz (about 90 kbit/s): the
    # frames queue behind each other far past the queue's first size, and arrive late, in order
    b, stepper = flying_bench(EscBusConfig(bitrate_bps=10_000))
    seen: list[tuple[float, list[int]]] = []
    stepper.esc.bus.attach(99, lambda m, t: seen.append((t, list(m.fields["cmd"]))),
                           (uavcan.equipment.esc.RawCommand,))
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    b.stream(1.0, thrust=0.5 * HOVER)
    bus = stepper.esc.bus
    assert len(bus.queue) > 256 and bus.load(b.clock.now_s()) > 0.99
    times = [t for t, _ in seen]
    assert times == sorted(times) and 0 < len(seen) < 0.5 * stepper.esc.fc_node.commands_sent
    # a frame corrupted on every try: its transmitter gives it up (it would be bus-off) instead of the
    # model resending it for ever
    doomed = CanBus(EscBusConfig(corruption=0.999), np.random.default_rng(0))
    got: list[Message] = []
    doomed.attach(99, lambda m, t: got.append(m))
    msg = Message(uavcan.equipment.esc.RawCommand, 10, {"cmd": [1, 2, 3, 4]})
    for i in range(20):
        doomed.send(msg, i, 8, i * 0.1)
    doomed.advance_to(10.0)
    assert doomed.stats.lost >= 15 and doomed.stats.error_frames >= 15 * 32 and len(got) <= 5


def test_every_report_of_a_busy_moment_reaches_the_fc_none_dropped():
    """All four ESCs fall silent at once and then come back with rising error counts, their statuses
    delivered together: each "silent", each failsafe request, each "errors" and "answers again" is
    reported, in order, however many pile up at one instant."""
    from emulator.esc import kernels as k
    from emulator.esc.bus import EscBus

    said: list[tuple[str, str]] = []
    esc = EscBus(EscBusConfig(failsafe_action="land"), np.random.default_rng(0), 0.0,
                 lambda sev, text, t: said.append((sev, text)), lambda action, t: said.append(("fs", action)))
    rotor = np.full(4, 500.0)
    for i in range(4):
        esc.set_silent(i, True)
    esc.poll(0.5, rotor, armed=True)  # past the 0.1 s timeout for all four at once
    assert [t for s, t in said if s == "critical"] == [f"ESC {i} silent for 0.1 s" for i in range(4)]
    assert [t for s, t in said if s == "fs"] == ["land"] * 4
    said.clear()
    b = esc.bus
    for n in range(30):  # thirty esc.Status on the wire at once, each with more errors (the compiled path)
        p = np.array([1 + n, 15.0, 1.0, 300.0, 900, 10, n % 4, 0])
        k.queue_transfer(b.wire, b.queue, b.draws, k.ESC_STATUS, 20 + n % 4, n & 31, 16, p,
                         b.layouts[k.ESC_STATUS], b.n_frames[k.ESC_STATUS], 0.5)
    b.advance_to(1.0)
    assert [t for s, t in said if s == "info"] == [f"ESC {i} answers again" for i in range(4)]
    assert [t for s, t in said if s == "warning"] == [f"ESC {n % 4} errors: {1 + n}" for n in range(30)]


def test_a_non_finite_motor_output_goes_on_the_wire_as_a_defined_command():
    # (a NaN out of a diverged controller must not become an undefined int14: off; +inf full, -inf off)
    _, stepper = flying_bench()
    seen: list[list[int]] = []
    stepper.esc.bus.attach(99, lambda m, t: seen.append(list(m.fields["cmd"])),
                           (uavcan.equipment.esc.RawCommand,))
    stepper.esc.fc_node.send_command([math.nan, math.inf, -math.inf, 0.5], 50.0)
    stepper.esc.bus.advance_to(51.0)
    assert seen == [[0, RAW_COMMAND_MAX, 0, round(0.5 * RAW_COMMAND_MAX)]]


def test_a_flood_from_the_real_bus_is_taken_in_bounded_passes_and_every_loss_is_counted():
    """3,000 frames at once from another process: each pass takes at most what the wire could carry
    since the last one (at least `MIN_INTAKE_FRAMES`), the rest wait in the socket for later passes, and
    what the socket could not hold is counted as dropped: every frame taken in or counted lost."""
    n = os.getpid() % 200 + 25
    bus = CanBus(EscBusConfig(), np.random.default_rng(0), Bridge(f"mcast:{n}", 1_000_000))
    flood = McastCanSocket("mcast", str(n))
    try:
        for i in range(3000):
            flood.send(0x10_1234_00 | 99, bytes([i & 0xFF, 0xC0 | (i & 31)]))
        taken, t = [], 0.0
        while not taken or taken[-1]:
            n0 = bus.stats.external_in
            t += 0.001
            bus.take_external(t)
            bus.advance_to(t)
            taken.append(bus.stats.external_in - n0)
        sock = bus.bridge.mcast.stats
        assert bus.stats.external_in + sock.dropped == 3000 and sock.malformed == 0
        assert max(taken) == MIN_INTAKE_FRAMES and bus.intake_deferred >= 2
        assert bus.outside_nodes[99].frames == bus.stats.external_in
        for i in range(3000):  # ... and after a pause of a second, at most `MAX_INTAKE_FRAMES` in a pass
            flood.send(0x10_1234_00 | 99, bytes([i & 0xFF, 0xC0 | (i & 31)]))
        n0 = bus.stats.external_in
        bus.take_external(t + 1.0)
        assert bus.stats.external_in - n0 == min(MAX_INTAKE_FRAMES, 3000 - (sock.dropped - (3000 - n0)))
    finally:
        flood.close()
        bus.close()
