"""LinkTrack-style codec: the documented byte example, round trips, resync and rejection of bad frames."""

from __future__ import annotations

import contextlib
import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from hil.link.clock import SimClock
from hil.link.linktrack import (
    _BODY,
    _PAYLOAD_HEAD,
    BODY_LEN,
    FLAG_VALID,
    MAX_BODIES,
    MAX_NODE_DATA,
    ROLE_ANCHOR,
    ROLE_TAG,
    BodySample,
    FrameDecoder,
    FrameError,
    MocapFrameEncoder,
    MocapPacket,
    Node,
    NodeFrame,
    crc16_ccitt,
    decode_frame,
    decode_mocap_payload,
    encode_frame,
    encode_mocap_frame,
    encode_mocap_payload,
    encode_mocap_rows,
    encode_node_frame,
    mocap_frame_len,
    sum8,
    unpack_mocap_payload,
)
from hil.link.memory import MemoryTransport
from policies.mocap_reader import MocapReader, PoseSample

DOC = Path(__file__).resolve().parents[1] / "docs" / "mocap-link-format.md"


def _packet(frame_no: int = 7, t: float = 1.5, n: int = 2) -> MocapPacket:
    bodies = tuple(
        BodySample(body_id=k + 1, stamp_s=t, pos_m=(0.25 * k, -1.0 + k, 2.0), quat_wxyz=(0.5, 0.5, -0.5, 0.5))
        for k in range(n)
    )
    return MocapPacket(frame_no=frame_no, bodies=bodies)


def test_documented_example_matches_the_encoder_byte_for_byte():
    text = DOC.read_text()
    block = re.search(r"## Worked example.*?```\n(.*?)```", text, re.S)
    assert block, "worked example hex dump not found in the spec page"
    documented = bytes(int(h, 16) for line in block.group(1).splitlines() for h in line.split()[1:])
    c, s = math.cos(math.radians(-30)), math.sin(math.radians(-30))
    packet = MocapPacket(1234, (
        BodySample(1, 12.345678, (-2.0, -1.0, 0.5), (1.0, 0.0, 0.0, 0.0)),
        BodySample(2, 12.345678, (0.0, 0.5, 2.1), (c, s, 0.0, 0.0)),
    ))
    assert encode_mocap_frame(packet) == documented
    decoded = decode_mocap_payload(decode_frame(documented).nodes[0].data)
    assert [b.name for b in decoded.bodies] == ["vehicle", "gap"]
    assert decoded.bodies[1].pos_m[2] == pytest.approx(2.1, abs=1e-6)
    assert len(documented) == mocap_frame_len(2) == 101


def test_round_trip_keeps_every_field():
    packet = MocapPacket(frame_no=0xFFFFFFFF, bodies=(
        BodySample(1, 3.000001, (1.5, -2.25, 0.125), (1.0, 0.0, 0.0, 0.0), valid=True),
        BodySample(9, 3.000001, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), valid=False),
    ))
    frame = decode_frame(encode_mocap_frame(packet, module_id=3, node_id=4))
    assert (frame.module_id, frame.nodes[0].node_id) == (3, 4)
    out = decode_mocap_payload(frame.nodes[0].data)
    assert out.frame_no == 0xFFFFFFFF
    assert out.bodies[0].pos_m == (1.5, -2.25, 0.125) and out.bodies[0].valid
    assert out.bodies[0].stamp_s == pytest.approx(3.000001, abs=1e-9)
    assert out.bodies[1].name == "body9" and not out.bodies[1].valid


def test_frame_checksum_is_the_sum_of_preceding_bytes_and_length_is_the_whole_frame():
    raw = encode_frame(NodeFrame(role=2, module_id=0, nodes=(Node(1, 5, b"abc"), Node(1, 6, b""))))
    assert raw[-1] == sum8(raw[:-1])
    assert int.from_bytes(raw[2:4], "little") == len(raw) == 11 + 4 + 3 + 4 + 0 + 1
    assert decode_frame(raw).nodes == (Node(1, 5, b"abc"), Node(1, 6, b""))


