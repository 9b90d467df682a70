"""The second round of per-tick fast paths keeps behaviour: hand-framed MAVLink is byte for byte
pymavlink's and decodes to the same messages, the scalar estimator is the textbook Kalman filter, a
repeated lockstep tick is acted on once, readers drain datagram links fully, and a run reports the
onboard start-up apart from the loop."""

from __future__ import annotations

import math
import select
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from hil.link.clock import SimClock
from hil.link.mavlink import MavlinkCodec, decode_frame, encode_frame, mav, message_from_payload
from hil.link.memory import MemoryTransport
from hil.link.tlog import TlogWriter
from hil.link.udp import UdpTransport
from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios
from policies.onboard import OnboardProgram, ProgramConfig
from policies.onboard.command_link import CommandLink
from policies.onboard.estimator import EstimatorConfig, PoseEstimator

RNG_SEED = 11


def _random_messages(m: mav.MAVLink, rng: np.random.Generator) -> list[mav.MAVLink_message]:
    """Per-tick messages with random fields, zeros included (MAVLink 2 trims trailing zero bytes)."""
    def f() -> float:
        return float(rng.choice([0.0, rng.normal(0.0, 10.0)]))

    def u(bits: int) -> int:
        return int(rng.choice([0, rng.integers(0, 2**bits)]))

    q = [f() for _ in range(4)]
    return [
        m.set_attitude_target_encode(u(32), u(8), u(8), u(8), q, f(), f(), f(), f()),
        m.timesync_encode(int(rng.integers(-2**62, 2**62)) * int(rng.integers(0, 2)), u(62)),
        m.heartbeat_encode(u(8), u(8), u(8), u(32), u(8)),
        m.attitude_encode(u(32), f(), f(), f(), f(), f(), f()),
        m.local_position_ned_encode(u(32), f(), f(), f(), f(), f(), f()),
        m.command_ack_encode(u(16), u(8), u(8), int(rng.integers(-2**31, 2**31)), u(8), u(8)),
    ]


def _payload(msg: mav.MAVLink_message) -> bytes:
    """The message's full payload in wire order, packed the way pymavlink packs it."""
    values = []
    for name in msg.ordered_fieldnames:
        v = getattr(msg, name)
        values.extend(v if isinstance(v, list) else [v])
    return msg.unpacker.pack(*values)


def test_hand_framed_messages_are_pymavlinks_bytes_and_decode_to_the_same_message():
    rng = np.random.default_rng(RNG_SEED)
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=191)
    for _ in range(300):
        for msg in _random_messages(ref, rng):
            ref.seq = int(rng.integers(0, 256))
            frame = bytes(msg.pack(ref))
            assert encode_frame(msg.get_msgId(), _payload(msg), ref.seq, 1, 191) == frame
            mine, theirs = decode_frame(frame), ref.decode(bytearray(frame))
            assert mine.to_dict() == theirs.to_dict()
            assert (mine.get_msgbuf(), mine.get_payload(), mine.get_crc()) == (
                theirs.get_msgbuf(), theirs.get_payload(), theirs.get_crc())
            assert vars(mine.get_header()) == vars(theirs.get_header())


def test_codec_pack_payload_follows_the_sequence_and_records_like_pack():
    clock = SimClock()
    a, _ = MemoryTransport.pair()
    frames: list[bytes] = []

    class Keep:
        def record(self, frame: bytes, time_s: float) -> None:
            frames.append(frame)

    codec = MavlinkCodec(a, clock, 1, 191, recorder=Keep())
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=191)
    m = codec.mav
    for i in range(300):  # past a sequence wrap, mixing both ways of sending
        msg = m.timesync_encode(i, 2 * i)
        frame = codec.pack_payload(msg.id, _payload(msg)) if i % 3 else codec.pack(msg)
        assert frame == bytes(ref.timesync_encode(i, 2 * i).pack(ref))
        ref.seq = (ref.seq + 1) % 256
    assert codec.stats.frames_sent == 300 and len(frames) == 300


