"""Bench group `world`: cost of the gap world's collision and clearance checks (one pose and a batch)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from emulator.world import Gap, LabVolume, World, rotation_zyx
from hil.benches import BenchRow, time_per_call


def collect(quick: bool) -> Iterator[BenchRow]:
    world = World(Gap.from_deg((0.0, 0.0, 1.5), roll_deg=60, height_m=0.16), LabVolume(), (0.45, 0.45, 0.12))
    min_time = 0.1 if quick else 0.5
    pos_in, pos_far = np.array([0.0, 0.0, 1.5]), np.array([-1.5, 0.0, 1.5])
    rot = rotation_zyx(math.radians(60), 0.0, 0.0)
    quat = np.array([math.cos(math.pi / 6), math.sin(math.pi / 6), 0.0, 0.0])
    in_gap = time_per_call(lambda: world.collision(pos_in, rot), min_time)
    yield BenchRow("world_collision_in_gap_us", 1e6 * in_gap, "us", "one pose in the wall slab, 3x3 attitude")
    far = time_per_call(lambda: world.collision(pos_far, quat), min_time)
    yield BenchRow("world_collision_far_us", 1e6 * far, "us", "one pose away from the wall, quaternion")
    rng = np.random.default_rng(0)
    n = 4096
    pos = np.array([0.0, 0.0, 1.5]) + rng.uniform(-0.4, 0.4, size=(n, 3))
    quats = rng.normal(size=(n, 4))
    per_batch = time_per_call(lambda: world.check_batch(pos, quats), min_time)
    yield BenchRow("world_collision_batch_us", 1e6 * per_batch / n, "us/pose", f"{n} poses near the gap")
