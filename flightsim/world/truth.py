"""Ground truth per frame: OBSTACLE_DISTANCE sectors, target positions and ranges, camera checks.

Sector convention (docs/derivations/sectors.md, MAVLink OBSTACLE_DISTANCE with MAV_FRAME_BODY_FRD):
72 sectors of 5°, sector ``i`` centred on the body bearing 5·i degrees clockwise from forward.
Bearings are measured in the horizontal plane using the vehicle's yaw only (roll and pitch do
not tilt the sectors): sector ``i`` looks along the world bearing ``yaw + 5·i°``.

Sector width — what "the nearest obstacle in the sector" means here: the sector is the horizontal
wedge of ±2.5° around its centre bearing, and its truth is the smallest horizontal distance from
the vehicle to any point of an obstacle footprint *inside that wedge*.  Footprints are convex
(rectangles, circles, the segment of a target), so this minimum is exact and cheap: it is either
the footprint's closest point (when that point lies inside the wedge) or the first hit of one of
the two edge rays.  An obstacle counts only if its vertical extent overlaps the band
``[z − band, z + band]`` around the vehicle (``band_half_height_m``), as the companion reports
points within a vertical band around the flight path; the ground never counts.

Unseen sectors are NaN in :func:`sector_truth`: a sector is *seen* (in view) when the horizontal
direction of its centre bearing, from the camera centre at the camera's own height, projects inside
the image (through the companion's camera model, distortion and mount included).  Sectors with
nothing within ``max_distance_m`` are ``inf``.

Scoring over 360° (docs/derivations/obstacle_map.md: the local obstacle map publishes remembered
obstacles beside and behind the vehicle): :func:`sector_truth_360` gives the true distance of *all*
72 sectors and the in-view mask separately, so claims outside the camera's view can be scored too.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.core.camera import CameraConfig, CameraModel
from companion.errors import ConfigError, InputError

from .geometry import SKY, World

N_SECTORS = 72
SECTOR_WIDTH_DEG = 5.0
#: Default half-height of the vertical band in which obstacles count for sectors, metres.
DEFAULT_BAND_HALF_HEIGHT_M = 10.0


def sector_bearings_body(n: int = N_SECTORS) -> np.ndarray:
    """Centre bearings of the sectors, rad, clockwise from body forward: 0, 5°, …, 355°."""
    return np.radians(np.arange(n) * (360.0 / n))


def _yaw(R_world_body: np.ndarray) -> float:
    R = np.asarray(R_world_body, float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise InputError("R_world_body must be a finite 3×3 rotation")
    return math.atan2(R[1, 0], R[0, 0])


@functools.lru_cache(maxsize=16)
def _image_border_normalized(config: CameraConfig, samples: int = 64) -> np.ndarray:
    """Undistorted normalized coordinates of the image outline (pixel-area edges), a polygon."""
    w, h = config.width, config.height
    xs = np.linspace(-0.5, w - 0.5, samples)
    ys = np.linspace(-0.5, h - 0.5, samples)
    border = np.concatenate(
        [
            np.stack([xs, np.full_like(xs, -0.5)], 1),
            np.stack([np.full_like(ys, w - 0.5), ys], 1),
            np.stack([xs[::-1], np.full_like(xs, h - 0.5)], 1),
            np.stack([np.full_like(ys, -0.5), ys[::-1]], 1),
        ]
    )
    return CameraModel(config).pixels_to_normalized(border)


@functools.lru_cache(maxsize=16)
def _image_border_polygon(config: CameraConfig) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The image outline as OpenCV takes it (float32 contour) and its bounding box (x0, x1, y0, y1)."""
    poly = _image_border_normalized(config).astype(np.float32).reshape(-1, 1, 2)
    poly.flags.writeable = False
    xy = poly.reshape(-1, 2)
    return poly, (float(xy[:, 0].min()), float(xy[:, 0].max()), float(xy[:, 1].min()), float(xy[:, 1].max()))


@functools.lru_cache(maxsize=16)
def _camera_model(config: CameraConfig) -> CameraModel:
    return CameraModel(config)  # holds nothing but the (frozen) config's arrays


def _directions_in_image(config: CameraConfig, d_cam: np.ndarray) -> np.ndarray:
    """Boolean (N,): camera-frame directions in front of the camera whose pixel lies in the image."""
    d_cam = np.asarray(d_cam, float).reshape(-1, 3)
    front = d_cam[:, 2] > 1e-9
    out = np.zeros(len(d_cam), bool)
    if not np.any(front):
        return out
    poly, (bx0, bx1, by0, by1) = _image_border_polygon(config)
    xy = d_cam[front, :2] / d_cam[front, 2:3]
    # OpenCV tests the point in float32: one outside the outline's bounding box is outside (-1)
    # without asking it (most of the sectors in front of a narrow camera)
    x32, y32 = xy.astype(np.float32).T.tolist()
    out[front] = [bx0 <= x <= bx1 and by0 <= y <= by1 and cv2.pointPolygonTest(poly, (x, y), False) >= 0
                  for x, y in zip(x32, y32)]
    return out