def test_codec_pack_of_per_tick_messages_is_pymavlinks_bytes():
    rng = np.random.default_rng(RNG_SEED + 1)
    a, _ = MemoryTransport.pair()
    codec = MavlinkCodec(a, SimClock(), 1, mav.MAV_COMP_ID_AUTOPILOT1)
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=mav.MAV_COMP_ID_AUTOPILOT1)
    for _ in range(100):
        for msg in _random_messages(codec.mav, rng):
            assert codec.pack(msg) == bytes(msg.pack(ref))
            ref.seq = (ref.seq + 1) % 256
    text = codec.mav.statustext_encode(4, b"chunk", 7, 0)  # has a field named "id": not a HEARTBEAT
    assert codec.pack(text) == bytes(text.pack(ref))
    ref.seq = (ref.seq + 1) % 256
    q = (0.5, 0.5, 0.5, 0.5)  # an array field given as a tuple or an array packs the same
    for qq in (q, np.array(q)):
        msg = codec.mav.set_attitude_target_encode(1, 1, 1, 7, qq, 0.0, 0.0, 0.0, 0.5)
        assert codec.pack(msg) == bytes(msg.pack(ref))
        ref.seq = (ref.seq + 1) % 256


def test_everything_the_fc_sends_is_framed_as_pymavlink_frames_it():
    # the FC's codec frames every message itself on an unsigned link: each kind it can send, from a
    # vehicle in flight, must be pymavlink's bytes
    from emulator.fc import EmulatedVehicle, MavlinkServer
    from emulator.physics.native import hover_state
    from emulator.profile import load_profile

    profile = load_profile("n3_tx2")
    vehicle = EmulatedVehicle(profile, initial_state=hover_state(profile, (0.5, -1.0, 1.5)))
    vehicle.fc.arm(0.0)
    vehicle.step(20)
    a, _ = MemoryTransport.pair()
    codec = MavlinkCodec(a, SimClock(), 1, mav.MAV_COMP_ID_AUTOPILOT1)
    server = MavlinkServer(vehicle, codec)
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=mav.MAV_COMP_ID_AUTOPILOT1)
    ref.seq = codec.mav.seq
    m = codec.mav
    msgs = [sender(0.02) for sender in server._senders.values()] + [
        m.statustext_encode(mav.MAV_SEVERITY_CRITICAL, b"Failsafe: setpoint stream lost"),
        m.command_ack_encode(mav.MAV_CMD_DO_SET_MODE, mav.MAV_RESULT_ACCEPTED, 0, 0, 1, 191),
        m.timesync_encode(123_000_000, 456),
        m.ping_encode(1_000, 7, 1, 191),
    ]
    assert len({msg.get_msgId() for msg in msgs}) == len(msgs) >= 14
    for msg in msgs:
        assert codec.pack(msg) == bytes(msg.pack(ref)), msg.get_type()
        ref.seq = (ref.seq + 1) % 256
    assert codec.stats.frames_sent == len(msgs)


def test_signed_codec_packs_payloads_through_pymavlink():
    clock = SimClock()
    a, b = MemoryTransport.pair()
    key = bytes(range(32))
    tx = MavlinkCodec(a, clock, 1, 191, signing_key=key)
    rx = MavlinkCodec(b, clock, 1, 1, signing_key=key)
    msg = tx.mav.set_attitude_target_encode(5, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.5)
    frame = tx.pack_payload(msg.id, _payload(msg))
    assert frame[2] & mav.MAVLINK_IFLAG_SIGNED
    got = rx.feed(frame)
    assert [g.get_type() for g in got] == ["SET_ATTITUDE_TARGET"] and rx.stats.bad_signature == 0
    assert message_from_payload(msg.id, _payload(msg)).to_dict() == got[0].to_dict()


