"""The emulator side's per-tick fast paths give what the general code gives: one-node LinkTrack frames
and mocap payloads from rows are the documented encoders' bytes, the radio's jitter drawn in blocks is
the same sequence as one draw per packet, the fused world kernel is `World.check`, and the lockstep
tick's NAMED_VALUE_INT decodes to pymavlink's message."""

from __future__ import annotations

import math

import numpy as np
import pytest

from emulator.mocap import MocapConfig, MocapSystem, pose_of
from emulator.physics.state import VehicleState
from emulator.uwb import UwbConfig, UwbRadio
from emulator.world import EDGE_NAMES, Gap, LabVolume, World
from hil.link.linktrack import (
    BodySample,
    FrameError,
    MocapPacket,
    Node,
    NodeFrame,
    encode_frame,
    encode_mocap_payload,
    encode_mocap_rows,
    encode_node_frame,
)
from hil.link.mavlink import decode_frame, mav


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


def test_radio_jitter_drawn_in_blocks_is_the_per_packet_sequence():
    cfg = UwbConfig(latency_s=0.01, jitter_s=0.004)
    radio = UwbRadio(cfg, np.random.default_rng(9))
    ref = np.random.default_rng(9)
    arrivals = []
    for k in range(300):  # past several blocks
        assert radio.send(k * 0.01, b"x" * 40)
        arrivals.extend(d.arrival_s for d in radio.update(k * 0.01 + 1.0))
    last = -math.inf
    for k, got in enumerate(arrivals):
        air_end = k * 0.01 + cfg.air_time_s(40)
        want = max(air_end + max(0.0, cfg.latency_s + ref.normal(0.0, cfg.jitter_s)), last)
        last = want
        assert got == want


def test_mocap_rows_and_frames_agree():
    state = VehicleState(pos_m=np.array([1.0, 2.0, 1.5]), quat_wxyz=np.array([0.9, 0.1, 0.2, 0.3]))
    truth = {1: state, 2: pose_of(Gap())}
    a = MocapSystem(MocapConfig(occlusion_prob=0.2), np.random.default_rng(3))
    b = MocapSystem(MocapConfig(occlusion_prob=0.2), np.random.default_rng(3))
    for k in range(1, 100):
        frames, rows = a.update(k / 120, truth), b.update_rows(k / 120, truth)
        assert len(frames) == len(rows)
        for f, r in zip(frames, rows, strict=True):
            assert (f.frame_no, f.stamp_s, f.ready_s) == (r.frame_no, r.stamp_s, r.ready_s)
            for body, (body_id, valid, _, values) in zip(f.bodies, r.rows, strict=True):
                assert (body.body_id, body.valid) == (body_id, valid)
                assert [*body.pos_m.tolist(), *body.quat_wxyz.tolist()] == values
    assert a.stats == b.stats and a.stats.bodies_occluded > 0


def test_fused_world_kernel_is_world_check():
    world = World(Gap.from_deg((2.0, 0.0, 1.5), -60, 0, 0, width_m=0.6, height_m=0.3), LabVolume())
    rng = np.random.default_rng(5)
    for _ in range(300):
        pos = rng.normal((2.0, 0.0, 1.0), (0.4, 0.3, 1.0))
        quat = rng.normal(size=4)
        hit, clr = world.check(pos, quat)
        code, clr_m, in_slab, edge = world.check_state_values(pos, quat)
        assert (World.obstacle(code), clr_m, in_slab, EDGE_NAMES[edge]) == (
            hit, clr.clearance_m, clr.in_slab, clr.limiting_edge)
        assert world.check_state(pos, quat) == (hit, clr)


def test_named_value_int_decodes_to_pymavlinks_message():
    ref = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    for name, value in ((b"mocap_n", 123), (b"abcdefghij", -5), (b"", 0)):
        frame = bytes(ref.named_value_int_encode(1234, name, value).pack(ref))
        mine, theirs = decode_frame(frame), ref.decode(bytearray(frame))
        assert mine.to_dict() == theirs.to_dict() and mine.get_msgbuf() == theirs.get_msgbuf()
