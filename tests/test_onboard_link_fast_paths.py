"""The onboard links' per-tick shortcuts give what the general code gives: the command link's own
decoding of the lockstep frames (TIMESYNC, NAMED_VALUE_INT) acts as the pymavlink messages would, the
codec counts and orders frames handed over raw as decoded ones, the table CRC is pymavlink's, and on the
mocap link the node-data decoder, the flat payload unpacker, the Adler-based 8-bit sum and the reader's
poses without PoseSamples match the frame objects, the packets and the samples, corrupt bytes included."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from pymavlink.generator.mavcrc import x25crc_slow

from hil.link.clock import SimClock
from hil.link.linktrack import (
    _BODY,
    _PAYLOAD_HEAD,
    BODY_LEN,
    FLAG_VALID,
    MAX_BODIES,
    BodySample,
    FrameDecoder,
    FrameError,
    MocapPacket,
    Node,
    NodeFrame,
    crc16_ccitt,
    decode_mocap_payload,
    encode_frame,
    encode_mocap_frame,
    encode_mocap_payload,
    sum8,
    unpack_mocap_payload,
)
from hil.link.mavlink import MavlinkCodec, crc_x25, decode_frame, mav
from hil.link.mavlink import encode_frame as encode_mavlink
from hil.link.memory import MemoryTransport
from policies.mocap_reader import MocapReader, PoseSample
from policies.onboard.command_link import RAW_MSG_IDS, USED_MSG_IDS, CommandLink

RNG_SEED = 23
FC = mav.MAV_COMP_ID_AUTOPILOT1


# --- command link ------------------------------------------------------------------------------
def _name(rng: np.random.Generator) -> bytes:
    """NAMED_VALUE_INT names around the lockstep's "mocap_n": exact, NUL-terminated with junk after,
    longer, shorter, other case, non-ASCII, empty."""
    return [b"mocap_n", b"mocap_n\x00\x01z", b"mocap_nn", b"mocap_", b"MOCAP_N", b"mocap_\xff", b"",
            b"mocap_n\x00", bytes(rng.integers(0, 256, 10, dtype=np.uint8))][int(rng.integers(0, 9))]


def _tick_payloads(rng: np.random.Generator) -> list[tuple[int, bytes]]:
    """(id, payload) of random TIMESYNC and NAMED_VALUE_INT messages, trailing zeros and over-long
    payloads (cut by the decoder) included."""
    ts = mav.MAVLink_timesync_message.unpacker
    nv = mav.MAVLink_named_value_int_message.unpacker
    out = []
    for _ in range(300):
        tc1 = int(rng.choice([0, 0, int(rng.integers(-2**62, 2**62))]))
        ts1 = int(rng.choice([int(rng.integers(0, 2**40)) * 1_000_000, int(rng.integers(-2**62, 2**62)), 0]))
        out.append((mav.MAVLINK_MSG_ID_TIMESYNC, ts.pack(tc1, ts1)))
        value = int(rng.choice([int(rng.integers(0, 2**31)), -int(rng.integers(1, 2**31)), 0]))
        name = _name(rng)
        out.append((mav.MAVLINK_MSG_ID_NAMED_VALUE_INT, nv.pack(int(rng.integers(0, 2**32)), value, name)))
    for msg_id, payload in out[:40]:
        out.append((msg_id, payload + bytes(rng.integers(1, 256, 5, dtype=np.uint8))))
    return out


def test_the_command_link_acts_on_its_tick_frames_as_on_the_decoded_messages():
    rng = np.random.default_rng(RNG_SEED)
    clock = SimClock()
    fc_end, ob_end = MemoryTransport.pair()
    link = CommandLink(ob_end, clock)
    ref = CommandLink(MemoryTransport.pair()[0], clock)
    for seq, (msg_id, payload) in enumerate(_tick_payloads(rng)):
        frame = encode_mavlink(msg_id, payload, seq % 256, 1, FC)
        fc_end.send(frame)
        got = link.poll() if seq % 2 else None
        if got is None:
            assert link.read() == 1
        else:
            assert [m.to_dict() for m in got] == [decode_frame(frame).to_dict()]
        ref._handle(decode_frame(frame))
        assert link.take_ticks() == ref.take_ticks()
        assert link.mocap_announced == ref.mocap_announced
    assert link.codec.stats.frames_received == 600 + 40 and link.codec.stats.errors == 0


def _fc_stream(rng: np.random.Generator) -> bytes:
    """A stream of the FC's frames (tick frames, telemetry the onboard side ignores or decodes) with
    bit flips, junk bytes and cut frames."""
    fc = mav.MAVLink(None, srcSystem=1, srcComponent=FC)
    msgs = []
    for k in range(200):
        msgs += [fc.named_value_int_encode(k, b"mocap_n", int(rng.integers(0, 2**31))),
                 fc.timesync_encode(0, (k + 1) * 10_000_000)]
        kind = int(rng.integers(0, 5))
        if kind == 0:
            msgs.append(fc.heartbeat_encode(2, 12, 129, 6 << 16, 4))
        elif kind == 1:
            msgs.append(fc.attitude_encode(k, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0))
        elif kind == 2:
            msgs.append(fc.statustext_encode(4, b"status %d" % k))
        elif kind == 3:
            msgs.append(fc.command_ack_encode(176, 0, 0, 0, 1, 191))
    stream = bytearray()
    for msg in msgs:
        raw = bytearray(msg.pack(fc))
        r = rng.random()
        if r < 0.06:
            raw[int(rng.integers(0, len(raw)))] ^= int(rng.integers(1, 256))
        elif r < 0.09:
            raw = raw[: int(rng.integers(1, len(raw)))]
        elif r < 0.12:
            raw = bytearray(rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8).tobytes()) + raw
        stream += raw
    return bytes(stream)


class _Recorder:
    def __init__(self) -> None:
        self.frames: list[tuple[bytes, float]] = []

    def record(self, frame: bytes, time_s: float) -> None:
        self.frames.append((bytes(frame), time_s))


@pytest.mark.parametrize("chunk", [7, 64, 4096])
def test_raw_tick_frames_keep_the_codecs_counts_order_and_recording(chunk: int):
    rng = np.random.default_rng(RNG_SEED + chunk)
    stream = _fc_stream(rng)
    clock = SimClock()
    rec_raw, rec_ref = _Recorder(), _Recorder()
    raw = MavlinkCodec(MemoryTransport.pair()[0], clock, 1, 191, accept_ids=USED_MSG_IDS, raw_ids=RAW_MSG_IDS,
                       recorder=rec_raw)
    ref = MavlinkCodec(MemoryTransport.pair()[0], clock, 1, 191, accept_ids=USED_MSG_IDS, recorder=rec_ref)
    got, want = [], []
    for i in range(0, len(stream), chunk):
        got += raw.feed(stream[i:i + chunk])
        want += ref.feed(stream[i:i + chunk])
    assert any(m.__class__ is bytes for m in got) == (chunk > 7)  # split frames all go through pymavlink
    assert [(decode_frame(m) if m.__class__ is bytes else m).to_dict() for m in got] == \
        [m.to_dict() for m in want]
    assert all(m[7] in RAW_MSG_IDS for m in got if m.__class__ is bytes)
    assert raw.stats.as_dict() == ref.stats.as_dict() and raw.stats.errors > 0
    assert rec_raw.frames == rec_ref.frames
    # and the codec's own fast CRC check lets through what pymavlink's parser accepts, no more (frames
    # behind a bad one go through pymavlink, which decodes the ids the link does not use too)
    plain = mav.MAVLink(None)
    plain.robust_parsing = True
    parsed = [m for m in plain.parse_buffer(stream) or []
              if not isinstance(m, mav.MAVLink_bad_data | mav.MAVLink_unknown)]
    assert [m.to_dict() for m in want if m.get_msgId() in USED_MSG_IDS] == \
        [m.to_dict() for m in parsed if m.get_msgId() in USED_MSG_IDS]


def test_crc_x25_is_pymavlinks_for_every_crc_extra():
    rng = np.random.default_rng(RNG_SEED)
    for extra in range(256):
        data = rng.integers(0, 256, int(rng.integers(0, 60)), dtype=np.uint8).tobytes()
        assert crc_x25(data, extra) == x25crc_slow(data + bytes([extra])).crc
        assert crc_x25(bytearray(data)) == crc_x25(memoryview(data)) == x25crc_slow(data).crc


# --- mocap link --------------------------------------------------------------------------------
def test_sum8_is_the_8_bit_byte_sum_at_every_length():
    rng = np.random.default_rng(RNG_SEED)
    for n in [*range(0, 300), 511, 512, 4000]:
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        want = sum(data) & 0xFF
        assert sum8(data) == sum8(bytearray(data)) == sum8(memoryview(data)[:]) == want
    assert sum8(b"\xff" * 256) == (255 * 256) & 0xFF and sum8(b"\xff" * 257) == (255 * 257) & 0xFF


def _decode_mocap_payload_reference(data: bytes) -> MocapPacket:
    """The payload decoder before `unpack_mocap_payload`: one body at a time."""
    if len(data) < _PAYLOAD_HEAD.size + 2:
        raise FrameError(f"mocap payload too short ({len(data)} bytes)")
    kind, version, frame_no, count = _PAYLOAD_HEAD.unpack_from(data, 0)
    if kind != 0x4D:
        raise FrameError(f"not a mocap payload (type 0x{kind:02X})")
    if version != 1:
        raise FrameError(f"mocap payload version {version} not supported (want 1)")
    if len(data) != _PAYLOAD_HEAD.size + count * BODY_LEN + 2:
        raise FrameError(f"mocap payload of {len(data)} bytes does not hold {count} bodies")
    (crc,) = struct.unpack_from("<H", data, len(data) - 2)
    if crc16_ccitt(data[:-2]) != crc:
        raise FrameError("mocap payload CRC mismatch")
    bodies = []
    for k in range(count):
        body_id, flags, stamp_us, *vals = _BODY.unpack_from(data, _PAYLOAD_HEAD.size + k * BODY_LEN)
        bodies.append(BodySample(body_id=body_id, stamp_s=stamp_us * 1e-6, pos_m=tuple(vals[:3]),
                                 quat_wxyz=tuple(vals[3:]), valid=bool(flags & FLAG_VALID)))
    return MocapPacket(frame_no=frame_no, bodies=tuple(bodies))


def _random_packet(rng: np.random.Generator, frame_no: int, plausible: bool = False) -> MocapPacket:
    """Random bodies; ``plausible``: most of them as a reader takes them (unit quaternions, stamps
    increasing with the frame number at 120 Hz), from the tenth frame on some with a random stamp (most
    of them far in the future) or a quaternion of norm 0.3 or 2."""
    bodies = []
    for _ in range(int(rng.integers(0, MAX_BODIES + 1))):
        q = rng.normal(size=4) * float(rng.choice([1.0, 0.3, 2.0]))
        stamp_s = float(rng.uniform(0, 1e4))
        if plausible:  # one in ten with a random stamp, one in ten with a random quaternion
            r = 1.0 if frame_no < 10 else rng.random()  # (the first ones set the reference)
            q = q if r < 0.1 else q / np.linalg.norm(q)
            stamp_s = stamp_s if 0.1 <= r < 0.2 else frame_no / 120
        bodies.append(BodySample(int(rng.integers(0, 6)), stamp_s,
                                 tuple(float(x) for x in rng.normal(0, 3, 3)), tuple(float(x) for x in q),
                                 bool(rng.random() < 0.9)))
    return MocapPacket(frame_no, tuple(bodies))


def _outcome(decode: object, data: bytes) -> object:
    """What ``decode`` makes of ``data``, or the FrameError's message."""
    try:
        return decode(data)  # type: ignore[operator]
    except FrameError as exc:
        return str(exc)


