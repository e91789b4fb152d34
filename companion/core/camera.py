"""Pinhole camera with OpenCV distortion and its mount on the vehicle (docs/derivations/frames.md).

Pixels follow OpenCV: u = fx·X/Z + cx, v = fy·Y/Z + cy for a point (X, Y, Z) in the camera frame,
then the OpenCV radial–tangential distortion (k1, k2, p1, p2, k3).  Undistortion uses
``cv2.undistortPoints`` as the brief requires.  The mount gives ``R_cam_body`` (a rotation relative
to a forward-looking camera) and the lever arm ``p_body_cam`` (camera centre in body FRD, metres).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from companion.config import require, require_finite
from companion.core.frames import mount_rotation
from companion.errors import InputError


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Intrinsics, distortion and mount; the ``[camera]`` table of the companion TOML."""

    width: int = 640
    height: int = 480
    fx: float = 554.3  # 60° horizontal field of view at 640 px
    fy: float = 554.3
    cx: float = 319.5
    cy: float = 239.5
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)  # OpenCV k1, k2, p1, p2, k3
    mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rotation from forward-looking
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # camera centre in body FRD

    def __post_init__(self) -> None:
        require(isinstance(self.width, int) and self.width > 0, f"width must be a positive integer, got {self.width!r}")
        require(isinstance(self.height, int) and self.height > 0, f"height must be a positive integer, got {self.height!r}")
        for name in ("fx", "fy"):
            require_finite(name, getattr(self, name), positive=True)
        for name in ("cx", "cy"):
            require_finite(name, getattr(self, name))
        require(len(self.distortion) in (4, 5, 8), f"distortion needs 4, 5 or 8 OpenCV coefficients, got {len(self.distortion)}")
        for i, c in enumerate(self.distortion):
            require_finite(f"distortion[{i}]", c)
        require(len(self.mount_rpy_deg) == 3, "mount_rpy_deg needs 3 angles")
        require(len(self.lever_arm_m) == 3, "lever_arm_m needs 3 components")
        for i, c in enumerate(tuple(self.mount_rpy_deg) + tuple(self.lever_arm_m)):
            require_finite(f"mount value {i}", c)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, **kw) -> "CameraConfig":
        """Square-pixel, centred, distortion-free camera with the given horizontal field of view.

        The principal point is the image centre in OpenCV's pixel-centre convention, (w−1)/2.
        """
        require_finite("hfov_deg", hfov_deg, positive=True)
        require(hfov_deg < 179.0, f"hfov_deg must be < 179, got {hfov_deg}")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, **kw)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    @property
    def R_cam_body(self) -> np.ndarray:
        return mount_rotation(*self.mount_rpy_deg)

    @property
    def p_body_cam(self) -> np.ndarray:
        return np.asarray(self.lever_arm_m, dtype=float)

    @property
    def hfov_rad(self) -> float:
        """Horizontal field of view of the undistorted pinhole (for sector masking)."""
        return math.atan((self.width - 1 - self.cx + 0.5) / self.fx) + math.atan((self.cx + 0.5) / self.fx)


class CameraModel:
    """Projection and back-projection for one :class:`CameraConfig` (vectorized over points)."""

    def __init__(self, config: CameraConfig):
        self.config = config
        self.K = config.K
        self.dist = config.dist
        self._R_cam_body = config.R_cam_body
        self._p_body_cam = config.p_body_cam
        self._has_distortion = config.has_distortion  # the config is frozen: evaluated once
        self._grid_rays: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    @property
    def R_cam_body(self) -> np.ndarray:
        """The mount rotation of the config (computed once; do not modify)."""
        return self._R_cam_body

    # -- pinhole <-> pixels ------------------------------------------------------------------
    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame points (N, 3), distortion applied. Points need Z > 0."""
        p_cam = np.asarray(p_cam, dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(p_cam)):
            raise InputError("project: points contain NaN or inf")
        if np.any(p_cam[:, 2] <= 0):
            raise InputError("project: points at or behind the camera (Z <= 0)")
        xy = p_cam[:, :2] / p_cam[:, 2:3]
        return self.normalized_to_pixels(xy)

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Distort normalized coordinates (x = X/Z, y = Y/Z) and map them to pixels."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self._has_distortion:
            xy = self._distort(xy)
        c = self.config
        return np.stack([c.fx * xy[:, 0] + c.cx, c.fy * xy[:, 1] + c.cy], 1)

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        d = np.zeros(8)
        d[: len(self.dist)] = self.dist
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], 1)

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates (N, 2) of pixels (N, 2) via ``cv2.undistortPoints``."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        if not np.all(np.isfinite(uv)):
            raise InputError("pixels_to_normalized: pixels contain NaN or inf")
        if len(uv) == 0:
            return np.zeros((0, 2))
        if not self._has_distortion:
            c = self.config
            return np.stack([(uv[:, 0] - c.cx) / c.fx, (uv[:, 1] - c.cy) / c.fy], 1)
        out = cv2.undistortPoints(
            uv.reshape(-1, 1, 2), self.K, self.dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        )
        return out.reshape(-1, 2)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Unit rays (N, 3) in the camera frame through pixels (N, 2)."""
        xy = self.pixels_to_normalized(uv)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], 1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def grid_rays(self, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Columns ``us``, rows ``vs`` of the pixel grid every ``stride`` px from ``stride // 2`` and the
        unit rays (len(vs)·len(us), 3) through it (row-major): :meth:`unproject` of the grid, computed
        once per stride (the camera is fixed).  Read-only arrays."""
        got = self._grid_rays.get(stride)
        if got is None:
            c = self.config
            us = np.arange(stride // 2, c.width, stride, dtype=float)
            vs = np.arange(stride // 2, c.height, stride, dtype=float)
            uu, vv = np.meshgrid(us, vs)
            rays = self.unproject(np.stack([uu.ravel(), vv.ravel()], 1))
            for a in (us, vs, rays):
                a.flags.writeable = False
            got = self._grid_rays[stride] = (us, vs, rays)
        return got

    def undistort_to_pinhole(self, uv: np.ndarray) -> np.ndarray:
        """Pixels of an ideal (distortion-free) camera with the same K: what the filters measure."""
        xy = self.pixels_to_normalized(uv)
        c = self.config
        return np.stack([c.fx * xy[:, 0] + c.cx, c.fy * xy[:, 1] + c.cy], 1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (with an optional inner margin)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        c = self.config
        return (
            (uv[:, 0] >= margin)
            & (uv[:, 0] <= c.width - 1 - margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 1] <= c.height - 1 - margin)
        )

    # -- mount -------------------------------------------------------------------------------
    def camera_pose(self, R_world_body: np.ndarray, p_world_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera pose ``(R_world_cam, p_world_cam)`` from the vehicle pose (broadcasts over time)."""
        R_world_body = np.asarray(R_world_body, dtype=float)
        R_world_cam = R_world_body @ self._R_cam_body.T
        p_world_cam = np.asarray(p_world_body, dtype=float) + np.einsum("...ij,j->...i", R_world_body, self._p_body_cam)
        return R_world_cam, p_world_cam

    def world_to_camera(self, p_world: np.ndarray, R_world_cam: np.ndarray, p_world_cam: np.ndarray) -> np.ndarray:
        """Points (N, 3) from world NED into the camera frame of pose (R_world_cam, p_world_cam)."""
        return (np.asarray(p_world, float) - p_world_cam) @ R_world_cam
