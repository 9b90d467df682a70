"""Mocap tracker model: frame rate, latency, noise, occlusions, moving bodies, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from emulator.mocap import BodyPose, MocapConfig, MocapSystem, optitrack_latency_s
from emulator.physics.state import VehicleState
from emulator.world.geometry import Gap
from hil.link.linktrack import FrameError, MocapFrameEncoder, decode_frame, decode_mocap_payload

LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _fly(config: MocapConfig, duration_s: float = 2.0, step_s: float = 1e-3, seed: int = 0, truth=None):
    system = MocapSystem(config, np.random.default_rng(seed))
    frames = []
    for k in range(round(duration_s / step_s) + 1):
        t = k * step_s
        bodies = truth(t) if truth else {1: BodyPose(np.array([t, 0.0, 1.0]), LEVEL)}
        frames += [(t, f) for f in system.update(t, bodies)]
    return system, frames


@pytest.mark.parametrize("rate_hz", [100.0, 120.0, 240.0, 360.0])
def test_frames_come_at_the_configured_rate_with_the_optitrack_latency(rate_hz):
    cfg = MocapConfig(rate_hz=rate_hz, processing_s=0.0, pos_noise_m=0.0, att_noise_rad=0.0)
    _, frames = _fly(cfg, duration_s=1.0, step_s=1e-4)
    stamps = np.array([f.stamp_s for _, f in frames])
    assert np.allclose(np.diff(stamps), 1 / rate_hz)
    assert len(frames) == pytest.approx(rate_hz - optitrack_latency_s(rate_hz) * rate_hz, abs=1.5)
    # each frame is handed out at the first update after exposure + camera latency
    for t, f in frames:
        assert f.ready_s == pytest.approx(f.stamp_s + optitrack_latency_s(rate_hz))
        assert f.ready_s <= t + 1e-9 < f.ready_s + 1e-4 + 1e-9
    # the pose is the truth at exposure: x = t
    assert np.allclose([f.bodies[0].pos_m[0] for _, f in frames], stamps, atol=1e-4 + 1e-9)


def test_optitrack_figures_and_processing_latency():
    assert optitrack_latency_s(120) == pytest.approx(5.56e-3)
    assert optitrack_latency_s(240) == pytest.approx(4.17e-3)
    assert optitrack_latency_s(360) == pytest.approx(2.78e-3)
    cfg = MocapConfig(rate_hz=120, processing_s=2e-3, latency_s=1e-3)
    _, frames = _fly(cfg, duration_s=5.0, step_s=1e-4)
    extra = np.array([f.ready_s - f.stamp_s - 1e-3 for _, f in frames])
    assert extra.min() >= 0 and extra.mean() == pytest.approx(2e-3, rel=0.15)


def test_noise_has_the_configured_spread_and_attitude_stays_unit():
    cfg = MocapConfig(rate_hz=360, pos_noise_m=1e-3, att_noise_rad=2e-3)
    _, frames = _fly(cfg, duration_s=3.0, truth=lambda t: {1: BodyPose(np.array([0.0, 0.0, 1.0]), LEVEL)})
    pos = np.array([f.bodies[0].pos_m for _, f in frames])
    assert pos.std(axis=0) == pytest.approx([1e-3] * 3, rel=0.15)
    quats = np.array([f.bodies[0].quat_wxyz for _, f in frames])
    assert np.allclose(np.linalg.norm(quats, axis=1), 1.0)
    # small-angle: the vector part is half the rotation vector
    assert (2 * quats[:, 1:]).std(axis=0) == pytest.approx([2e-3] * 3, rel=0.15)


def test_occlusions_mark_bodies_invalid_in_runs():
    cfg = MocapConfig(rate_hz=120, occlusion_prob=0.01, occlusion_mean_s=0.1)
    system, frames = _fly(cfg, duration_s=20.0, step_s=2e-3)
    valid = np.array([f.bodies[0].valid for _, f in frames])
    invalid_frac = 1 - valid.mean()
    # about one start per 100 frames, each lasting ~12 frames: roughly 10 % invalid
    assert 0.04 < invalid_frac < 0.2
    assert system.stats.bodies_occluded == int((~valid).sum())
    starts = int(np.sum(valid[:-1] & ~valid[1:]))
    assert invalid_frac * len(valid) / starts > 5  # runs, not single frames


def test_vehicle_state_and_a_moving_gap_are_both_tracked():
    gap = Gap(centre_m=(0.0, 0.5, 2.1), roll_rad=-np.pi / 3)

    def truth(t):
        moved = Gap(centre_m=(0.0, 0.5 + 0.1 * t, 2.1), roll_rad=gap.roll_rad)
        return {1: VehicleState(time_s=t, pos_m=[-2.0, -1.0, 0.5]), 2: moved}

    cfg = MocapConfig(pos_noise_m=0.0, att_noise_rad=0.0)
    _, frames = _fly(cfg, duration_s=1.0, truth=truth)
    last = frames[-1][1]
    assert [b.body_id for b in last.bodies] == [1, 2]
    # sample and hold: the truth of the first update at or after exposure (1 ms steps here)
    assert last.bodies[1].pos_m[1] == pytest.approx(0.5 + 0.1 * last.stamp_s, abs=0.1 * 1e-3 + 1e-12)
    assert np.allclose(last.bodies[1].quat_wxyz, gap.quat_wxyz(), atol=1e-9)


def test_bad_input_gives_errors_or_invalid_bodies_not_crashes():
    with pytest.raises(ValueError, match="rate_hz"):
        MocapConfig(rate_hz=50)
    with pytest.raises(ValueError, match="occlusion_prob"):
        MocapConfig(occlusion_prob=2.0)
    system = MocapSystem(MocapConfig(latency_s=0.0, processing_s=0.0), np.random.default_rng(0))
    frames = system.update(0.0, {1: BodyPose(np.array([np.nan, 0.0, 0.0]), LEVEL)})
    assert not frames[0].bodies[0].valid
    with pytest.raises(TypeError, match="no pose"):
        system.update(1.0, {1: object()})
    # the plain-values form (x, y, z, qw, qx, qy, qz) the runner hands over: a short one is refused by
    # body, non-finite numbers make the body invalid, never a frame of NaN
    with pytest.raises(ValueError, match="body 1: a pose of plain values is 7 numbers, got 3"):
        system.update(2.0, {1: (0.0, 0.0, 1.0)})
    for bad in ((0.0, 0.0, 1.0, np.nan, 0.0, 0.0, 0.0), (np.inf, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0)):
        fresh = MocapSystem(MocapConfig(latency_s=0.0, processing_s=0.0), np.random.default_rng(0))
        (frame,) = fresh.update(0.0, {1: bad, 2: (1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0)})
        assert [b.valid for b in frame.bodies] == [False, True]
        assert all(np.isfinite(b.pos_m).all() for b in frame.bodies)


@pytest.mark.parametrize("occlusion_prob", [0.0, 0.2])
def test_plain_values_in_body_order_expose_the_frames_of_the_mapping(occlusion_prob):
    cfg = MocapConfig(occlusion_prob=occlusion_prob, occlusion_mean_s=0.02)
    by_map, by_values = (MocapSystem(cfg, np.random.default_rng(5)) for _ in range(2))
    got_map, got_values = [], []
    for k in range(1000):
        t = 0.0037 * k + (1.0 if k >= 500 else 0.0)  # (a second missed: its exposures are skipped)
        vehicle, gap = (t, 0.1, 1.0, 0.9, 0.1, 0.2, 0.3), (0.0, 0.5, 2.1, 0.866, -0.5, 0.0, 0.0)
        got_map += by_map.update_rows(t, {2: gap, 1: vehicle})
        by_values.expose_values(t, (1, 2), vehicle + gap)
        got_values += by_values.release_rows(t)
    assert got_values == got_map and len(got_map) > 400
    assert by_values.stats == by_map.stats


@pytest.mark.parametrize("occlusion_prob", [0.0, 0.2])
def test_a_tracker_with_an_encoder_keeps_each_frame_as_the_linktrack_frame_of_its_rows(occlusion_prob):
    cfg = MocapConfig(occlusion_prob=occlusion_prob, occlusion_mean_s=0.02)
    encoder = MocapFrameEncoder(module_id=3, node_id=4)
    by_rows = MocapSystem(cfg, np.random.default_rng(5))
    by_frames = MocapSystem(cfg, np.random.default_rng(5), encoder)
    got_rows, got_frames = [], []
    for k in range(1200):
        t = 0.0037 * k
        vehicle = (t, 0.1, 1.0 if k % 97 else np.nan, 0.9, 0.1, 0.2, 0.3)  # (now and then not seen)
        gap = (0.0, 0.5, 2.1, 0.866, -0.5, 0.0, 0.0)
        # one, two, then three bodies (the frame's buffers follow the count and the ids)
        ids, poses = ((1,), vehicle) if k < 300 else ((1, 2), vehicle + gap) if k < 800 else \
            ((1, 2, 200), vehicle + gap + (5.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0))
        by_rows.expose_values(t, ids, poses)
        by_frames.expose_values(t, ids, poses)
        got_rows += by_rows.released(t)
        got_frames += by_frames.released(t)
    assert len(got_frames) == len(got_rows) > 500 and by_frames.stats == by_rows.stats
    assert any(not valid for _, _, rows in got_rows for _, valid, _, _ in rows)
    for (ready_s, k, rows), (frame_ready_s, frame_k, frame) in zip(got_rows, got_frames, strict=True):
        assert (frame_ready_s, frame_k) == (ready_s, k)
        assert frame == encoder.encode(k, rows)
        packet = decode_mocap_payload(decode_frame(frame).nodes[0].data)
        assert [(b.body_id, b.valid) for b in packet.bodies] == [(r[0], r[1]) for r in rows]
    with pytest.raises(ValueError, match="LinkTrack bytes"):
        by_frames.release_rows(10.0)
    with pytest.raises(FrameError, match="body id"):
        by_frames.expose_values(10.0, (1, 300), vehicle + gap)
    with pytest.raises(ValueError, match="at most 5 bodies"):
        by_frames.expose_values(10.0, tuple(range(6)), gap * 6)


def test_frames_ready_out_of_their_order_leave_earliest_first_however_many_wait():
    """The tracker's queue (its room doubled when full): frames whose processing latency puts them out of
    their exposure order leave the earliest ready first (of two ready together, the lower number),
    released as they come or hundreds at once."""
    cfg = MocapConfig(rate_hz=360, processing_s=0.02)
    encoder = MocapFrameEncoder()
    as_they_come, at_once = (MocapSystem(cfg, np.random.default_rng(7), encoder) for _ in range(2))
    got: list = []
    for k in range(2000):
        t = k * 1e-3
        pose = (t, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0)
        as_they_come.expose_values(t, (1,), pose)
        at_once.expose_values(t, (1,), pose)
        got += as_they_come.released(t)
    assert [k for _, k, _ in got] != sorted(k for _, k, _ in got)  # (out of their exposure order)
    everything = at_once.released(10.0)
    assert len(everything) == at_once.stats.frames == 720
    assert everything == sorted(everything, key=lambda f: (f[0], f[1])) and everything[: len(got)] == got
    assert as_they_come.next_release_s() == everything[len(got)][0] and at_once.next_release_s() == np.inf


def test_a_late_first_update_does_not_replay_the_past():
    system = MocapSystem(MocapConfig(latency_s=0.0, processing_s=0.0), np.random.default_rng(0))
    frames = system.update(100.0, {1: BodyPose(np.zeros(3), LEVEL)})
    assert len(frames) == 1 and frames[0].stamp_s == pytest.approx(100.0)
    assert system.stats.frames_skipped == 12000
    assert system.next_event_s() == pytest.approx(100.0 + 1 / 120)