_BEARINGS = np.radians(np.arange(N_SECTORS) * (360.0 / N_SECTORS))  # sector_bearings_body(), for internal use
_BEARINGS.flags.writeable = False


def sectors_seen(R_world_body: np.ndarray, p_world_body: np.ndarray, camera_config: CameraConfig) -> np.ndarray:
    """(72,) bool: sectors whose centre bearing (horizontal, at the camera's height) is in the image."""
    yaw = _yaw(R_world_body)
    model = _camera_model(camera_config)
    R_world_cam, _ = model.camera_pose(np.asarray(R_world_body, float), np.asarray(p_world_body, float))
    b = yaw + _BEARINGS
    d_world = np.stack([np.cos(b), np.sin(b), np.zeros_like(b)], 1)
    return _directions_in_image(camera_config, d_world @ R_world_cam)


def sector_truth_360(
    world: World,
    R_world_body: np.ndarray,
    p_world_body: np.ndarray,
    camera_config: CameraConfig | None,
    max_distance_m: float,
    *,
    band_half_height_m: float | None = DEFAULT_BAND_HALF_HEIGHT_M,
) -> tuple[np.ndarray, np.ndarray]:
    """``(distance (72,), in_view (72,) bool)``: the true horizontal distance of every sector over
    360° (``inf`` where nothing lies within ``max_distance_m``; never NaN) and which sectors the
    camera sees (all True when ``camera_config`` is None).  docs/derivations/sectors.md (sectors),
    docs/derivations/obstacle_map.md (360°)."""
    dist = sector_truth(world, R_world_body, p_world_body, None, max_distance_m, band_half_height_m=band_half_height_m)
    if camera_config is None:
        return dist, np.ones(N_SECTORS, bool)
    return dist, sectors_seen(R_world_body, np.asarray(p_world_body, float).reshape(3), camera_config)


def sector_truth(
    world: World,
    R_world_body: np.ndarray,
    p_world_body: np.ndarray,
    camera_config: CameraConfig | None,
    max_distance_m: float,
    *,
    band_half_height_m: float | None = DEFAULT_BAND_HALF_HEIGHT_M,
) -> np.ndarray:
    """True horizontal distance (m) to the nearest obstacle in each of the 72 sectors.

    ``inf`` where nothing lies within ``max_distance_m``; NaN for sectors the camera does not see
    (pass ``camera_config=None`` to get every sector).  See the module docstring for the wedge,
    band and visibility rules.
    """
    p = np.asarray(p_world_body, float).reshape(3)
    if not np.all(np.isfinite(p)):
        raise InputError("p_world_body contains NaN or inf")
    if not (max_distance_m > 0):
        raise InputError(f"max_distance_m must be > 0, got {max_distance_m}")
    yaw = _yaw(R_world_body)
    half = math.radians(SECTOR_WIDTH_DEG / 2.0)
    centres = yaw + _BEARINGS
    out = np.full(N_SECTORS, np.inf)
    if world.obstacles:
        edges = centres - half  # edge k is the left edge of sector k and the right edge of sector k-1
        ray = world.horizontal_distances(p, edges, band_half_height_m)  # (72, M)
        edge_min = np.minimum(ray, np.roll(ray, -1, axis=0))  # sector i: edges i and i+1
        dist, bear = world.closest_horizontal(p, band_half_height_m)
        off = (bear[None, :] - centres[:, None] + math.pi) % (2 * math.pi) - math.pi
        inside = (np.abs(off) <= half + 1e-12) | (dist[None, :] == 0.0)
        closest = np.where(inside, dist[None, :], np.inf)
        out = np.min(np.minimum(edge_min, closest), axis=1)
    out[out > max_distance_m] = np.inf
    if camera_config is not None:
        out[~sectors_seen(R_world_body, p, camera_config)] = np.nan
    return out