def test_codec_feed_keeps_order_and_error_counts_with_the_fast_decoder():
    clock = SimClock()
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    m = ref
    good = [
        m.heartbeat_encode(2, 12, 1, 0, 4),
        m.statustext_encode(4, b"hello"),  # not a fast id: pymavlink decodes it, in its place
        m.set_attitude_target_encode(1, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.4),
        m.timesync_encode(0, 10_000_000),
    ]
    frames = []
    for msg in good:
        frames.append(bytes(msg.pack(ref)))
        ref.seq += 1
    bad = bytearray(frames[2])
    bad[12] ^= 0xFF  # a corrupted setpoint: a CRC error, counted, not decoded
    stream = frames[0] + frames[1] + bytes(bad) + frames[2] + b"\x00junk" + frames[3]
    a, _ = MemoryTransport.pair()
    fast = MavlinkCodec(a, clock, 1, 1)
    plain = mav.MAVLink(None)
    plain.robust_parsing = True
    expected = [x for x in plain.parse_buffer(stream) if not isinstance(x, mav.MAVLink_bad_data)]
    got = fast.feed(stream)
    assert [x.to_dict() for x in got] == [x.to_dict() for x in expected]
    assert [x.get_type() for x in got] == ["HEARTBEAT", "STATUSTEXT", "SET_ATTITUDE_TARGET", "TIMESYNC"]
    assert fast.stats.bad_crc == 1 and fast.stats.garbage_bytes > 0 and fast.stats.frames_received == 4


def test_tlog_of_hand_framed_setpoints_reads_back_with_pymavlink(tmp_path: Path):
    clock = SimClock()
    path = tmp_path / "run.tlog"
    a, b = MemoryTransport.pair()
    with TlogWriter(path) as tlog:
        onboard = CommandLink(a, clock)
        fc = MavlinkCodec(b, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1, recorder=tlog)
        for k in range(20):
            clock.advance_to(0.01 * (k + 1))
            onboard.send_attitude_target(0.1 * k, -0.05, 0.3, 0.5)
            onboard.answer_tick(clock.now_s())
            fc.receive()
    log = mavutil.mavlink_connection(str(path))
    seen = []
    while (msg := log.recv_match()) is not None:
        seen.append(msg)
    setpoints = [s for s in seen if s.get_type() == "SET_ATTITUDE_TARGET"]
    ticks = [s for s in seen if s.get_type() == "TIMESYNC"]
    assert len(setpoints) == 20 and len(ticks) == 20
    assert setpoints[-1].thrust == pytest.approx(0.5)
    assert ticks[-1].tc1 == ticks[-1].ts1 == 200_000_000


def _reference_filter(cfg: EstimatorConfig, poses: list[tuple[float, np.ndarray]]) -> np.ndarray:
    """A plain matrix constant-acceleration Kalman filter per axis (the estimator's model)."""
    x = P = None
    last = -math.inf
    for stamp, z in poses:
        dt = stamp - last
        if x is None or dt > cfg.reset_after_s:
            x = np.stack([z, np.zeros(3), np.zeros(3)])
            P = np.diag([cfg.pos_noise_m**2, 1.0, 10.0])
        else:
            F = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
            Q = cfg.jerk_psd * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6],
                                         [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                                         [dt**3 / 6, dt**2 / 2, dt]])
            x, P = F @ x, F @ P @ F.T + Q
            k = P[:, 0] / (P[0, 0] + cfg.pos_noise_m**2)
            x = x + np.outer(k, z - x[0])
            P = P - np.outer(k, P[0, :])
        last = stamp
    assert x is not None
    return x