def test_flat_unpacking_gives_the_packet_and_the_errors_of_the_body_by_body_decoder():
    rng = np.random.default_rng(RNG_SEED)
    payloads = []
    for k in range(300):
        raw = bytearray(encode_mocap_payload(_random_packet(rng, k)))
        if rng.random() < 0.4:
            raw[int(rng.integers(0, len(raw)))] ^= int(rng.integers(1, 256))
        if rng.random() < 0.1:
            raw = raw[: int(rng.integers(0, len(raw)))]
        payloads.append(bytes(raw))
    # more bodies than a node carries: the decoders take them all the same
    rows = struct.pack("<BBIB", 0x4D, 1, 9, MAX_BODIES + 2) + b"".join(
        _BODY.pack(k, 1, 10 * k, 0.0, 1.0, 2.0, 1.0, 0.0, 0.0, 0.0) for k in range(MAX_BODIES + 2))
    payloads += [rows + struct.pack("<H", crc16_ccitt(rows)), b"", b"M\x01", b"X" * 20]
    for data in payloads:
        want = _outcome(_decode_mocap_payload_reference, data)
        assert _outcome(decode_mocap_payload, data) == want
        assert _outcome(decode_mocap_payload, bytearray(data)) == want
        flat = _outcome(unpack_mocap_payload, data)
        if isinstance(want, str):
            assert flat == want
        else:
            assert flat[2] == want.frame_no and flat[3] == len(want.bodies) == (len(flat) - 4) // 10


