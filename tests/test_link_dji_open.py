"""The OPEN-protocol codec of the link layer: DJI's CRCs, frames byte for byte the worked examples of
docs/dji-open-link.md, a parser that finds every good frame among garbage and bad frames, and the
session rules (ACKs matched by SESSION and SEQ, retries that resend the same bytes)."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

from hil.link import dji_open as d
from hil.link.clock import SimClock
from hil.link.memory import MemoryTransport
from hil.link.tlog import TlogWriter, read_tlog

DOC = Path(__file__).resolve().parents[1] / "docs" / "dji-open-link.md"


def _bitwise_crc(data: bytes, poly_reflected: int, init: int = 0x3AA3) -> int:
    """A reflected CRC bit by bit, no table (as DJI's `dji_crc` tables are made)."""
    crc = init
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ poly_reflected if crc & 1 else crc >> 1
    return crc


def _doc_example(name: str) -> bytes:
    text = DOC.read_text(encoding="utf-8")
    m = re.search(rf"<!-- worked-example: {name} -->\s*```\s*\n([0-9a-f ]+)\n```", text)
    assert m is not None, f"docs/dji-open-link.md lost its worked example {name!r}"
    return bytes.fromhex(m.group(1))


def test_crcs_are_djis_reflected_crcs_from_0x3aa3():
    rng = np.random.default_rng(1)
    for n in (0, 1, 10, 31, 1019):
        data = rng.bytes(n)
        assert d.crc16(data) == _bitwise_crc(data, 0xA001)
        assert d.crc32(data) == _bitwise_crc(data, 0xEDB88320)


def test_the_docs_worked_examples_are_the_codecs_bytes():
    setpoint = d.encode_command(d.SET_CONTROL, d.CMD_SETPOINT, d.setpoint_payload(0x20, 10.0, 0.0, 50.0, 0.0),
                                session=0, seq=1)
    assert setpoint == _doc_example("setpoint")
    assert d.encode_ack(2, 7, d.ack_code(d.CONTROL_OBTAINED)) == _doc_example("ack")
    # and the fields read back as the page says
    f = d.decode(d.FrameParser().feed(_doc_example("setpoint"))[0])
    assert (f.session, f.is_ack, f.seq, f.cmd_set, f.cmd_id) == (0, False, 1, 0x01, 0x03)
    assert d.read_setpoint(f.payload) == (0x20, 10.0, 0.0, 50.0, 0.0)
    a = d.decode(d.FrameParser().feed(_doc_example("ack"))[0])
    assert (a.session, a.is_ack, a.seq, d.read_ack_code(a.data)) == (2, True, 7, d.CONTROL_OBTAINED)


def test_a_frame_checks_its_own_crcs_to_zero_and_its_length_field():
    frame = d.encode_command(0x00, 0x01, bytes(44), session=3, seq=0xBEEF)
    assert len(frame) == 12 + 2 + 44 + 4 and d.frame_size(frame, 0) == len(frame)
    assert d.crc16(frame[:12]) == 0 and d.crc32(frame) == 0
    assert frame[8:10] == struct.pack("<H", 0xBEEF)


def test_encode_refuses_what_does_not_fit_the_header():
    with pytest.raises(ValueError, match="session"):
        d.encode(32, 0, b"\x00\x00")
    with pytest.raises(ValueError, match="at most 1007"):
        d.encode(0, 0, bytes(1008))
    assert len(d.encode(0, 0, bytes(1007))) == d.MAX_FRAME_BYTES


def _frames(rng: np.random.Generator, n: int) -> list[bytes]:
    out = []
    for i in range(n):
        data = rng.bytes(int(rng.integers(2, 60)))
        out.append(d.encode(int(rng.integers(0, 32)), i, data, is_ack=bool(rng.integers(0, 2))))
    return out


def _damage(frame: bytes, rng: np.random.Generator) -> bytes:
    """A frame made bad: a flipped bit, a cut, a wrong version, reserved bits, a length too small."""
    b = bytearray(frame)
    kind = int(rng.integers(0, 5))
    if kind == 0:
        i = int(rng.integers(0, len(b)))
        b[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:
        return bytes(b[: int(rng.integers(1, len(b)))])
    elif kind == 2:  # VER 1, header CRC made good again: the version check must catch it
        b[2] |= 0x04
        b[10:12] = struct.pack("<H", d.crc16(bytes(b[:10])))
    elif kind == 3:  # reserved byte set, header CRC good
        b[6] = 0x5A
        b[10:12] = struct.pack("<H", d.crc16(bytes(b[:10])))
    else:  # LEN 5 (under a header), header CRC good
        b[1], b[2] = 5, 0
        b[10:12] = struct.pack("<H", d.crc16(bytes(b[:10])))
    return bytes(b)


@pytest.mark.parametrize("chunk", [1, 7, 64, 4096])
def test_the_parser_finds_every_good_frame_among_garbage_and_bad_frames(chunk: int):
    rng = np.random.default_rng(chunk)
    good = _frames(rng, 400)
    stream = bytearray()
    for f in good:
        r = int(rng.integers(0, 4))
        if r == 0:
            stream += rng.bytes(int(rng.integers(1, 40))).replace(b"\xaa", b"\x55")
        elif r == 1:
            stream += _damage(good[int(rng.integers(0, len(good)))], rng)
        elif r == 2:
            stream += b"\xaa"  # a lone SOF right in front of a frame
        stream += f
    parser = d.FrameParser()
    got = []
    for i in range(0, len(stream), chunk):
        got.extend(parser.feed(bytes(stream[i : i + chunk])))
    assert got == good
    st = parser.stats
    assert st.garbage_bytes > 0 and st.bad_header > 0 and st.bad_crc > 0 and st.bad_length > 0


def test_random_bytes_never_make_a_frame_nor_raise():
    rng = np.random.default_rng(5)
    parser = d.FrameParser()
    for _ in range(200):
        assert parser.feed(rng.bytes(int(rng.integers(0, 3000)))) == []
    assert parser.pending_bytes < d.MAX_FRAME_BYTES


def _codec_pair():
    clock = SimClock()
    a, b = MemoryTransport.pair()
    return clock, d.OpenCodec(a, clock, retry_s=0.1, tries=3), d.OpenCodec(b, clock)


def test_a_reliable_command_is_resent_with_the_same_bytes_until_its_ack():
    clock, client, fc = _codec_pair()
    sent = client.send_command(d.SET_CONTROL, d.CMD_ARM, b"\x01")
    f = fc.receive()[0]
    assert f.session in d.RELIABLE_SESSIONS and f.wants_ack
    clock.advance_to(0.05)
    assert client.service(clock.now_s()) == []  # not due yet
    clock.advance_to(0.1)
    assert client.service(clock.now_s()) == [sent]  # the same SESSION, SEQ, bytes
    fc.send_ack(f.session, f.seq, d.ack_code(d.ARM_SUCCESS))
    client.receive()
    assert client.acks[(d.SET_CONTROL, d.CMD_ARM)][0] == d.ack_code(d.ARM_SUCCESS)
    assert client.waiting == 0
    clock.advance_to(1.0)
    assert client.service(clock.now_s()) == []


def test_frames_are_recorded_at_the_time_the_receiver_acts_on_them(tmp_path):
    """An FC's poll passes its time: a frame read after it (a busy host) is logged at that time, which its
    timers run from; without one, at the clock's time of the read."""
    clock = SimClock()
    a, b = MemoryTransport.pair()
    log = TlogWriter(tmp_path / "fc.tlog", epoch_unix_s=1.7e9)
    client, fc = d.OpenCodec(a, clock), d.OpenCodec(b, clock, recorder=log)
    client.send_command(d.SET_CONTROL, d.CMD_ARM, b"\x01")
    clock.advance_to(0.52)
    assert len(fc.receive(0.0, 0.5)) == 1
    client.send_command(d.SET_CONTROL, d.CMD_ARM, b"\x00")
    assert len(fc.receive()) == 1
    log.close()
    assert [t for t, _ in read_tlog(tmp_path / "fc.tlog")] == [round((1.7e9 + x) * 1e6) for x in (0.5, 0.52)]


def test_an_ack_of_another_seq_is_not_taken_and_a_command_runs_out_of_tries():
    clock, client, fc = _codec_pair()
    client.send_command(d.SET_CONTROL, d.CMD_CONTROL_AUTHORITY, b"\x01")
    f = fc.receive()[0]
    fc.send_ack(f.session, (f.seq + 1) & 0xFFFF, d.ack_code(d.CONTROL_OBTAINED))
    client.receive()
    assert client.acks == {} and client.waiting == 1
    for k in range(1, 5):
        clock.advance_to(0.1 * k + 1e-9)
        client.service(clock.now_s())
    assert client.waiting == 0 and client.stats.retries == 2 and client.stats.timeouts == 1


def test_session_zero_gets_no_ack_and_session_one_is_matched_by_seq():
    _, client, fc = _codec_pair()
    frame = client.pack_command(d.SET_ACTIVATION, d.CMD_VERSION, b"\x00", d.SESSION_ACK_ONCE)
    client.transport.send(frame)
    f = fc.receive()[0]
    assert f.session == 1 and f.wants_ack
    fc.send_ack(1, f.seq, d.ack_code(0))
    client.receive()
    assert (d.SET_ACTIVATION, d.CMD_VERSION) in client.acks
    client.transport.send(client.pack_command(d.SET_CONTROL, d.CMD_SETPOINT, bytes(17)))
    assert not fc.receive()[0].wants_ack


def test_frame_size_refuses_each_fixed_header_bit_and_takes_the_free_ones():
    """Every bit of VER, the two reserved bits and the three reserved bytes set alone (the header's CRC16
    made good again) starts no frame; LEN's, SESSION's, ACK's, PADDING's, ENC's and SEQ's bits leave the
    header good (its LEN read from bits 0-9 of bytes 1-2)."""
    frame = d.encode(3, 0x1234, bytes(40))
    fixed = ({(2, bit) for bit in range(2, 8)} | {(3, 6), (3, 7)}
             | {(k, bit) for k in (5, 6, 7) for bit in range(8)})
    for k in range(1, 10):
        for bit in range(8):
            b = bytearray(frame)
            b[k] ^= 1 << bit
            b[10:12] = struct.pack("<H", d.crc16(bytes(b[:10])))
            size = d.frame_size(bytes(b), 0)
            if (k, bit) in fixed:
                assert size == d.NO_FRAME, (k, bit)
            else:
                length = (b[1] | b[2] << 8) & 0x3FF
                assert size == (length if length >= d.MIN_FRAME_BYTES else d.SHORT_FRAME), (k, bit)
    assert d.frame_size(frame, 0) == len(frame)
