"""Where new corners are wanted most: the detection priority region (docs/derivations/sectors.md).

The tracker refills with the strongest Harris corners, which gather where the image is busiest;
the sectors only count points in a vertical band around the flight path (``[sectors]``), and an
in-view sector without a live point stays unknown (65535), which ArduPilot treats as no
constraint and PX4 refuses to fly into.  This module gives the tracker an (H, W) bool image of the
pixels whose corners matter most:

* **band**: pixels whose viewing ray, in the levelled body frame (yaw kept, roll and pitch
  removed, as in :mod:`companion.core.sectors`), lies within the sector band at a typical range
  ``band_range_m``: ``|tan(elevation) − tan γ| ≤ band_half_height_m / band_range_m`` (``"metres"``
  band) or ``|elevation − γ| ≤ band_half_angle_deg`` (``"degrees"``), γ the flight-path angle
  (0 below ``flight_path_min_speed_mps``, clamped to ``flight_path_max_angle_deg``);
* within the band, the columns of the sectors in view that held **no live point** in the previous
  frame (no converged point of the camera's own, obstacle or clear; remembered map points do not
  count: they give no new range), and the columns within ``path_half_width_deg`` of the
  **direction of travel** (the horizontal bearing of the velocity; when slower than
  ``flight_path_min_speed_mps`` there is no direction and the whole band counts).

Pure and vectorized: the rays of a coarse pixel grid (every ``stride`` px) are classified at once
and the result is enlarged to full size with nearest-neighbour resampling (``stride`` defaults to
width / 80, at least 4 px).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from companion.core import jit as _jit
from companion.core.camera import CameraModel
from companion.core.frames import euler_zyx_to_R, euler_zyx_to_R_scalar
from companion.core.sectors import SECTOR_COUNT, SectorConfig, sector_index
from companion.errors import InputError


def flight_path(config: SectorConfig, v_level) -> tuple[float, float | None]:
    """``(γ, ψ)``: flight-path angle (climb +, rad; the sectors' rule) and horizontal bearing of
    travel in the levelled body frame (rad, clockwise from forward; None when too slow)."""
    if v_level is None:
        return 0.0, None
    v = np.asarray(v_level, dtype=float).reshape(3)
    if not np.all(np.isfinite(v)):
        return 0.0, None
    speed = float(np.linalg.norm(v))
    if speed < config.flight_path_min_speed_mps or speed == 0.0:
        return 0.0, None
    lim = math.radians(config.flight_path_max_angle_deg)
    gamma = max(-lim, min(lim, math.atan2(-v[2], math.hypot(v[0], v[1]))))
    h = math.hypot(v[0], v[1])
    psi = math.atan2(v[1], v[0]) if h >= config.flight_path_min_speed_mps * 0.5 else None
    return gamma, psi


def detection_priority(
    camera: CameraModel,
    sectors: SectorConfig,
    *,
    roll_pitch_rad: tuple[float, float] = (0.0, 0.0),
    velocity_body=None,
    live_points=None,
    band_range_m: float = 8.0,
    path_half_width_deg: float = 15.0,
    stride: int | None = None,
) -> np.ndarray:
    """(H, W) bool priority region for new corners (see module docstring).

    ``camera``: the camera model (intrinsics, distortion and mount ``R_cam_body``);
    ``roll_pitch_rad``: vehicle attitude at exposure; ``velocity_body``: velocity in body FRD;
    ``live_points``: (72,) live points per sector in the previous frame (None: no previous frame,
    so no sector has a live point: the whole band).
    """
    c = camera.config
    if stride is None:
        stride = max(4, int(round(c.width / 80)))  # 4 px at 320 wide, 8 px at 640: ~5000 rays
    if not (isinstance(stride, int) and stride >= 1):
        raise InputError(f"stride must be an integer >= 1, got {stride!r}")
    if not (math.isfinite(band_range_m) and band_range_m > 0):
        raise InputError(f"band_range_m must be finite and > 0, got {band_range_m!r}")
    rp = tuple(float(a) for a in roll_pitch_rad)
    if len(rp) != 2 or not all(math.isfinite(a) for a in rp):
        raise InputError(f"roll_pitch_rad must be two finite angles, got {roll_pitch_rad!r}")
    # body → levelled (the scalar form in the kernel path: the same matrix, bit for bit)
    R_lb = euler_zyx_to_R_scalar(rp[0], rp[1], 0.0) if _jit.ENABLED else euler_zyx_to_R(rp[0], rp[1], 0.0)
    v_level = None if velocity_body is None else R_lb @ np.asarray(velocity_body, dtype=float).reshape(3)
    gamma, psi = flight_path(sectors, v_level)

    us, vs, rays = camera.grid_rays(stride)  # (N, 3) camera, cached per camera
    lp = None
    if live_points is not None:
        lp = np.asarray(live_points).reshape(-1)
        if lp.shape != (SECTOR_COUNT,):
            raise InputError(f"live_points must have {SECTOR_COUNT} entries, got {lp.shape}")
    if _jit.ENABLED:
        small = _priority_grid_k(_writable(rays), len(us), len(vs), R_lb @ camera.R_cam_body.T, sectors.band_mode == "metres",
                                 math.tan(gamma), sectors.band_half_height_m / band_range_m, gamma,
                                 math.radians(sectors.band_half_angle_deg), psi is not None, 0.0 if psi is None else psi,
                                 math.radians(path_half_width_deg), lp is not None,
                                 _NO_LIVE if lp is None else lp.astype(float))
        return small.astype(bool) if stride == 1 else _enlarge_k(small, stride, c.width, c.height).view(bool)
    d = rays @ (R_lb @ camera.R_cam_body.T).T  # camera → body → levelled
    horiz = np.hypot(d[:, 0], d[:, 1])
    up = -d[:, 2]
    if sectors.band_mode == "metres":
        tan_e = up / np.maximum(horiz, 1e-9)
        band = np.abs(tan_e - math.tan(gamma)) <= sectors.band_half_height_m / band_range_m
    else:
        band = np.abs(np.arctan2(up, horiz) - gamma) <= math.radians(sectors.band_half_angle_deg)
    bearing = np.arctan2(d[:, 1], d[:, 0])
    if psi is None:
        want = np.ones(len(d), bool)
    else:
        off = np.abs((bearing - psi + math.pi) % (2 * math.pi) - math.pi)
        want = off <= math.radians(path_half_width_deg)
    if live_points is None:  # no previous frame: no sector has a live point yet
        want[:] = True
    else:
        want |= lp[sector_index(bearing)] <= 0
    small = (band & want).reshape(len(vs), len(us)).astype(np.uint8)
    if stride == 1:
        return small.astype(bool)
    # each coarse sample stands for the stride × stride block around it
    big = cv2.resize(small, (len(us) * stride, len(vs) * stride), interpolation=cv2.INTER_NEAREST)[: c.height, : c.width]
    if big.shape != (c.height, c.width):
        big = cv2.copyMakeBorder(big, 0, c.height - big.shape[0], 0, c.width - big.shape[1], cv2.BORDER_REPLICATE)
    return big.view(bool)


_NO_LIVE = np.zeros(SECTOR_COUNT)
_WRITABLE: dict = {}


def _writable(rays: np.ndarray) -> np.ndarray:
    """A writable copy of a camera's cached grid rays, made once (numba loops over read-only arrays
    run at half speed)."""
    got = _WRITABLE.get(id(rays))
    if got is None or got[0] is not rays:
        got = _WRITABLE[id(rays)] = (rays, np.array(rays, float))
        if len(_WRITABLE) > 16:
            _WRITABLE.pop(next(iter(_WRITABLE)))
    return got[1]


def live_points_per_sector(sectors_prev) -> np.ndarray | None:
    """(72,) live (camera, not remembered) converged points behind each sector of a
    :class:`~companion.core.sectors.Sectors` (obstacle and clear), or None without one."""
    if sectors_prev is None:
        return None
    live = np.asarray(sectors_prev.obstacle_points) - np.asarray(sectors_prev.remembered_points) + np.asarray(sectors_prev.clear_points)
    return np.maximum(live, 0)


@_jit.njit
def _priority_grid_k(rays, n_u, n_v, R_level_cam, metres, tan_gamma, tan_half, gamma, half_angle, has_psi, psi, half_width,
                     has_live, live_points):
    """:func:`detection_priority`'s grid answer (uint8 (n_v, n_u)) as one loop over the grid rays:
    in the levelled frame the ray is in the band and wanted (near the direction of travel, or in a
    sector without a live point in the previous frame); the same expressions as the reference."""
    small = np.zeros((n_v, n_u), np.uint8)
    for i in range(n_v):
        for j in range(n_u):
            q = i * n_u + j
            x, y, z = rays[q, 0], rays[q, 1], rays[q, 2]
            d0 = R_level_cam[0, 0] * x + R_level_cam[0, 1] * y + R_level_cam[0, 2] * z
            d1 = R_level_cam[1, 0] * x + R_level_cam[1, 1] * y + R_level_cam[1, 2] * z
            d2 = R_level_cam[2, 0] * x + R_level_cam[2, 1] * y + R_level_cam[2, 2] * z
            horiz = np.hypot(d0, d1)
            up = -d2
            if metres:
                band = abs(up / max(horiz, 1e-9) - tan_gamma) <= tan_half
            else:
                band = abs(math.atan2(up, horiz) - gamma) <= half_angle
            if not band:
                continue
            want = True
            if has_live:  # without a previous frame every column is wanted
                bearing = math.atan2(d1, d0)
                if has_psi:
                    want = abs((bearing - psi + math.pi) % (2 * math.pi) - math.pi) <= half_width
                if not want:
                    want = live_points[np.int64(np.rint(bearing * (180.0 / math.pi) / 5.0)) % SECTOR_COUNT] <= 0
            small[i, j] = want
    return small


@_jit.njit
def _enlarge_k(small, stride, width, height):
    """The grid answer enlarged to (height, width) uint8 as the reference's ``cv2.resize``
    (INTER_NEAREST, an integer factor: pixel x takes sample x // stride) and replicated border give:
    each row built once, then copied to the rows of its block (element loops: numba's slice
    assignment is slow)."""
    n_v, n_u = small.shape
    big = np.empty((height, width), np.uint8)
    col = np.empty(width, np.int64)
    for x in range(width):
        col[x] = min(x // stride, n_u - 1)
    for y in range(height):
        i = min(y // stride, n_v - 1)
        if y > 0 and i == min((y - 1) // stride, n_v - 1):
            for x in range(width):
                big[y, x] = big[y - 1, x]
        else:
            for x in range(width):
                big[y, x] = small[i, col[x]]
    return big


@_jit.register_warmup
def _warm_up() -> None:
    """Compile the priority kernel on a small camera (metres and degrees bands, with and without travel)."""
    import dataclasses

    from companion.core.camera import CameraConfig

    cam = CameraModel(CameraConfig.from_fov(64, 48, 60.0))
    for mode in ("metres", "degrees"):
        cfg = dataclasses.replace(SectorConfig(), band_mode=mode)
        detection_priority(cam, cfg, velocity_body=(3.0, 0.0, 0.0), live_points=np.zeros(SECTOR_COUNT, np.int64))
        detection_priority(cam, cfg, stride=1)
