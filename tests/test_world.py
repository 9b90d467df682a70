"""The gap world: gap frame, collision (wall, ground, lab), clearance and crossing detection.

Unless a test says otherwise the body box is 0.45 x 0.45 x 0.12 m (half sizes 0.225, 0.225, 0.06) and
the opening is 0.8 m wide (long side, e0) in a 5 cm thick wall (slab half thickness 0.025 m).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from emulator.physics.state import VehicleState
from emulator.world import (
    Clearance,
    CrossingTracker,
    Gap,
    LabVolume,
    Obstacle,
    ObstacleCode,
    World,
    rotation_zyx,
)
from emulator.world.box_kernel import quat_to_rot

BOX = (0.45, 0.45, 0.12)
C = (0.0, 0.0, 1.5)
S60, C60 = math.sin(math.pi / 3), math.cos(math.pi / 3)


def roll(deg: float) -> np.ndarray:
    return rotation_zyx(math.radians(deg), 0.0, 0.0)


def world(roll_deg: float = 0.0, height_m: float = 0.3, **kw: float) -> World:
    return World(Gap.from_deg(C, roll_deg=roll_deg, width_m=0.8, height_m=height_m, **kw), LabVolume(), BOX)


# --- gap frame --------------------------------------------------------------------------------------------
def test_gap_axes_follow_the_paper_convention() -> None:
    # roll -60 deg (the paper's test case): e0 = Rx(-60) y = (0, cos60, -sin60), e1 = x,
    # e2 = e0 x e1 = (0, -sin60, -cos60).
    axes = Gap.from_deg(C, roll_deg=-60).axes()
    np.testing.assert_allclose(axes[0], [0, C60, -S60], atol=1e-12)
    np.testing.assert_allclose(axes[1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(axes[2], [0, -S60, -C60], atol=1e-12)
    # yaw 90 deg turns the crossing direction to +y and the long side to -x.
    axes = Gap.from_deg(C, yaw_deg=90).axes()
    np.testing.assert_allclose(axes[1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(axes[0], [-1, 0, 0], atol=1e-12)


# --- clearance and wall collision ----------------------------------------------------------------------
def test_level_box_at_the_centre_of_a_level_gap() -> None:
    # margins: width (0.8 - 0.45)/2 = 0.175, height (0.3 - 0.12)/2 = 0.09 -> the height limits: 0.09
    w = world()
    clr = w.clearance(C, np.eye(3))
    assert clr.clearance_m == pytest.approx(0.09, abs=1e-12)
    assert clr.in_slab and clr.limiting_edge in ("+e2", "-e2")
    assert w.collision(C, np.eye(3)) is None


def test_clearance_does_not_depend_on_the_gap_yaw() -> None:
    # gap and body both yawed 90 deg: the same 0.09 m margin
    w = world(yaw_deg=90)
    assert w.clearance(C, rotation_zyx(0, 0, math.pi / 2)).clearance_m == pytest.approx(0.09, abs=1e-12)


def test_rolled_body_through_a_60deg_gap_with_2cm_to_spare() -> None:
    # opening height 0.12 + 2 * 0.02 = 0.16; body rolled like the gap: its 0.12 m side lies along e2,
    # so the margin is 0.08 - 0.06 = 0.02 (width: 0.4 - 0.225 = 0.175)
    w = world(roll_deg=60, height_m=0.16)
    clr = w.clearance(C, roll(60))
    assert clr.clearance_m == pytest.approx(0.02, abs=1e-9)
    assert clr.limiting_edge in ("+e2", "-e2")
    assert w.collision(C, roll(60)) is None
    # the same attitude as a quaternion (w, x, y, z) = (cos 30, sin 30, 0, 0), e.g. from VehicleState
    state = VehicleState(pos_m=C, quat_wxyz=[math.cos(math.pi / 6), math.sin(math.pi / 6), 0, 0])
    assert w.clearance(state.pos_m, state.quat_wxyz).clearance_m == pytest.approx(0.02, abs=1e-9)


def test_unrolled_body_clips_the_60deg_gap() -> None:
    # level body, gap rolled 60: along e2 = (0, sin60, -cos60) the box reaches 0.225 sin60 + 0.06 cos60
    # = 0.22486 m, the opening only 0.08 m: depth 0.14486 m past the edge
    w = world(roll_deg=60, height_m=0.16)
    clr = w.clearance(C, np.eye(3))
    assert clr.clearance_m == pytest.approx(0.08 - (0.225 * S60 + 0.06 * C60), abs=1e-9)
    assert w.collision(C, np.eye(3)) == Obstacle.WALL == "wall"
    # rolled 50 instead of 60: 10 deg off gives 0.08 - (0.225 sin10 + 0.06 cos10) = -0.01816 m
    s10, c10 = math.sin(math.radians(10)), math.cos(math.radians(10))
    assert w.clearance(C, roll(50)).clearance_m == pytest.approx(0.08 - (0.225 * s10 + 0.06 * c10), abs=1e-9)
    assert w.collision(C, roll(50)) == Obstacle.WALL


def test_clearance_uses_only_the_part_of_the_box_inside_the_slab() -> None:
    # body pitched 45 deg (x -> (k, 0, -k), z -> (k, 0, k), k = sqrt(2)/2): its front corner is at
    # x = 0.285 k, z = -0.165 k from the centre. Put that corner 1 cm into the slab (x = -0.015); the part
    # in the slab is the 1 cm tip, whose z spans corner z +- 0.01. With e2 = -z the tip reaches
    # v = 0.165 k + 0.01, so clearance = 0.15 - 0.165 k - 0.01 = 0.02333 m, although the whole box would
    # stick out 0.285 k - 0.15 = 0.05 m if projected.
    k = math.sqrt(0.5)
    pos = (-0.025 + 0.01 - 0.285 * k, 0.0, 1.5)
    pitch45 = rotation_zyx(0, math.pi / 4, 0)
    clr = world().clearance(pos, pitch45)
    assert clr == Clearance(pytest.approx(0.15 - 0.165 * k - 0.01, abs=1e-9), True, "+e2")
    assert world().collision(pos, pitch45) is None
    # a 0.2 m high opening: 0.1 - 0.165 k - 0.01 = -0.02667 m, a hit
    low = world(height_m=0.2)
    assert low.clearance(pos, pitch45).clearance_m == pytest.approx(0.1 - 0.165 * k - 0.01, abs=1e-9)
    assert low.collision(pos, pitch45) == Obstacle.WALL


def test_clearance_away_from_the_wall_is_the_projected_one() -> None:
    # 1 m before the wall: not in the slab; rolled 90 deg the 0.45 m side stands along z: 0.15 - 0.225
    clr = world().clearance((-1.0, 0.0, 1.5), roll(90))
    assert not clr.in_slab
    assert clr.clearance_m == pytest.approx(0.15 - 0.225, abs=1e-12)
    assert world().collision((-1.0, 0.0, 1.5), roll(90)) is None


def test_missing_the_opening_hits_the_wall_but_flying_around_it_does_not() -> None:
    w = world()
    assert w.collision((0.0, 0.7, 1.5), np.eye(3)) == Obstacle.WALL  # beside the opening, in the wall
    assert w.collision((0.0, 2.3, 1.5), np.eye(3)) is None  # beyond the 4 m wall's edge (2 + 0.225 < 2.3)
    assert w.collision((0.0, 2.2, 1.5), np.eye(3)) == Obstacle.WALL  # 2.2 - 0.225 < 2: clips the end


# --- ground and lab ---------------------------------------------------------------------------------------
def test_ground_contact() -> None:
    w = world()
    assert w.collision((-2.0, 0.0, 0.06), np.eye(3)) is None  # resting on the floor: touching only
    assert w.collision((-2.0, 0.0, 0.059), np.eye(3)) == Obstacle.GROUND  # 1 mm into the floor
    # rolled 30 deg at 0.12 m: lowest point 0.12 - (0.225 sin30 + 0.06 cos30) = -0.0445 m
    assert w.collision((-2.0, 0.0, 0.12), roll(30)) == Obstacle.GROUND
    assert w.collision((-2.0, 0.0, 0.17), roll(30)) is None  # 0.17 - 0.1645 > 0


def test_lab_boundary() -> None:
    w = world()
    assert w.collision((4.7, 0.0, 1.0), np.eye(3)) is None  # 4.7 + 0.225 = 4.925 < 5
    assert w.collision((4.9, 0.0, 1.0), np.eye(3)) == Obstacle.LAB_BOUNDARY  # 5.125 > 5
    assert w.collision((-2.0, 0.0, 3.95), np.eye(3)) == Obstacle.LAB_BOUNDARY  # top at 4.01 > 4
    assert w.collision((7.0, 0.0, 1.0), np.eye(3)) == Obstacle.LAB_BOUNDARY  # wholly outside


# --- batch helpers against the scalar kernel and against brute force ------------------------------------
def _random_poses(rng: np.random.Generator, gap: Gap, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n poses around the opening, and n // 4 more around the wall's outer edge at u = +-2 m."""
    local = rng.uniform([-0.7, -0.35, -0.45], [0.7, 0.35, 0.45], size=(n, 3))
    edge = rng.uniform([1.75, -0.35, -2.3], [2.25, 0.35, 2.3], size=(n // 4, 3))
    edge[:, 0] *= rng.choice([-1.0, 1.0], size=n // 4)
    local = np.concatenate([local, edge])
    pos = np.asarray(gap.centre_m) + local @ gap.axes()
    quats = rng.normal(size=(len(local), 4))
    return pos, quats


def test_batch_matches_the_scalar_path() -> None:
    rng = np.random.default_rng(7)
    gap = Gap.from_deg((0.5, -0.3, 1.4), roll_deg=30, pitch_deg=10, yaw_deg=20, width_m=0.7, height_m=0.3)
    w = World(gap, LabVolume(), BOX)
    pos, quats = _random_poses(rng, gap, 400)
    pos[:20, 2] = rng.uniform(0.0, 0.1, 20)  # some near the floor
    codes, clr, in_slab = w.check_batch(pos, quats)
    for i in range(len(pos)):
        hit, c = w.check(pos[i], quats[i])
        assert World.obstacle(codes[i]) == hit
        assert c.clearance_m == pytest.approx(clr[i], abs=1e-12) and c.in_slab == in_slab[i]
    assert {ObstacleCode.NONE, ObstacleCode.WALL, ObstacleCode.GROUND} <= set(codes.tolist())
    assert (codes[400:] == ObstacleCode.NONE).any() and (codes[400:] == ObstacleCode.WALL).any()


def test_clearance_and_collision_agree_with_sampled_box_points() -> None:
    # Sample each box on a 21^3 grid: if a sample lies in the wall's solid part, the exact check must
    # report the wall; the exact clearance is never above the one measured on the in-slab samples and
    # at most one grid step (0.0225 m along the long axes) below it.
    rng = np.random.default_rng(11)
    gap = Gap.from_deg((0.0, 0.0, 1.5), roll_deg=-40, yaw_deg=15, width_m=0.7, height_m=0.25)
    w = World(gap, LabVolume(), BOX)
    pos, quats = _random_poses(rng, gap, 150)
    g = np.linspace(-1, 1, 21)
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * (np.asarray(BOX) / 2)
    found_wall = 0
    for p, q in zip(pos, quats, strict=True):
        pts = (p + grid @ quat_to_rot(q).T - gap.centre_m) @ gap.axes().T  # gap coordinates
        u, n, v = pts[:, 0], pts[:, 1], pts[:, 2]
        in_slab = np.abs(n) <= 0.025
        in_block = in_slab & (np.abs(u) <= 2.0) & (np.abs(v) <= 2.0)
        solid = in_block & ((np.abs(u) > 0.35 + 1e-9) | (np.abs(v) > 0.125 + 1e-9))
        hit, clr = w.check(p, q)
        if solid.any():
            found_wall += 1
            assert hit == Obstacle.WALL
        if in_slab.any():
            sampled = min(0.35 - u[in_slab].max(), 0.35 + u[in_slab].min(),
                          0.125 - v[in_slab].max(), 0.125 + v[in_slab].min())
            assert clr.in_slab
            assert clr.clearance_m <= sampled + 1e-12
            assert clr.clearance_m >= sampled - 0.0225 * math.sqrt(3)
    assert found_wall > 20  # the sample really exercised wall hits


# --- crossings ---------------------------------------------------------------------------------------------
def test_crossing_through_a_60deg_gap() -> None:
    # straight along +x at 1 m/s, x = -0.503 + t, sampled every 10 ms: the centre meets the plane x = 0 at
    # t = 0.503 s, between the samples at 0.50 and 0.51 s; the aligned box keeps 0.02 m in the slab.
    w = world(roll_deg=60, height_m=0.16)
    tracker = CrossingTracker(w)
    for k in range(101):
        t = k * 0.01
        tracker.update(t, (-0.503 + t, 0.0, 1.5), roll(60))
    (crossing,) = tracker.crossings
    assert crossing.time_s == pytest.approx(0.503, abs=1e-9)
    assert crossing.direction == 1 and crossing.through_opening
    np.testing.assert_allclose(crossing.point_m, C, atol=1e-9)
    assert tracker.min_clearance_m == pytest.approx(0.02, abs=1e-9)
    assert tracker.first_collision is None and tracker.crossed_through_opening
    assert tracker.to_dict()["crossing_time_s"] == pytest.approx(0.503, abs=1e-9)


def test_crossing_time_and_point_are_interpolated() -> None:
    # samples at t = 0, 0.1, 0.2 s with x = -0.13, -0.03, 0.07 and y = 0, 0.01, 0.02:
    # x = 0 at t = 0.1 + 0.03 / 1.0 * 0.1 = 0.13 s, where y = 0.013
    tracker = CrossingTracker(world())
    for t, x, y in ((0.0, -0.13, 0.0), (0.1, -0.03, 0.01), (0.2, 0.07, 0.02)):
        tracker.update(t, (x, y, 1.5), np.eye(3))
    (crossing,) = tracker.crossings
    assert crossing.time_s == pytest.approx(0.13, abs=1e-12)
    np.testing.assert_allclose(crossing.point_m, (0.0, 0.013, 1.5), atol=1e-12)
    assert crossing.offset_m == pytest.approx((0.013, 0.0), abs=1e-12)


def test_missing_the_opening_is_not_a_crossing_through_it() -> None:
    # 0.6 m to the side of a 0.8 m wide opening: the centre passes the plane outside the rectangle
    tracker = CrossingTracker(world())
    for k in range(41):
        t = k * 0.01
        tracker.update(t, (-0.2 + t, 0.6, 1.5), np.eye(3))
    (crossing,) = tracker.crossings
    assert not crossing.through_opening and not tracker.crossed_through_opening
    assert crossing.offset_m[0] == pytest.approx(0.6, abs=1e-12)
    assert tracker.first_collision is not None and tracker.first_collision.obstacle == Obstacle.WALL
    assert tracker.min_clearance_m is not None and tracker.min_clearance_m < 0


def test_backward_crossing_and_bad_times() -> None:
    tracker = CrossingTracker(world())
    tracker.update(0.0, (0.1, 0.0, 1.5), np.eye(3))
    tracker.update(0.1, (-0.1, 0.0, 1.5), np.eye(3))
    assert tracker.crossings[0].direction == -1 and not tracker.crossed_through_opening
    with pytest.raises(ValueError, match="increase"):
        tracker.update(0.1, (-0.2, 0.0, 1.5), np.eye(3))


def test_a_batch_of_samples_tracks_like_the_samples_one_by_one() -> None:
    # a weaving path through and back past a 45 deg gap, hitting the wall on the way: the batch API (what
    # the run recorder uses) must give the crossings, clearance and first collision of one-by-one calls
    w = world(roll_deg=45, height_m=0.3)
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.001, 0.01, 300))
    pos = np.stack([0.4 * np.sin(12 * t), 0.25 * np.sin(7 * t), 1.5 + 0.1 * np.cos(5 * t)], axis=1)
    q = rng.normal(size=(300, 4)) * 0.05 + [1, 0, 0, 0]
    q /= np.linalg.norm(q, axis=1)[:, None]
    codes, clr, in_slab = w.check_states_values(pos, q)
    n = (pos - w.gap.centre_m) @ w.gap.axes()[1]
    one = CrossingTracker(w)
    for i in range(300):
        one.update(t[i], pos[i], q[i])
    batch = CrossingTracker(w)
    done = []
    for lo, hi in ((0, 1), (1, 49), (49, 50), (50, 300)):  # batches of every size, a crossing across two
        got = batch.add_checked_batch(t[lo:hi], pos[lo:hi], codes[lo:hi], clr[lo:hi], in_slab[lo:hi],
                                      n[lo:hi])
        done += [(lo + i, c) for i, c in got]
    assert len(one.crossings) >= 4 and one.first_collision is not None and one.min_clearance_m is not None
    assert [c for _, c in done] == list(batch.crossings)
    assert [(c.direction, c.through_opening) for c in batch.crossings] == \
        [(c.direction, c.through_opening) for c in one.crossings]
    for a, b in zip(batch.crossings, one.crossings, strict=True):
        assert a.time_s == pytest.approx(b.time_s, abs=1e-12)
        np.testing.assert_allclose(a.point_m, b.point_m, atol=1e-12)
    assert all(t[i - 1] < c.time_s <= t[i] for i, c in done)
    assert batch.min_clearance_m == one.min_clearance_m
    assert batch.min_clearance_time_s == one.min_clearance_time_s
    assert batch.first_collision == one.first_collision and batch.samples == one.samples == 300
    with pytest.raises(ValueError, match="increase"):
        batch.add_checked_batch(t[-2:], pos[-2:], codes[-2:], clr[-2:], in_slab[-2:], n[-2:])


# --- bad input ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("pos", "att", "match"),
    [
        ((0.0, 0.0), np.eye(3), "shape"),
        ((0.0, math.nan, 1.0), np.eye(3), "non-finite"),
        ((0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 0.0), "quaternion"),
        ((0.0, 0.0, 1.0), np.eye(2), "attitude"),
        ((0.0, 0.0, 1.0), np.full((3, 3), math.inf), "non-finite"),
    ],
)
def test_bad_poses_are_clear_errors(pos: tuple, att: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        world().collision(pos, att)


def test_bad_world_values_are_clear_errors() -> None:
    with pytest.raises(ValueError, match="width_m"):
        Gap(width_m=-0.5)
    with pytest.raises(ValueError, match="long side"):
        Gap(width_m=0.3, height_m=0.5)
    with pytest.raises(ValueError, match="larger than the opening"):
        Gap(wall_width_m=0.5)
    with pytest.raises(ValueError, match="centre_m"):
        Gap(centre_m=(0.0, "a", 1.0))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="below max_m"):
        LabVolume(min_m=(0, 0, 0), max_m=(1, -1, 1))
    with pytest.raises(ValueError, match="body_box_m"):
        World(body_box_m=(0.4, 0.0, 0.1))
    with pytest.raises(ValueError, match="positions"):
        world().check_batch(np.zeros((3, 3)), np.tile(np.eye(3), (2, 1, 1)))
