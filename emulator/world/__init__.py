"""The gap world: a wall with a rectangular gap of any pose, the ground (z = 0) and the lab volume;
collision, clearance and crossing checks for the vehicle's body box (see the submodules for the exact
definitions)."""

from emulator.world.collision import EDGE_NAMES, Clearance, Obstacle, ObstacleCode, World
from emulator.world.crossing import CollisionEvent, Crossing, CrossingTracker
from emulator.world.geometry import (
    DEFAULT_WALL_HEIGHT_M,
    DEFAULT_WALL_WIDTH_M,
    Gap,
    LabVolume,
    matrix_to_quat,
    rotation_zyx,
)

__all__ = [
    "DEFAULT_WALL_HEIGHT_M",
    "DEFAULT_WALL_WIDTH_M",
    "EDGE_NAMES",
    "Clearance",
    "CollisionEvent",
    "Crossing",
    "CrossingTracker",
    "Gap",
    "LabVolume",
    "Obstacle",
    "ObstacleCode",
    "World",
    "matrix_to_quat",
    "rotation_zyx",
]