@dataclass(frozen=True)
class TargetTruth:
    """True state of the world's targets seen from one camera pose.

    ``p_world`` (M, 3) target centres (the checker's centre corner), ``range_m`` (M,) Euclidean
    distance from the camera centre.  With the camera attitude: ``p_cam`` (M, 3) in the camera
    frame and ``depth_m`` = its z.  With the camera model too: ``pixel`` (M, 2) where the centre
    projects (NaN behind the camera), ``in_image``, and ``occluded`` (another surface lies on the
    line of sight).
    """

    names: tuple[str, ...]
    p_world: np.ndarray
    range_m: np.ndarray
    p_cam: np.ndarray | None = None
    depth_m: np.ndarray | None = None
    pixel: np.ndarray | None = None
    in_image: np.ndarray | None = None
    occluded: np.ndarray | None = None

    @property
    def visible(self) -> np.ndarray | None:
        if self.in_image is None or self.occluded is None:
            return None
        return self.in_image & ~self.occluded


def target_truth(
    world: World, p_world_cam: np.ndarray, R_world_cam: np.ndarray | None = None, camera_config: CameraConfig | None = None
) -> TargetTruth:
    """True positions and ranges of the world's targets from a camera at ``p_world_cam``."""
    targets = world.targets
    c = np.asarray(p_world_cam, float).reshape(3)
    P = np.array([t.centre for t in targets], float).reshape(-1, 3)
    names = tuple(t.name for t in targets)
    rng = np.linalg.norm(P - c, axis=1)
    if R_world_cam is None:
        return TargetTruth(names, P, rng)
    R = np.asarray(R_world_cam, float)
    p_cam = (P - c) @ R
    if camera_config is None:
        return TargetTruth(names, P, rng, p_cam, p_cam[:, 2].copy())
    model = CameraModel(camera_config)
    pixel = np.full((len(P), 2), np.nan)
    front = p_cam[:, 2] > 1e-9
    if np.any(front):
        pixel[front] = model.project(p_cam[front])
    in_image = _directions_in_image(camera_config, p_cam) if len(P) else np.zeros(0, bool)
    occluded = np.zeros(len(P), bool)
    if len(P):
        hits = world.raycast(np.broadcast_to(c, P.shape), P - c)  # t = 1 at the target centre
        idx = np.array([t.index for t in targets])
        occluded = (hits.index != idx) & (hits.distance < 1.0 - 1e-6)
    return TargetTruth(names, P, rng, p_cam, p_cam[:, 2].copy(), pixel, in_image, occluded)


def camera_view_fraction(
    world: World,
    camera_config: CameraConfig,
    R_world_cam: np.ndarray,
    p_world_cam: np.ndarray,
    *,
    max_range_m: float = 10000.0,
    grid: tuple[int, int] = (64, 48),
) -> tuple[float, int]:
    """Fraction of a pixel grid whose rays hit the ground or an obstacle within ``max_range_m``,
    and the number of targets visible (in the image, unoccluded, within range)."""
    model = CameraModel(camera_config)
    gx, gy = grid
    us = (np.arange(gx) + 0.5) * camera_config.width / gx - 0.5
    vs = (np.arange(gy) + 0.5) * camera_config.height / gy - 0.5
    uv = np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2)
    rays = model.unproject(uv) @ np.asarray(R_world_cam, float).T
    hits = world.raycast(np.asarray(p_world_cam, float), rays, max_range_m)
    frac = float(np.mean(hits.index != SKY))
    n_targets = 0
    if world.targets:
        tt = target_truth(world, p_world_cam, R_world_cam, camera_config)
        n_targets = int(np.sum(tt.visible & (tt.range_m <= max_range_m)))
    return frac, n_targets


def check_camera_sees_something(
    world: World,
    camera_config: CameraConfig,
    R_world_cam: np.ndarray,
    p_world_cam: np.ndarray,
    *,
    min_fraction: float = 0.005,
    max_range_m: float = 10000.0,
    what: str = "camera",
) -> float:
    """Raise :class:`ConfigError` if the camera sees only sky: fewer than ``min_fraction`` of its
    pixels hit the ground or an obstacle within ``max_range_m`` and no target is visible.
    Returns the fraction of pixels that see a surface."""
    frac, n_targets = camera_view_fraction(world, camera_config, R_world_cam, p_world_cam, max_range_m=max_range_m)
    if frac < min_fraction and n_targets == 0:
        R = np.asarray(R_world_cam, float)
        axis = R[:, 2]
        heading = math.degrees(math.atan2(axis[1], axis[0])) % 360.0
        elev = math.degrees(math.asin(max(-1.0, min(1.0, -axis[2]))))
        p = np.asarray(p_world_cam, float).reshape(3)
        raise ConfigError(
            f"{world.source}: the {what} at NED ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) looking at heading {heading:.1f}° "
            f"and elevation {elev:+.1f}° sees nothing but sky: {100 * frac:.2f}% of its pixels hit a surface within "
            f"{max_range_m:.0f} m (need {100 * min_fraction:.2f}%) and no target is in view"
        )
    return frac
