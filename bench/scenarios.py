"""Synthetic scenarios of the source papers (seeds 000 and 004), generated exactly and seeded.

These produce measurement-level data (true poses, true points, noisy pixels, telemetry poses with
an optional gyro error model) that the estimators consume through
:class:`companion.core.estimator.RangeEstimator`.  No images are rendered here; the image-level
version of the same flight lives in ``flightsim``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import R_CAM_BODY_FORWARD, so3_exp


@dataclasses.dataclass(frozen=True)
class Seed004Scenario:
    """Seed 004: 320×240, 45° FOV, 30 fps, 30 m/s straight and level along the optical axis, 5 s.

    The paper's frame has z along the flight; here the flight is north in NED, so the paper's
    point (x, 0, 300) becomes p_world = (300, x, 0).  The camera starts at the origin.
    """

    width: int = 320
    height: int = 240
    hfov_deg: float = 45.0
    fps: float = 30.0
    speed_mps: float = 30.0
    duration_s: float = 5.0
    lateral_m: tuple[float, ...] = (-75.0, -45.0, -15.0, 15.0, 45.0, 75.0)
    distance_m: float = 300.0
    gyro_bias_deg_s: float = 0.05  # per-axis constant bias bound (uniform in ±bound per run)
    gyro_random_deg_s: float = 0.01  # white rate noise σ per frame interval

    @property
    def camera(self) -> CameraConfig:
        return CameraConfig.from_fov(self.width, self.height, self.hfov_deg)

    @property
    def n_frames(self) -> int:
        return int(round(self.duration_s * self.fps)) + 1  # frames 0..150

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps

    @property
    def points_world(self) -> np.ndarray:
        return np.array([[self.distance_m, x, 0.0] for x in self.lateral_m])

    def true_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_world_cam (K,3,3), p_world_cam (K,3)) of the true flight."""
        t = self.times
        p = np.stack([self.speed_mps * t, np.zeros_like(t), np.zeros_like(t)], 1)
        R = np.broadcast_to(R_CAM_BODY_FORWARD.T, (len(t), 3, 3)).copy()
        return R, p

    def visibility(self, R_world_cam, p_world_cam) -> tuple[np.ndarray, np.ndarray]:
        """True pixels (K, N, 2) and visibility (K, N) of the points."""
        cam = CameraModel(self.camera)
        pts = self.points_world
        pc = np.einsum("kji,knj->kni", R_world_cam, pts[None] - p_world_cam[:, None])
        front = pc[..., 2] > 0.1
        pcs = np.where(front[..., None], pc, np.array([0.0, 0.0, 1.0]))
        uv = cam.project(pcs.reshape(-1, 3)).reshape(pc.shape[:2] + (2,))
        vis = front & cam.in_image(uv.reshape(-1, 2)).reshape(front.shape)
        return uv, vis

    def telemetry_attitude(self, rng: np.random.Generator, R_world_cam: np.ndarray) -> np.ndarray:
        """Camera attitudes as a gyro-integrating autopilot would report them (seed 004 gyro model).

        Per run a constant bias b ~ U(−bound, bound) on each body (= camera) axis and white rate
        noise n are integrated from the exactly known initial attitude.  A body-frame rate error
        rotates the reported attitude in the world frame at R_world_cam·(b + n), so the report is
        R_est = Exp(w) · R_true with w(t) = Σ R_world_cam (b + n) Δt, w(0) = 0.
        """
        K = len(R_world_cam)
        dt = 1.0 / self.fps
        bias = np.radians(rng.uniform(-self.gyro_bias_deg_s, self.gyro_bias_deg_s, 3))
        rate_err = bias + np.radians(self.gyro_random_deg_s) * rng.standard_normal((K, 3))
        step = np.einsum("kij,kj->ki", R_world_cam, rate_err) * dt
        w = np.concatenate([np.zeros((1, 3)), np.cumsum(step[:-1], axis=0)])
        return so3_exp(w) @ R_world_cam


@dataclasses.dataclass(frozen=True)
class Seed000Scenario:
    """Seed 000 simulation: a point at (0.4, 0.4, 8) m in the camera frame, camera advancing along
    its optical axis at 0.5 m/s, Δt = 0.1 s, input noise σ_ω = 0.001 rad/s/√Hz, σ_V = 0.01 m/s/√Hz.

    The paper does not state the pixel noise or focal length behind its table; the defaults here
    (f = 500 px, σ = 0.5 px) are this reproduction's assumption and are printed with the results.
    """

    point_cam: tuple[float, float, float] = (0.4, 0.4, 8.0)
    speed_mps: float = 0.5
    dt: float = 0.1
    sigma_w: float = 0.001
    sigma_v: float = 0.01
    focal_px: float = 500.0
    sigma_px: float = 0.5
    L_values: tuple[float, ...] = (0.05, 0.12, 0.18, 0.24, 0.31)
    initial_error_m: float = 3.0  # initial range error (paper §4)

    @property
    def camera(self) -> CameraConfig:
        return CameraConfig(width=640, height=480, fx=self.focal_px, fy=self.focal_px, cx=319.5, cy=239.5)

    @property
    def initial_range(self) -> float:
        return float(np.linalg.norm(self.point_cam))

    def n_steps(self) -> int:
        L_max = max(self.L_values)
        return int(math.ceil(L_max * self.initial_range / (self.speed_mps * self.dt))) + 1
