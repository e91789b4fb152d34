"""flightsim.world: worlds the simulated camera looks at, and the ground truth they define.

* :func:`load_world` reads ``configs/worlds/*.toml`` (:mod:`.config`) into a :class:`World`:
  a textured ground plane and obstacles — boxes (buildings), vertical cylinders (masts, trees),
  walls and small checker targets at exact positions;
* :class:`World` answers the geometry questions truth needs (:mod:`.geometry`): vectorized ray
  casting, clearance of a start position, horizontal ranges along bearings;
* :mod:`.truth`: per-frame truth — OBSTACLE_DISTANCE sectors, target positions and ranges — and
  the check that a camera sees something;
* :mod:`.textures`: the seeded procedural textures the renderer draws.

Frames (docs/derivations/frames.md): world = local NED (z down, ground at z = −ground.altitude_m), body FRD,
camera OpenCV.
"""

from .config import (
    BoxConfig,
    CylinderConfig,
    GroundConfig,
    SkyConfig,
    TargetConfig,
    WallConfig,
    WorldConfig,
    load_world_config,
    world_config_from_mapping,
)
from .geometry import GROUND, SKY, Obstacle, RayHits, World, load_world
from .truth import (
    N_SECTORS,
    SECTOR_WIDTH_DEG,
    TargetTruth,
    camera_view_fraction,
    check_camera_sees_something,
    sector_bearings_body,
    sector_truth,
    sectors_seen,
    target_truth,
)

__all__ = [
    "GROUND",
    "N_SECTORS",
    "SECTOR_WIDTH_DEG",
    "SKY",
    "BoxConfig",
    "CylinderConfig",
    "GroundConfig",
    "Obstacle",
    "RayHits",
    "SkyConfig",
    "TargetConfig",
    "TargetTruth",
    "WallConfig",
    "World",
    "WorldConfig",
    "camera_view_fraction",
    "check_camera_sees_something",
    "load_world",
    "load_world_config",
    "sector_bearings_body",
    "sector_truth",
    "sectors_seen",
    "target_truth",
    "world_config_from_mapping",
]