def test_decoder_resyncs_after_garbage_whatever_the_chunking():
    frames = [encode_mocap_frame(_packet(k)) for k in range(5)]
    garbage = b"\x55\x02\xff\xff" + b"\x00\x55" + bytes(range(200, 256))
    stream = garbage + frames[0] + frames[1] + garbage + frames[2] + b"\x55" + frames[3] + frames[4]
    for chunk in (1, 2, 7, 50, len(stream)):
        dec = FrameDecoder()
        got = []
        for i in range(0, len(stream), chunk):
            got += dec.feed(stream[i:i + chunk])
        assert [decode_mocap_payload(f.nodes[0].data).frame_no for f in got] == [0, 1, 2, 3, 4]
        assert dec.stats.frames_ok == 5
        assert dec.stats.bytes_skipped == 2 * len(garbage) + 1
        assert dec.stats.resyncs == 3
        assert dec.buffered == 0


def test_bad_checksum_is_counted_and_the_next_frame_still_decodes():
    good = encode_mocap_frame(_packet(1))
    bad = bytearray(encode_mocap_frame(_packet(2)))
    bad[40] ^= 0x10
    dec = FrameDecoder()
    got = dec.feed(bytes(bad) + good)
    assert len(got) == 1 and decode_mocap_payload(got[0].nodes[0].data).frame_no == 1
    assert dec.stats.bad_checksum == 1
    assert dec.stats.bytes_skipped == len(bad)


def test_random_corruption_never_yields_a_wrong_frame_and_every_byte_is_accounted_for():
    rng = np.random.default_rng(5)
    sent, stream = [], bytearray()
    clean = set()
    for k in range(400):
        raw = bytearray(encode_mocap_frame(_packet(k, t=k / 120)))
        if rng.random() < 0.5:
            idx = rng.choice(len(raw), size=int(rng.integers(1, 8)), replace=False)
            for i in idx:
                raw[i] ^= int(rng.integers(1, 256))
        else:
            clean.add(k)
        sent.append(bytes(raw))
        stream += raw
    dec = FrameDecoder()
    got = []
    for i in range(0, len(stream), 37):
        got += dec.feed(bytes(stream[i:i + 37]))
    accepted = []
    for f in got:
        with contextlib.suppress(FrameError):
            accepted.append(decode_mocap_payload(f.nodes[0].data).frame_no)
    assert accepted == sorted(clean)
    accepted_bytes = sum(len(sent[k]) for k in accepted)
    frames_bytes = sum(len(encode_frame(f)) for f in got)
    assert frames_bytes + dec.stats.bytes_skipped + dec.buffered == len(stream)
    assert accepted_bytes <= frames_bytes


def test_payload_crc_catches_what_the_8_bit_sum_misses():
    raw = bytearray(encode_mocap_frame(_packet(3)))
    # +1 on one byte and -1 on another keeps the 8-bit sum: the frame checksum cannot see it
    raw[30] = (raw[30] + 1) & 0xFF
    raw[31] = (raw[31] - 1) & 0xFF
    frame = decode_frame(bytes(raw))
    with pytest.raises(FrameError, match="CRC"):
        decode_mocap_payload(frame.nodes[0].data)


