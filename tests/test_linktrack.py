"""LinkTrack-style codec: the documented byte example, round trips, resync and rejection of bad frames."""

from __future__ import annotations

import contextlib
import math
import re
from pathlib import Path

import numpy as np
import pytest

from hil.link.linktrack import (
    MAX_BODIES,
    MAX_NODE_DATA,
    BodySample,
    FrameDecoder,
    FrameError,
    MocapPacket,
    Node,
    NodeFrame,
    decode_frame,
    decode_mocap_payload,
    encode_frame,
    encode_mocap_frame,
    encode_mocap_payload,
    encode_mocap_rows,
    encode_node_frame,
    mocap_frame_len,
    sum8,
)

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
])
def test_encoder_rejects_out_of_range_values_with_a_clear_error(packet, message):
    with pytest.raises(FrameError, match=message):
        encode_mocap_payload(packet)


def test_node_data_over_224_bytes_is_refused_and_decode_of_junk_raises():
    with pytest.raises(FrameError, match="224"):
        encode_frame(NodeFrame(2, 0, (Node(1, 0, bytes(MAX_NODE_DATA + 1)),)))
    with pytest.raises(FrameError):
        decode_frame(b"\x55\x02\x05\x00")
    with pytest.raises(FrameError, match="not a mocap payload"):
        decode_mocap_payload(b"X" * 20)


def test_one_node_frames_and_payload_rows_are_the_general_encoders_bytes():
    rng = np.random.default_rng(4)
    for k in range(200):
        data = bytes(rng.integers(0, 256, int(rng.integers(0, 225)), dtype=np.uint8))
        role, module, node_role, node = (int(x) for x in rng.integers(0, 256, 4))
        assert encode_node_frame(data, role, module, node_role, node) == encode_frame(
            NodeFrame(role, module, (Node(node_role, node, data),)))
        bodies = tuple(
            BodySample(int(rng.integers(0, 256)), float(rng.uniform(0, 100)), tuple(rng.normal(size=3)),
                       tuple(rng.normal(size=4)), bool(rng.integers(0, 2)))
            for _ in range(int(rng.integers(0, 6))))
        rows = [(b.body_id, b.valid, b.stamp_s, [*b.pos_m, *b.quat_wxyz]) for b in bodies]
        assert encode_mocap_rows(k, rows) == encode_mocap_payload(MocapPacket(k, bodies))


def test_fast_encoders_still_refuse_bad_input():
    with pytest.raises(FrameError):
        encode_node_frame(bytes(225))
    with pytest.raises(FrameError):
        encode_node_frame(b"abc", role=1.0)  # type: ignore[arg-type]  # equal to 1 as a key, not a byte
    with pytest.raises(FrameError):
        encode_mocap_rows(1, [(1, True, 0.0, [0.0, math.nan, 0.0, 1.0, 0.0, 0.0, 0.0])])
    with pytest.raises(FrameError):
        encode_mocap_rows(1, [(1, True, 0.0, [0.0, math.inf, -math.inf, 1.0, 0.0, 0.0, 0.0])])
    with pytest.raises(FrameError):
        encode_mocap_rows(1, [(256, True, 0.0, [0.0] * 7)])
    with pytest.raises(FrameError):
        encode_mocap_rows(1, [(1, True, -1.0, [0.0] * 7)])
