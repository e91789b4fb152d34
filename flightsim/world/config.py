"""World description: the ``configs/worlds/*.toml`` files as frozen, validated dataclasses.

A world is a textured ground plane plus obstacles, all in the world frame (local NED at the
origin, docs/derivations/frames.md; positions in metres, ``_ne_m`` = (north, east), heights measured up):

* ``[[box]]`` — a building: an upright box on a rectangular footprint, turned by ``yaw_deg``;
* ``[[cylinder]]`` — a vertical cylinder: a mast, a chimney, a tree trunk;
* ``[[wall]]`` — a wall between two points, of some thickness (an upright box underneath);
* ``[[target]]`` — a small flat marker with a checker pattern whose centre corner sits exactly at
  ``position_ned_m`` (the six points of the seed-004 scenario are targets).

Each TOML table maps onto one dataclass through :func:`companion.config.from_mapping`, so unknown
or misspelt keys, wrong types and out-of-range values stop with a :class:`ConfigError` naming the
file, the table (``[box[2]]``) and the key.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.config import from_mapping, require, require_finite
from companion.errors import ConfigError
from companion.io.config_files import read_toml


#: Procedural texture styles of obstacle faces (see :mod:`flightsim.world.textures`).
OBSTACLE_TEXTURES = ("blocks", "facade", "plain")
#: Procedural texture styles of the ground plane.
GROUND_TEXTURES = ("fields", "blocks", "plain")
#: Largest texture edge generated for one face, texels (a coarser texel is used beyond it).
MAX_TEXTURE_PX = 4096


def _vec(name: str, v: Any, n: int) -> None:
    require(v is not None, f"{name} is required")
    require(isinstance(v, (tuple, list)) and len(v) == n, f"{name} must have {n} numbers, got {v!r}")
    for i, x in enumerate(v):
        require_finite(f"{name}[{i}]", x)


def _grey(name: str, v: float) -> None:
    require_finite(name, v)
    require(0.0 <= v <= 255.0, f"{name} must be a grey level in [0, 255], got {v!r}")


def _seed(name: str, v: int | None) -> None:
    require(v is None or (isinstance(v, int) and not isinstance(v, bool) and v >= 0), f"{name} must be an integer >= 0, got {v!r}")


@dataclass(frozen=True)
class GroundConfig:
    """The ground: an infinite horizontal plane at ``altitude_m`` above the world origin
    (NED z = −altitude_m), textured with a seeded tile of ``tile_px``² texels of ``texel_m``."""

    enabled: bool = True
    altitude_m: float = 0.0
    texel_m: float = 0.1
    tile_px: int = 2048
    texture: str = "fields"
    mean_grey: float = 110.0
    contrast: float = 1.0
    seed: int | None = None

    def __post_init__(self) -> None:
        require(isinstance(self.enabled, bool), f"enabled must be true/false, got {self.enabled!r}")
        require_finite("altitude_m", self.altitude_m)
        require_finite("texel_m", self.texel_m, positive=True)
        require(
            isinstance(self.tile_px, int) and 64 <= self.tile_px <= 8192 and self.tile_px & (self.tile_px - 1) == 0,
            f"tile_px must be a power of two in [64, 8192], got {self.tile_px!r}",
        )
        require(self.texture in GROUND_TEXTURES, f"texture must be one of {', '.join(GROUND_TEXTURES)}, got {self.texture!r}")
        _grey("mean_grey", self.mean_grey)
        require_finite("contrast", self.contrast, nonnegative=True)
        _seed("seed", self.seed)

    @property
    def z_ned(self) -> float:
        return -float(self.altitude_m)


@dataclass(frozen=True)
class SkyConfig:
    """A smooth, corner-free sky: grey level at the horizon and at the zenith (and, mirrored,
    towards the nadir where no ground is drawn)."""

    horizon_grey: float = 215.0
    zenith_grey: float = 165.0

    def __post_init__(self) -> None:
        _grey("horizon_grey", self.horizon_grey)
        _grey("zenith_grey", self.zenith_grey)


@dataclass(frozen=True)
class _Solid:
    """Keys shared by every obstacle."""

    name: str = ""
    texture: str = "blocks"
    grey: float = 128.0  # only for texture = "plain": the uniform grey level of every face
    contrast: float = 1.0
    seed: int | None = None
    base_altitude_m: float | None = None  # bottom above the origin; None = standing on the ground

    def _check_common(self) -> None:
        require(isinstance(self.name, str), f"name must be a string, got {self.name!r}")
        require(self.texture in OBSTACLE_TEXTURES, f"texture must be one of {', '.join(OBSTACLE_TEXTURES)}, got {self.texture!r}")
        _grey("grey", self.grey)
        require_finite("contrast", self.contrast, nonnegative=True)
        _seed("seed", self.seed)
        if self.base_altitude_m is not None:
            require_finite("base_altitude_m", self.base_altitude_m)


@dataclass(frozen=True)
class BoxConfig(_Solid):
    """A building: footprint ``size_m`` = (length along the ``yaw_deg`` direction, width across),
    centred on ``centre_ne_m``; ``yaw_deg`` 0 puts the length along north, 90 along east."""

    centre_ne_m: tuple[float, float] | None = None
    size_m: tuple[float, float] | None = None
    height_m: float | None = None
    yaw_deg: float = 0.0
    texture: str = "facade"

    def __post_init__(self) -> None:
        self._check_common()
        _vec("centre_ne_m", self.centre_ne_m, 2)
        _vec("size_m", self.size_m, 2)
        require(all(s > 0 for s in self.size_m), f"size_m must be > 0, got {self.size_m!r}")
        require(self.height_m is not None, "height_m is required")
        require_finite("height_m", self.height_m, positive=True)
        require_finite("yaw_deg", self.yaw_deg)


@dataclass(frozen=True)
class CylinderConfig(_Solid):
    """A vertical cylinder (mast, chimney, tree trunk) of ``radius_m`` around ``centre_ne_m``."""

    centre_ne_m: tuple[float, float] | None = None
    radius_m: float | None = None
    height_m: float | None = None

    def __post_init__(self) -> None:
        self._check_common()
        _vec("centre_ne_m", self.centre_ne_m, 2)
        require(self.radius_m is not None, "radius_m is required")
        require_finite("radius_m", self.radius_m, positive=True)
        require(self.height_m is not None, "height_m is required")
        require_finite("height_m", self.height_m, positive=True)


@dataclass(frozen=True)
class WallConfig(_Solid):
    """A wall from ``start_ne_m`` to ``end_ne_m`` (its centre line), ``thickness_m`` thick."""

    start_ne_m: tuple[float, float] | None = None
    end_ne_m: tuple[float, float] | None = None
    thickness_m: float = 0.3
    height_m: float | None = None

    def __post_init__(self) -> None:
        self._check_common()
        _vec("start_ne_m", self.start_ne_m, 2)
        _vec("end_ne_m", self.end_ne_m, 2)
        require(
            math.dist(self.start_ne_m, self.end_ne_m) > 0.01,
            f"start_ne_m and end_ne_m must be at least 0.01 m apart, got {self.start_ne_m!r} and {self.end_ne_m!r}",
        )
        require_finite("thickness_m", self.thickness_m, positive=True)
        require(self.height_m is not None, "height_m is required")
        require_finite("height_m", self.height_m, positive=True)


@dataclass(frozen=True)
class TargetConfig:
    """A flat square marker of side ``size_m`` centred exactly on ``position_ned_m`` (world NED).

    Its face is a ``cells`` × ``cells`` checker (``cells`` even, so the centre is a checker corner)
    of seeded grey levels; it faces the horizontal direction ``facing_deg`` (0 = its front looks
    north, 180 = south, towards a vehicle coming from the south) and is visible from both sides.
    """

    position_ned_m: tuple[float, float, float] | None = None
    size_m: float = 10.0
    facing_deg: float = 180.0
    cells: int = 2
    name: str = ""
    seed: int | None = None

    def __post_init__(self) -> None:
        _vec("position_ned_m", self.position_ned_m, 3)
        require_finite("size_m", self.size_m, positive=True)
        require_finite("facing_deg", self.facing_deg)
        require(
            isinstance(self.cells, int) and not isinstance(self.cells, bool) and 2 <= self.cells <= 16 and self.cells % 2 == 0,
            f"cells must be an even integer in [2, 16], got {self.cells!r}",
        )
        require(isinstance(self.name, str), f"name must be a string, got {self.name!r}")
        _seed("seed", self.seed)


@dataclass(frozen=True)
class WorldConfig:
    """A whole world file. ``seed`` seeds every texture that has no ``seed`` of its own;
    ``texel_m`` is the texel size of obstacle textures."""

    name: str = ""
    seed: int = 0
    texel_m: float = 0.05
    ground: GroundConfig = field(default_factory=GroundConfig)
    sky: SkyConfig = field(default_factory=SkyConfig)
    box: tuple[BoxConfig, ...] = ()
    cylinder: tuple[CylinderConfig, ...] = ()
    wall: tuple[WallConfig, ...] = ()
    target: tuple[TargetConfig, ...] = ()

    def __post_init__(self) -> None:
        require(isinstance(self.name, str), f"name must be a string, got {self.name!r}")
        _seed("seed", self.seed)
        require(self.seed is not None, "seed must be an integer >= 0")
        require_finite("texel_m", self.texel_m, positive=True)
        require(self.texel_m >= 0.005, f"texel_m must be >= 0.005 m, got {self.texel_m!r}")
        for kind, cls in _LISTS.items():
            items = getattr(self, kind)
            require(isinstance(items, tuple) and all(isinstance(x, cls) for x in items), f"{kind} must be a list of [[{kind}]] tables")
        names = [n for n in (x.name for kind in _LISTS for x in getattr(self, kind)) if n]
        dup = sorted({n for n in names if names.count(n) > 1})
        require(not dup, f"obstacle names must be unique; repeated: {', '.join(repr(n) for n in dup)}")


_LISTS: dict[str, type] = {"box": BoxConfig, "cylinder": CylinderConfig, "wall": WallConfig, "target": TargetConfig}


def world_config_from_mapping(data: dict, where: str = "") -> WorldConfig:
    """Build a :class:`WorldConfig` from a parsed TOML document (``[[box]]`` etc. as lists of tables)."""
    data = dict(data)
    prefix = f"{where}: " if where else ""
    try:
        for kind, cls in _LISTS.items():
            if kind not in data:
                continue
            items = data[kind]
            if isinstance(items, dict):
                raise ConfigError(f"[{kind}] must be written as an array of tables, [[{kind}]]")
            if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
                raise ConfigError(f"{kind} must be a list of [[{kind}]] tables, got {items!r}")
            data[kind] = tuple(from_mapping(cls, x, f"{kind}[{i}]") for i, x in enumerate(items))
        return from_mapping(WorldConfig, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{prefix}{exc}") from None


def load_world_config(path: str | os.PathLike) -> WorldConfig:
    """Parse and validate a world TOML; every problem is a :class:`ConfigError` naming the file."""
    path = Path(path)
    data = read_toml(path, "world")
    return world_config_from_mapping(data, str(path))
