"""The MAVLink codec of the link layer: frames byte for byte pymavlink's, decoded to the same
messages, telemetry a side does not use dropped only when its CRC is good, counts, order, signing,
recording, and the frame scanner."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from hil.link.clock import SimClock
from hil.link.mavlink import (
    MavlinkCodec,
    decode_frame,
    encode_frame,
    mav,
    message_from_payload,
)
from hil.link.memory import MemoryTransport
from hil.link.tlog import TlogWriter
from policies.onboard.command_link import CommandLink

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
    from emulator.physics.native import hover_state
    from emulator.profile import load_profile
    from emulator.servers.mavlink_server import MavlinkServer
    from emulator.vehicle import EmulatedVehicle

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


def _fc_frames(fc: MavlinkCodec) -> list[bytes]:
    m = fc.mav
    return [
        fc.pack(m.attitude_encode(10, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)),
        fc.pack(m.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 1, 2, 3)),
        fc.pack(m.local_position_ned_encode(10, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0)),
        fc.pack(m.timesync_encode(0, 123_000_000)),
    ]


def test_onboard_codec_decodes_what_it_uses_and_drops_the_rest_undecoded():
    clock = SimClock()
    a, b = MemoryTransport.pair()
    fc = MavlinkCodec(a, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    used = {mav.MAVLINK_MSG_ID_HEARTBEAT, mav.MAVLINK_MSG_ID_TIMESYNC}
    ob = MavlinkCodec(b, clock, 1, 191, accept_ids=used)
    msgs = ob.feed(b"".join(_fc_frames(fc)))
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "TIMESYNC"]
    assert ob.stats.frames_ignored == 2 and ob.stats.errors == 0


def test_a_corrupted_unused_frame_is_still_counted_as_bad():
    clock = SimClock()
    a, b = MemoryTransport.pair()
    fc = MavlinkCodec(a, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    ob = MavlinkCodec(b, clock, 1, 191, accept_ids={mav.MAVLINK_MSG_ID_HEARTBEAT})
    att, hb, *_ = _fc_frames(fc)
    bad = bytearray(att)
    bad[12] ^= 0x40  # a payload bit: the CRC no longer matches
    msgs = ob.feed(bytes(bad) + hb)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT"]
    assert ob.stats.bad_crc == 1 and ob.stats.frames_ignored == 0


def test_named_value_int_decodes_to_pymavlinks_message():
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    for name, value in ((b"mocap_n", 123), (b"abcdefghij", -5), (b"", 0)):
        frame = bytes(ref.named_value_int_encode(1234, name, value).pack(ref))
        mine, theirs = decode_frame(frame), ref.decode(bytearray(frame))
        assert mine.to_dict() == theirs.to_dict() and mine.get_msgbuf() == theirs.get_msgbuf()


def test_signed_codec_judges_every_frame_and_counts_refusals_by_kind():
    clock = SimClock()
    _, b = MemoryTransport.pair()
    key = bytes(range(32))
    rx = MavlinkCodec(b, clock, 1, 1, signing_key=key)
    good = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    good.signing.secret_key, good.signing.sign_outgoing, good.signing.timestamp = key, True, 1000
    wrong = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    wrong.signing.secret_key, wrong.signing.sign_outgoing, wrong.signing.timestamp = bytes(32), True, 2000
    plain = mav.MAVLink(None, srcSystem=255, srcComponent=190)

    def frame(m, msg) -> bytes:
        return bytes(msg.pack(m))

    beat = frame(good, good.heartbeat_encode(6, 8, 0, 0, 4))
    param_set = frame(good, good.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5, 9))
    assert [m.get_type() for m in rx.feed(beat + param_set)] == ["HEARTBEAT", "PARAM_SET"]
    # a HEARTBEAT may come unsigned, but one with a bad signature is refused all the same
    assert rx.feed(frame(wrong, wrong.heartbeat_encode(6, 8, 0, 0, 4))) == []
    unsigned_beat = frame(plain, plain.heartbeat_encode(6, 8, 0, 0, 4))
    assert [m.get_type() for m in rx.feed(unsigned_beat)] == ["HEARTBEAT"]
    assert rx.feed(frame(plain, plain.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5, 9))) == []
    assert rx.feed(param_set) == []  # the same frame again
    # a forged frame with a later timestamp does not move the stream's timestamp
    wrong.signing.timestamp = 10**9
    rx.feed(frame(wrong, wrong.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5, 9)))
    assert [m.get_type() for m in rx.feed(frame(good, good.param_set_encode(1, 1, b"X", 1.0, 9)))] == \
        ["PARAM_SET"]
    # a new stream (another link id) more than a minute behind the receiver's clock
    clock.advance_to(120.0)
    rx.pack(rx.mav.heartbeat_encode(2, 12, 0, 0, 4))  # (the receiver's own timestamp moves on)
    old = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    old.signing.secret_key, old.signing.sign_outgoing, old.signing.link_id = key, True, 7
    old.signing.timestamp = 2000
    assert rx.feed(frame(old, old.param_set_encode(1, 1, b"X", 1.0, 9))) == []
    s = rx.stats
    assert (s.unsigned_refused, s.bad_signature, s.replayed, s.stale_timestamp) == (1, 2, 1, 1)
    assert s.signing_refused == 5


def test_fast_path_reads_the_whole_24_bit_id_and_takes_bytearrays_as_bytes():
    """An id pymavlink does not know, whose low byte is a used id's (TIMESYNC 111 + 2^16), is left to
    pymavlink's parser (counted unknown), never read as the used one; a bytearray chunk gives the same
    frames (as bytes) and counts as the same bytes."""
    clock = SimClock()
    fc = mav.MAVLink(None, srcSystem=1, srcComponent=mav.MAV_COMP_ID_AUTOPILOT1)
    tick = bytes(fc.timesync_encode(0, 10_000_000).pack(fc))
    payload = mav.MAVLink_timesync_message.unpacker.pack(0, 20_000_000)
    alien = encode_frame(mav.MAVLINK_MSG_ID_TIMESYNC, payload, 1, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    alien = bytearray(alien)
    alien[9] = 1  # the id's upper byte: 0x01006F, not TIMESYNC
    stream = bytes(alien) + tick
    for chunk in (stream, bytearray(stream)):
        codec = MavlinkCodec(MemoryTransport.pair()[0], clock, 1, 191, raw_ids={mav.MAVLINK_MSG_ID_TIMESYNC})
        got = codec.feed(chunk)
        assert [decode_frame(m).ts1 if m.__class__ is bytes else m.ts1 for m in got] == [10_000_000]
        assert codec.stats.frames_received == 1 and codec.stats.errors == 1
        fast = MavlinkCodec(MemoryTransport.pair()[0], clock, 1, 191, raw_ids={mav.MAVLINK_MSG_ID_TIMESYNC})
        assert fast.feed(bytearray(tick)) == [tick] and fast.feed(bytearray(tick))[0].__class__ is bytes
