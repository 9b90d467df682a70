"""The per-tick fast paths keep behaviour: the onboard codec drops unused telemetry only when its CRC is
good, one write per lockstep tick on each side, the plain-float
controller, rotation and quaternion helpers agree with the general ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.generator.mavcrc import x25crc_slow

from hil.link.clock import SimClock
from hil.link.mavlink import (
    MavlinkCodec,
    crc_x25,
    mav,
    quat_enu_flu_to_ned_frd,
    quat_enu_flu_to_ned_frd_tuple,
    quat_from_euler,
    quat_from_euler_tuple,
)
from hil.link.memory import MemoryTransport
from hil.runner.faults import FaultSchedule
from hil.runner.wires import CommandWire, LinkModel
from policies.controller import ExpertController, expert_command_batch
from policies.frames import matrix_to_euler, quat_to_matrix
from policies.onboard.command_link import CommandLink

RNG_SEED = 7


def _fc_frames(fc: MavlinkCodec) -> list[bytes]:
    m = fc.mav
    return [
        fc.pack(m.attitude_encode(10, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)),
        fc.pack(m.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 1, 2, 3)),
        fc.pack(m.local_position_ned_encode(10, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0)),
        fc.pack(m.timesync_encode(0, 123_000_000)),
    ]


def test_crc_matches_pymavlink():
    rng = np.random.default_rng(RNG_SEED)
    for n in range(0, 80, 7):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert crc_x25(data) == x25crc_slow(data).crc
        assert crc_x25(data, 42) == x25crc_slow(data + bytes([42])).crc


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


def test_plain_float_helpers_agree_with_the_array_ones():
    rng = np.random.default_rng(RNG_SEED)
    ctrl = ExpertController(0.9)
    for _ in range(300):
        q = rng.normal(size=4)
        np.testing.assert_allclose(quat_to_matrix(q), quat_to_matrix(q[None])[0], atol=1e-15)
        r = quat_to_matrix(q)
        assert matrix_to_euler(r) == pytest.approx([float(x[0]) for x in matrix_to_euler(r[None])], abs=1e-14)
        qu = q / np.linalg.norm(q)
        want = list(quat_enu_flu_to_ned_frd(qu))
        assert quat_enu_flu_to_ned_frd_tuple(*qu) == pytest.approx(want, abs=1e-15)
        e = rng.uniform(-3, 3, 3)
        assert quat_from_euler_tuple(*e) == pytest.approx(list(quat_from_euler(*e)), abs=1e-15)
        a = [rng.normal(0.0, s, 3) for s in (0.5, 2.0, 8.0, 0.5, 2.0)]
        yaw = float(rng.uniform(-math.pi, math.pi))
        cmd = ctrl.command(a[0], a[1], a[2], yaw, a[3], a[4])
        roll, pitch, _, thrust = expert_command_batch(a[0], a[1], a[2], yaw, a[3], a[4], 0.9)
        assert (cmd.roll_rad, cmd.pitch_rad, cmd.thrust_n) == pytest.approx(
            (float(roll), float(pitch), float(thrust)), abs=1e-12
        )
    with pytest.raises(ValueError):
        quat_to_matrix(np.zeros(4))
    with pytest.raises(ValueError):
        ctrl.command([0.0, 0.0], [0.0] * 3, [0.0] * 3, 0.0, [0.0] * 3, [0.0] * 3)
    with pytest.raises(ValueError):
        ctrl.command([0.0, 0.0, math.nan], [0.0] * 3, [0.0] * 3, 0.0, [0.0] * 3, [0.0] * 3)


def test_the_fc_frames_of_a_lockstep_tick_go_out_with_the_tick():
    clock = SimClock()
    raw, peer = MemoryTransport.pair()
    wire = CommandWire(raw, clock, LinkModel(), np.random.default_rng(RNG_SEED), FaultSchedule(()))
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