def _random_frames(rng: np.random.Generator, plausible: bool = False) -> bytes:
    """Mocap frames and other node frames (none, one, several nodes), some corrupted or cut;
    ``plausible``: as `_random_packet`."""
    stream = bytearray()
    for k in range(300):
        r = rng.random()
        if r < 0.7:
            raw = encode_mocap_frame(_random_packet(rng, k, plausible))
        else:
            nodes = tuple(Node(1, int(rng.integers(0, 256)),
                               encode_mocap_payload(_random_packet(rng, k, plausible)) if rng.random() < 0.5
                               else rng.integers(0, 256, int(rng.integers(0, 60)), dtype=np.uint8).tobytes())
                          for _ in range(int(rng.integers(0, 4))))
            raw = encode_frame(NodeFrame(2, 0, nodes))
        raw = bytearray(raw)
        r = rng.random()
        if r < 0.15:
            raw[int(rng.integers(0, len(raw)))] ^= int(rng.integers(1, 256))
        elif r < 0.2:
            raw = raw[: int(rng.integers(1, len(raw)))]
        elif r < 0.25:
            raw = bytearray(b"\x55\x02" + bytes(rng.integers(0, 256, 9, dtype=np.uint8))) + raw
        stream += raw
    return bytes(stream)


@pytest.mark.parametrize("chunk", [1, 37, 100, 5000])
def test_node_data_decoding_matches_the_frame_objects_on_corrupt_streams(chunk: int):
    stream = _random_frames(np.random.default_rng(RNG_SEED + chunk))
    objects, datas = FrameDecoder(), FrameDecoder()
    for i in range(0, len(stream), chunk):
        piece = stream[i:i + chunk]
        want = [tuple(n.data for n in f.nodes) for f in objects.feed(piece)]
        assert datas.feed_node_data(piece) == want
        assert datas.stats == objects.stats and datas.buffered == objects.buffered
    assert objects.stats.bad_checksum and objects.stats.bad_structure and objects.stats.frames_ok > 200