@pytest.mark.parametrize("packet, message", [
    (_packet(n=MAX_BODIES + 1), "at most"),
    (MocapPacket(1, (BodySample(1, 0.0, (math.nan, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),)), "finite"),
    (MocapPacket(1, (BodySample(1, -1.0, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),)), "stamp_s"),
    (MocapPacket(1, (BodySample(300, 0.0, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),)), "body id"),
    (MocapPacket(-1, ()), "32 bits"),
    (MocapPacket(1, (BodySample(7, 0.0, (0.0, 1e39, 0.0), (1.0, 0.0, 0.0, 0.0)),)), "body 7: .*float32"),
])
def test_encoder_rejects_out_of_range_values_with_a_clear_error(packet, message):
    with pytest.raises(FrameError, match=message):
        encode_mocap_payload(packet)


def _rows(packet: MocapPacket) -> list:
    return [(b.body_id, b.valid, b.stamp_s, (*b.pos_m, *b.quat_wxyz)) for b in packet.bodies]


@pytest.mark.parametrize("n", range(MAX_BODIES + 1))
def test_the_mocap_frame_encoder_writes_the_frame_of_the_payload_in_one_call(n):
    packet = _packet(frame_no=0xFFFFFFFF, n=n)
    frame = MocapFrameEncoder(ROLE_TAG, 3, ROLE_ANCHOR, 4).encode(packet.frame_no, _rows(packet))
    payload = encode_mocap_rows(packet.frame_no, _rows(packet))
    assert frame == encode_node_frame(payload, ROLE_TAG, 3, ROLE_ANCHOR, 4)
    assert len(frame) == mocap_frame_len(n) and frame[-1] == sum(frame[:-1]) & 0xFF
    decoded = decode_frame(frame)
    assert (decoded.role, decoded.module_id, decoded.nodes[0].role, decoded.nodes[0].node_id) == (2, 3, 1, 4)
    assert decode_mocap_payload(decoded.nodes[0].data) == packet


def test_the_mocap_frame_encoder_refuses_what_the_payload_and_frame_encoders_refuse():
    encoder = MocapFrameEncoder()
    not_finite = BodySample(1, 0.0, (0.0, math.inf, 0.0), (1.0, 0.0, 0.0, 0.0))
    for packet, message in [(_packet(n=MAX_BODIES + 1), "at most"), (MocapPacket(-1, ()), "32 bits"),
                            (MocapPacket(1, (not_finite,)), "finite")]:
        with pytest.raises(FrameError, match=message):
            encoder.encode(packet.frame_no, _rows(packet))
    with pytest.raises(FrameError, match="module id"):
        MocapFrameEncoder(module_id=256)
    with pytest.raises(FrameError, match="node id"):
        MocapFrameEncoder(node_id=1.0)


def test_node_data_over_224_bytes_is_refused_and_decode_of_junk_raises():
    with pytest.raises(FrameError, match="224"):
        encode_frame(NodeFrame(2, 0, (Node(1, 0, bytes(MAX_NODE_DATA + 1)),)))
    with pytest.raises(FrameError):
        decode_frame(b"\x55\x02\x05\x00")
    with pytest.raises(FrameError, match="not a mocap payload"):
        decode_mocap_payload(b"X" * 20)


# --- mocap link --------------------------------------------------------------------------------
def test_sum8_is_the_8_bit_byte_sum_at_every_length():
    rng = np.random.default_rng(23)
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
    rng = np.random.default_rng(23)
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
    stream = _random_frames(np.random.default_rng(23 + chunk))
    objects, datas = FrameDecoder(), FrameDecoder()
    for i in range(0, len(stream), chunk):
        piece = stream[i:i + chunk]
        want = [tuple(n.data for n in f.nodes) for f in objects.feed(piece)]
        assert datas.feed_node_data(piece) == want
        assert datas.stats == objects.stats and datas.buffered == objects.buffered
    assert objects.stats.bad_checksum and objects.stats.bad_structure and objects.stats.frames_ok > 200


def test_reader_poses_without_samples_are_the_samples():
    stream = _random_frames(np.random.default_rng(23), plausible=True)
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


@pytest.mark.parametrize("kind", [bytes, bytearray, memoryview])
def test_decoder_keeps_its_own_copy_of_a_partial_frame_whatever_the_chunks_type(kind):
    """A chunk is read where it lies: the part of a frame it ends with is copied, so a caller reusing
    its buffer (a bytearray or a view of one) for the next read changes nothing already given."""
    stream = b"\x00junk" + encode_mocap_frame(_packet(1)) + encode_mocap_frame(_packet(2))
    dec = FrameDecoder()
    got = []
    scratch = bytearray(64)
    for i in range(0, len(stream), 64):
        piece = stream[i:i + 64]
        scratch[: len(piece)] = piece
        chunk = kind(scratch[: len(piece)]) if kind is not memoryview else memoryview(scratch)[: len(piece)]
        got += dec.feed_node_data(chunk)
        if kind is memoryview:
            chunk.release()
        scratch[:] = bytes(64)  # the caller's buffer reused
    assert [decode_mocap_payload(d[0]).frame_no for d in got] == [1, 2]
    assert dec.stats.bytes_skipped == 5 and dec.buffered == 0