def test_scalar_estimator_is_the_matrix_kalman_filter():
    rng = np.random.default_rng(RNG_SEED)
    cfg = EstimatorConfig()
    est = PoseEstimator(cfg)
    poses = []
    t = 0.0
    for k in range(400):
        t += 1 / 120 + (0.6 if k == 200 else 0.0)  # one silence long enough to restart the filter
        pos = np.array([math.sin(t), 0.5 * t * t, 2.0 - math.cos(2 * t)]) + rng.normal(0, 0.003, 3)
        poses.append((t, pos))
        assert est.update(t, pos, np.array([1.0, 0.0, 0.0, 0.0]), t + 0.028)
    x_ref = _reference_filter(cfg, poses)
    e = est.estimate(t + 0.028)  # received at t + latency, asked at once: predicted over the latency
    h = cfg.latency_s
    np.testing.assert_allclose(e.acc_m_s2, x_ref[2], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(e.vel_m_s, x_ref[1] + x_ref[2] * h, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(e.pos_m, x_ref[0] + x_ref[1] * h + x_ref[2] * h * h / 2, rtol=1e-9, atol=1e-9)


def test_estimator_rejects_bad_poses_without_raising():
    est = PoseEstimator()
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    assert not est.update(0.1, np.array([1.0, math.nan, 0.0]), quat, 0.12)
    assert not est.update(0.1, np.array([1.0, 2.0]), quat, 0.12)
    assert not est.update(0.1, np.zeros(3), np.zeros(4), 0.12)
    assert not est.update(0.1, "abc", quat, 0.12)  # type: ignore[arg-type]
    assert not est.ready and est.rejected == 4
    with pytest.raises(ValueError):
        est.estimate(0.2)
    assert est.update(0.1, np.zeros(3), np.array([0.0, 0.0, 0.0, 2.0]), 0.12)
    np.testing.assert_allclose(est.estimate(0.12).quat_wxyz, [0.0, 0.0, 0.0, 1.0])
    assert not est.update(0.1, np.zeros(3), quat, 0.13)  # the same stamp again


def test_a_repeated_tick_is_acted_on_once_and_answered_each_time():
    clock = SimClock()
    cmd_ob, cmd_fc = MemoryTransport.pair()
    moc_ob, _ = MemoryTransport.pair()
    program = OnboardProgram(cmd_ob, moc_ob, ProgramConfig())
    program.link.lockstep = True
    fc = MavlinkCodec(cmd_fc, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    tick = fc.pack(fc.mav.timesync_encode(0, 10_000_000))
    cmd_fc.send(tick + tick)  # the same tick twice, as a resend during start-up leaves it
    assert program.lockstep_poll() == [0.01]
    answers = [m for m in fc.receive() if m.get_type() == "TIMESYNC"]
    assert [(m.tc1, m.ts1) for m in answers] == [(10_000_000, 10_000_000)] * 2
    assert [e["event"] for e in program.events.events] == ["start"]  # acted on once


def test_command_link_reads_every_waiting_datagram_in_one_poll():
    clock = SimClock()
    rx = UdpTransport.server("127.0.0.1", 0)
    tx = UdpTransport.client("127.0.0.1", int(rx.endpoint.rsplit(":", 1)[1]))
    try:
        link = CommandLink(rx, clock)
        ref = mav.MAVLink(None, srcSystem=1, srcComponent=mav.MAV_COMP_ID_AUTOPILOT1)
        for k in range(3):
            tx.send(bytes(ref.timesync_encode(0, (k + 1) * 10_000_000).pack(ref)))
        select.select([rx.fileno()], [], [], 2.0)
        time.sleep(0.05)  # loopback delivery is quick; let all three be waiting
        msgs = link.poll()  # one poll takes every waiting datagram, one read each
        assert len(msgs) == 3
        assert link.take_ticks() == pytest.approx([0.01, 0.02, 0.03])
    finally:
        tx.close()
        rx.close()


def test_run_reports_the_onboard_start_up_apart_from_the_loop(tmp_path: Path):
    # (a start beside the gap, not in the wall's plane: the program would refuse to plan from there)
    s = loads_scenarios("description: short hover\nduration_s: 0.5\ninitial: {pos_m: [-1, -2, 1.5]}\n")[0]
    sm = run_scenario(s, tmp_path / "run", RunOptions(in_process=False)).summary
    assert sm["onboard_startup_s"] > 0  # a process had to start and open its ports
    assert sm["loop_sim_time_s"] == pytest.approx(0.49)  # from the first answered tick (0.01 s) on
    assert sm["real_time_factor"] == pytest.approx(sm["loop_sim_time_s"] / sm["loop_wall_time_s"])
    assert sm["ticks_answered"] == sm["ticks"] == 50
    assert sm["wall_time_s"] >= sm["onboard_startup_s"] + sm["loop_wall_time_s"]
