"""The lockstep convention of the link layer, on both sides: a tick's frames, the onboard command
link acting on them however they arrive (raw or decoded), one write per tick on each side, a
repeated tick acted on once and answered each time."""

from __future__ import annotations

import select
import time

import numpy as np
import pytest

from emulator.servers.arrivals import arrivals
from hil.link.clock import SimClock
from hil.link.lockstep import tick_frames
from hil.link.mavlink import (
    MavlinkCodec,
    decode_frame,
    mav,
)
from hil.link.mavlink import encode_frame as encode_mavlink
from hil.link.memory import MemoryTransport
from hil.link.udp import UdpTransport
from hil.runner.faults import FaultSchedule
from hil.runner.wires import CommandWire
from hil.scenario.schema import LinkSpec
from policies.onboard import OnboardProgram, ProgramConfig
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


def test_lockstep_tick_outputs_go_out_in_one_write():
    clock = SimClock()
    fc_end, ob_end = MemoryTransport.pair()
    fc = MavlinkCodec(fc_end, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    link = CommandLink(ob_end, clock)
    link.lockstep = True
    fc_end.send(fc.pack(fc.mav.timesync_encode(0, 10_000_000)))
    link.poll()
    (tick,) = link.take_ticks()
    calls = ob_end.stats.send_calls
    link.send_attitude_target(0.1, 0.0, 0.0, 0.5)
    link.send_heartbeat()
    assert ob_end.stats.send_calls == calls  # held until the answer
    link.answer_tick(tick)
    assert ob_end.stats.send_calls == calls + 1
    got = [m.get_type() for m in fc.receive()]
    assert got == ["SET_ATTITUDE_TARGET", "HEARTBEAT", "TIMESYNC"]
    # outside lockstep every frame goes out at once
    link.lockstep = False
    link.send_heartbeat()
    assert ob_end.stats.send_calls == calls + 2


def test_in_lockstep_the_messages_after_a_tick_wait_for_that_tick():
    """Two ticks read at once (the harness keeps two in flight): the messages after the first tick are
    acted on with the second, in the order they came, and a read in between gets none of them."""
    clock = SimClock()
    fc_end, ob_end = MemoryTransport.pair()
    fc = MavlinkCodec(fc_end, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    link = CommandLink(ob_end, clock)
    link.lockstep = True
    heartbeat = fc.pack(fc.mav.heartbeat_encode(2, 12, 129, 6 << 16, 4))
    fc_end.send(b"".join([tick_frames(0.01, 100, 1, FC), heartbeat, tick_frames(0.02, 250, 1, FC),
                          fc.pack(fc.mav.statustext_encode(4, b"after"))]))
    assert link.read_ticks() == [0.01]
    assert link.backlogged and link.mocap_announced == 100 and link.status is None
    link.answer_tick(0.01)
    assert link.read() == 3  # the heartbeat and the second tick's two frames, not the text after it
    assert link.status is not None and link.mocap_announced == 250 and link.status_texts == []
    assert link.backlogged and link.take_ticks() == [0.02]
    assert [m.get_type() for m in link.poll()] == ["STATUSTEXT"]
    assert not link.backlogged and link.status_texts == ["after"] and link.read_ticks() == []


def test_the_fc_frames_of_a_lockstep_tick_go_out_with_the_tick():
    clock = SimClock()
    raw, peer = MemoryTransport.pair()
    wire = CommandWire(raw, clock, LinkSpec(), np.random.default_rng(7), FaultSchedule(()))
    fc = MavlinkCodec(wire, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    wire.hold_output = True
    fc.send(fc.mav.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 1, 2, 3))
    clock.advance_to(0.01)
    wire.pump()
    assert raw.stats.send_calls == 0  # held
    tick = MavlinkCodec(MemoryTransport.pair()[0], clock, 1, 1)
    wire.send_sync(tick.pack(tick.mav.timesync_encode(0, 10_000_000)))
    assert raw.stats.send_calls == 1
    ob = MavlinkCodec(peer, clock, 1, 191)
    assert [m.get_type() for m in ob.receive()] == ["HEARTBEAT", "TIMESYNC"]


def test_the_fc_reads_the_wire_once_a_frame_has_arrived_and_when_it_is_closed():
    clock = SimClock()
    raw, peer = MemoryTransport.pair()
    wire = CommandWire(raw, clock, LinkSpec(latency_ms=5.0), np.random.default_rng(7), FaultSchedule(()))
    assert arrivals(wire).next_input_s > clock.now_s()  # nothing on the way: a poll does not read
    assert arrivals(raw).next_input_s < clock.now_s()  # a link without arrival times: read at every poll
    ob = MavlinkCodec(peer, clock, 1, 191)
    ob.send(ob.mav.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    assert wire.read_onboard()
    arrival = wire.next_arrival_s()
    assert arrival >= 0.005 and wire.input_due() is False  # on its way over the link
    clock.advance_to(arrival)
    assert wire.input_due() is True
    fc = MavlinkCodec(wire, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    assert [m.get_type() for m in fc.receive()] == ["HEARTBEAT"]
    assert wire.input_due() is False
    wire.close()
    assert wire.input_due() is True  # the read then says the link is closed


def test_the_answer_is_taken_with_what_the_program_has_written_by_now_in_one_call():
    clock = SimClock()
    raw, peer = MemoryTransport.pair()
    wire = CommandWire(raw, clock, LinkSpec(), np.random.default_rng(7), FaultSchedule(()))
    ob = MavlinkCodec(peer, clock, 1, 191)
    hb = ob.mav.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    assert wire.take_until_answer(10_000_000, 0.02, True) is None  # nothing written yet
    ob.send(hb)
    assert wire.take_until_answer(10_000_000, 0.02) is False  # not read without ``read``
    assert wire.take_until_answer(10_000_000, 0.02, True) is False  # read: a frame, no answer yet
    assert wire.to_fc.frames_sent == 0  # (held until the answer says which tick it belongs to)
    ob.send(hb)
    ob.send(ob.mav.timesync_encode(10_000_000, 10_000_000))
    ob.send(hb)  # the next tick's, stays
    assert wire.take_until_answer(10_000_000, 0.02, True) is True
    assert wire.to_fc.frames_sent == 2 and wire.next_arrival_s() >= 0.02
    # an in-process run's reads find the bytes there: the memory link's wake-up pipe is never made
    assert raw._rx.wake_r is None
    assert not wire.read_raw(0.001)  # a wait asks for the descriptor (nothing more has come)
    assert raw._rx.wake_r is not None and wire.take_until_answer(20_000_000, 0.03) is False


@pytest.mark.parametrize("loss", [0.0, 0.02])
def test_the_command_wire_delivers_frames_in_order_after_their_wire_time_and_latency(loss):
    # more frames than the jitter draws a channel that cannot lose draws at once (64): the next block
    # is drawn on the way; a lossy one draws per frame
    clock = SimClock()
    raw, peer = MemoryTransport.pair()
    spec = LinkSpec(latency_ms=2.0, jitter_ms=1.0, loss=loss, baud=115200)
    wire = CommandWire(raw, clock, spec, np.random.default_rng(7), FaultSchedule(()))
    ob = MavlinkCodec(peer, clock, 1, 191)
    n = 150
    for _ in range(n):
        ob.send(ob.mav.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    wire.read_onboard()  # all handed to the link at 0
    fc = MavlinkCodec(wire, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)
    frame_s = len(ob.pack(ob.mav.heartbeat_encode(0, 0, 0, 0, 0))) * 10 / 115200
    got, times = [], []
    while wire.next_arrival_s() < 1.0:
        clock.advance_to(wire.next_arrival_s())
        for m in fc.receive():
            got.append(m.get_seq())
            times.append(clock.now_s())
    assert got == sorted(got) and len(set(got)) == len(got)  # in order, once each
    assert (len(got) == n) if loss == 0.0 else (n * 0.8 < len(got) < n)
    # the i-th frame delivered is out of the UART after the i + 1 frames the UART has carried by then at
    # least, the latency and its jitter after that (their sum not below 0: some arrive as they are out)
    out_s = (np.arange(len(times)) + 1) * frame_s
    assert np.all(np.array(times) >= out_s - 1e-12)
    assert np.mean(np.array(times) - out_s) > 0.001 and np.ptp(np.diff(times)) > 0  # late, and not evenly


def _lockstep_program() -> tuple[OnboardProgram, MavlinkCodec, MemoryTransport]:
    """A program in lockstep on memory links; the FC's codec and the FC's end of the command link."""
    cmd_ob, cmd_fc = MemoryTransport.pair()
    moc_ob, _ = MemoryTransport.pair()
    program = OnboardProgram(cmd_ob, moc_ob, ProgramConfig())
    program.link.lockstep = True
    return program, MavlinkCodec(cmd_fc, SimClock(), 1, mav.MAV_COMP_ID_AUTOPILOT1), cmd_fc


def test_a_repeated_tick_is_acted_on_once_and_answered_each_time():
    program, fc, cmd_fc = _lockstep_program()
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


def test_a_tick_repeated_after_its_answer_changes_none_of_the_frames_that_follow():
    """How often the harness repeats a tick depends on process scheduling (a wall-clock timeout): the
    repeat gets the first answer's frame again, so the program's later frames (and their sequence
    numbers, in the .tlog) are the same as without it."""

    def outputs(repeat: bool) -> list[bytes]:
        program, fc, cmd_fc = _lockstep_program()
        got = []
        for ns in (10_000_000, 10_000_000, 20_000_000) if repeat else (10_000_000, 20_000_000):
            cmd_fc.send(fc.pack(fc.mav.timesync_encode(0, ns)))
            program.lockstep_poll()
            got.append(cmd_fc.recv())
        return got

    with_repeat, without = outputs(True), outputs(False)
    assert with_repeat[0].endswith(with_repeat[1])  # the same answer frame, sequence number and all
    assert [with_repeat[0], with_repeat[2]] == without