def test_reader_poses_without_samples_are_the_samples():
    stream = _random_frames(np.random.default_rng(RNG_SEED), plausible=True)
    clock = SimClock()
    samples: list[PoseSample] = []
    poses: list[tuple] = []
    eager = MocapReader(MemoryTransport.pair()[0], clock, on_sample=samples.append)
    lazy = MocapReader(MemoryTransport.pair()[0], clock, on_pose=lambda *a: poses.append(a))
    both = MocapReader(MemoryTransport.pair()[0], clock, on_sample=lambda s: None,
                       on_pose=lambda *a: None)
    for k, i in enumerate(range(0, len(stream), 90)):
        clock.advance_to(0.01 * (k + 1))
        n = eager._feed(stream[i:i + 90])
        assert lazy._feed(stream[i:i + 90]) == both._feed(stream[i:i + 90]) == n
        if k % 3 == 0:  # asked now and then, so some samples are made from older poses
            for body in (1, 2, 3, "vehicle"):
                s = lazy.latest(body)
                assert repr(s) == repr(eager.latest(body)) == repr(both.latest(body))
                assert lazy.latest(body) is s and lazy.age_s(body) == eager.age_s(body)
                assert lazy.is_stale(body) == eager.is_stale(body)
    assert poses == [(s.body_id, s.stamp_s, tuple(s.pos_m), tuple(s.quat_wxyz), s.received_s)
                     for s in samples]
    assert all(type(x) is float for p in poses for x in (p[1], *p[2], *p[3], p[4]))
    assert lazy.counters == eager.counters == both.counters
    c = eager.counters
    assert c.bad_payload and c.bodies_invalid and c.bodies_bad_quat and c.bodies_stamp_future
    assert c.bodies_stamp_backwards and len(samples) > 100  # (a body id twice in a frame: its second)
    for body in range(6):
        assert repr(lazy.latest(body)) == repr(eager.latest(body))
