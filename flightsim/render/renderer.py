"""Software renderer: what the companion's camera sees in a :class:`~flightsim.world.World`.

Pipeline for one frame (all per-pixel work in numpy / OpenCV and the compiled loops of
:mod:`flightsim.render.kernels`, bit for bit the numpy they replace; no per-pixel Python loops):

1. **Pinhole canvas.**  Everything is drawn into an ideal pinhole image with intrinsics ``K_c``.
   Without lens distortion the canvas *is* the output image (``K_c = K``).  With distortion the
   canvas is enlarged to cover every output pixel, and step 5 remaps it through a map built once
   from the companion's own :class:`~companion.core.camera.CameraModel` (each output pixel looks
   up the canvas at its undistorted coordinates), so distortion is exactly the companion's model.
   Camera rays are ``m = ((u − cx)/fx, (v − cy)/fy, 1)`` in the camera frame; each world
   component of ``R_world_cam · m`` is affine in (u, v) and is formed by broadcasting a row and a
   column vector.  Depth along the optical axis is ``Z``; the z-buffer holds ``1/Z``.
2. **Sky and ground.**  The sky is a smooth function of elevation (computed on a coarse grid and
   resized: no corners).  The ground plane is a homography of its texture tile; texture level of
   detail is trilinear: the per-pixel mip level λ = log2(texels per pixel) comes from the
   analytic footprint of a pixel on the plane, and every level in use is warped
   (``cv2.warpPerspective``, ``BORDER_WRAP`` for the infinite tiling) into just the band of rows it
   serves and blended.  ``1/Z`` of a plane is affine in (u, v).  The horizon is anti-aliased.
3. **Boxes, walls, targets** (convex polyhedra; this step and the next are
   :class:`~flightsim.render.solids.Solids`).  For a ray that hits a convex solid, the entry
   point is on the front-facing plane with the *largest* t, so the solid's ``1/Z`` is the minimum
   over its front-facing planes of their affine ``1/Z`` — no polygon rasterization needed.  Its
   coverage is the silhouette (convex hull of the near-clipped, projected corners); each pixel's
   coverage α = clamp(0.5 + signed distance to the hull in pixels) gives anti-aliased edges and
   α ≥ 0.5 exactly where the pixel centre is inside.  Each face texture is warped with the
   plane's homography from the mip level its footprint needs (faces spanning several levels are
   drawn level by level under a per-pixel λ mask).
4. **Cylinders** are intersected exactly per pixel inside their screen rectangle (ray–circle
   quadratic, top and bottom discs) and textured with ``cv2.remap`` (one mip level per cylinder,
   from its mean depth).  Edge coverage comes from the ray's distance to the axis and the hit's
   height, turned into pixels as metres · f / depth (approximate width, exact α ≥ ½ rule).
   Solids are drawn far to near; the z-buffer (``1/Z`` greater wins) makes occlusion exact, and
   the depth of a pixel is that of the surface its centre ray hits.
5. **Output.**  With distortion the depth is remapped as ``1/Z`` bilinearly where the four canvas
   neighbours show the same surface (exact inside a plane, at OpenCV's 1/32-px remap positions)
   and from the nearest canvas sample across silhouettes (no "flying pixels"; there the depth is
   that of a point within ½ canvas pixel).  Then optional motion blur (sub-frames rendered at
   poses spread over the exposure and averaged), exposure gain and Gaussian pixel noise, seeded
   per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.config import require, require_finite
from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import so3_exp
from companion.errors import InputError
from flightsim.render.kernels import ground_level
from flightsim.render.solids import Solids

_F32 = np.float32
#: Coarse grid step (canvas pixels) for the smooth per-pixel fields (sky, ground level of detail).
_COARSE = 8


@dataclass(frozen=True)
class RenderOptions:
    """Camera effects and quality knobs (all default to an ideal, noise-free camera).

    * ``noise_sigma`` — σ of zero-mean Gaussian pixel noise, grey levels;
    * ``exposure_s`` — exposure time: with the camera's velocity and rate passed to
      :meth:`Renderer.render`, the frame averages sub-frames spread over it (motion blur); at most
      ``max_blur_subframes``, spaced so the image moves ≤ ``blur_step_px`` between them;
    * ``gain`` — exposure gain multiplying the grey levels; ``gain_jitter`` — σ of a random
      per-frame log-gain (auto-exposure flicker);
    * ``seed`` — seeds noise and jitter: frame ``k`` of a renderer with seed ``s`` is identical
      across runs;
    * ``near_m`` — near clipping distance; ``lod_bias`` — added to texture mip levels (+ = blurrier);
    * ``max_canvas_area`` — with distortion, the pinhole canvas is at most this multiple of the
      output area (wider lenses get a canvas of lower resolution).
    """

    noise_sigma: float = 0.0
    exposure_s: float = 0.0
    max_blur_subframes: int = 8
    blur_step_px: float = 1.0
    gain: float = 1.0
    gain_jitter: float = 0.0
    seed: int = 0
    near_m: float = 0.05
    lod_bias: float = 0.0
    max_canvas_area: float = 3.0

    def __post_init__(self) -> None:
        require_finite("noise_sigma", self.noise_sigma, nonnegative=True)
        require_finite("exposure_s", self.exposure_s, nonnegative=True)
        require(isinstance(self.max_blur_subframes, int) and 1 <= self.max_blur_subframes <= 64, f"max_blur_subframes must be an integer in [1, 64], got {self.max_blur_subframes!r}")
        require_finite("blur_step_px", self.blur_step_px, positive=True)
        require_finite("gain", self.gain, positive=True)
        require_finite("gain_jitter", self.gain_jitter, nonnegative=True)
        require(isinstance(self.seed, int) and self.seed >= 0, f"seed must be an integer >= 0, got {self.seed!r}")
        require_finite("near_m", self.near_m, positive=True)
        require_finite("lod_bias", self.lod_bias)
        require_finite("max_canvas_area", self.max_canvas_area)
        require(self.max_canvas_area >= 1.0, f"max_canvas_area must be >= 1, got {self.max_canvas_area}")


@dataclass(frozen=True, eq=False)
class Frame:
    """One rendered frame: ``image`` uint8 (H, W) grey; ``depth`` float32 (H, W) metres along the
    optical axis of the surface seen at each pixel centre (``inf`` for sky; None when not asked
    for); the pose it was
    rendered at (mid-exposure), the gain applied and the number of motion-blur sub-frames."""

    image: np.ndarray
    depth: np.ndarray | None
    R_world_cam: np.ndarray
    p_world_cam: np.ndarray
    gain: float = 1.0
    subframes: int = 1
    index: int = 0


class Renderer:
    """Renders grey images and depth of ``world`` through the companion's camera model.

    ``render(R_world_cam, p_world_cam)`` takes the camera pose (world NED ← camera OpenCV, and
    the camera centre in NED), e.g. from ``CameraModel.camera_pose(R_world_body, p_world_body)``;
    :meth:`render_body` does that step itself.
    """

    def __init__(self, world, camera_config: CameraConfig, options: RenderOptions | None = None):
        self.world = world
        self.camera_config = camera_config
        self.options = options or RenderOptions()
        self.model = CameraModel(camera_config)
        self._tex = world.textures()
        self._counter = 0
        self._setup_canvas()
        self._solids = Solids(world, self._tex, self.options, self.canvas_K, self.canvas_size, self._ub, self._vb,
                              self._frustum, self._f_mean)
        self._ground_tiles = self._tiled_ground()
        self._ground_levels = self._ground_level_constants()
        sky = world.config.sky
        self._sky_h, self._sky_z = float(sky.horizon_grey), float(sky.zenith_grey)

    # ------------------------------------------------------------------------------ set-up
    def _tiled_ground(self):
        """Per ground mip level: (texture repeated reps × reps times, reps).  Warps run fastest
        when the sampled coordinates stay inside the source image (``BORDER_WRAP`` is correct but
        several times slower outside), so each level is repeated until it spans ≥ 1024 texels
        (2048-texel levels twice) and the camera is placed near its middle every frame."""
        if self._tex.ground is None:
            return None
        cached = getattr(self._tex, "_tiled", None)
        if cached is None:
            cached = []
            for t in self._tex.ground:
                n = t.shape[0]
                reps = 1 if n > 2048 else max(2, -(-1024 // n))
                cached.append((np.ascontiguousarray(np.tile(t, (reps, reps))) if reps > 1 else t, reps))
            self._tex._tiled = cached
        return cached

    def _ground_level_constants(self):
        """Per ground mip level, what :meth:`_draw_ground` needs of it every frame, computed once:
        ``(tiled texture, reps, texel size in metres, flat grey)`` — the flat grey (float32 mean of
        the level) for levels of a few texels per period, which are drawn as their mean, else None."""
        if self._ground_tiles is None:
            return None
        tex = self._tex.ground
        tile_m = self._tex.ground_texel_m * tex[0].shape[0]
        return [(t, reps, tile_m / tex[L].shape[0], _F32(tex[L].mean()) if tex[L].shape[0] <= 4 else None)
                for L, (t, reps) in enumerate(self._ground_tiles)]

    def _setup_canvas(self) -> None:
        c = self.camera_config
        W, H = c.width, c.height
        self._remap = None
        if not c.has_distortion:
            fx, fy, cx, cy, Wc, Hc = c.fx, c.fy, c.cx, c.cy, W, H
        else:
            uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
            xy = self.model.pixels_to_normalized(np.stack([uu.ravel(), vv.ravel()], 1))
            xy = self._refine_undistortion(xy, np.stack([uu.ravel(), vv.ravel()], 1))
            x, y = xy[:, 0].reshape(H, W), xy[:, 1].reshape(H, W)
            margin = 2.0
            scale = 1.0
            for _ in range(2):
                fx, fy = c.fx * scale, c.fy * scale
                x0, x1 = x.min() * fx - margin, x.max() * fx + margin
                y0, y1 = y.min() * fy - margin, y.max() * fy + margin
                Wc, Hc = int(math.ceil(x1 - x0)) + 1, int(math.ceil(y1 - y0)) + 1
                area = Wc * Hc / float(W * H)
                if area <= self.options.max_canvas_area:
                    break
                scale *= math.sqrt(self.options.max_canvas_area / area) * 0.98
            cx, cy = -x0, -y0
            mx = (x * fx + cx).astype(_F32)
            my = (y * fy + cy).astype(_F32)
            self._remap = (
                cv2.convertMaps(mx, my, cv2.CV_16SC2),
                cv2.convertMaps(mx, my, cv2.CV_16SC2, nninterpolation=True),
            )
        self.canvas_K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        self.canvas_size = (Wc, Hc)
        self._ub = ((np.arange(Wc) - cx) / fx).astype(_F32)[None, :]
        self._vb = ((np.arange(Hc) - cy) / fy).astype(_F32)[:, None]
        # coarse grid (for smooth fields), covering the canvas corners
        self._cu = np.unique(np.r_[np.arange(0, Wc, _COARSE), Wc - 1]).astype(float)
        self._cv = np.unique(np.r_[np.arange(0, Hc, _COARSE), Hc - 1]).astype(float)
        self._cub = (self._cu - cx) / fx
        self._cvb = (self._cv - cy) / fy
        # canvas frustum in normalized coordinates (for culling)
        self._frustum = ((-0.5 - cx) / fx, (Wc - 0.5 - cx) / fx, (-0.5 - cy) / fy, (Hc - 0.5 - cy) / fy)
        self._f_mean = math.sqrt(fx * fy)

    def _refine_undistortion(self, xy: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Newton steps on the companion's forward distortion so that distort(xy) = uv to 1e-6 px."""
        c = self.camera_config
        for _ in range(5):
            f = self.model.normalized_to_pixels(xy)
            r = f - uv
            if np.max(np.abs(r)) < 1e-7:
                break
            eps = 1e-7
            fx_ = (self.model.normalized_to_pixels(xy + [eps, 0]) - f) / eps
            fy_ = (self.model.normalized_to_pixels(xy + [0, eps]) - f) / eps
            det = fx_[:, 0] * fy_[:, 1] - fy_[:, 0] * fx_[:, 1]
            ok = np.abs(det) > 1e-12 * c.fx * c.fy
            dx = np.where(ok, (r[:, 0] * fy_[:, 1] - r[:, 1] * fy_[:, 0]) / np.where(ok, det, 1), 0)
            dy = np.where(ok, (fx_[:, 0] * r[:, 1] - fx_[:, 1] * r[:, 0]) / np.where(ok, det, 1), 0)
            xy = xy - np.stack([dx, dy], 1)
        return xy

    # ------------------------------------------------------------------------------ API
    def render_body(self, R_world_body: np.ndarray, p_world_body: np.ndarray, **kw) -> Frame:
        """Render from the vehicle pose (the camera mount and lever arm applied)."""
        R, p = self.model.camera_pose(np.asarray(R_world_body, float), np.asarray(p_world_body, float))
        return self.render(R, p, **kw)

    def render(
        self,
        R_world_cam: np.ndarray,
        p_world_cam: np.ndarray,
        *,
        v_world_cam: np.ndarray | None = None,
        w_cam: np.ndarray | None = None,
        gain: float | None = None,
        frame_index: int | None = None,
        depth: bool = True,
    ) -> Frame:
        """Render the frame whose mid-exposure camera pose is (``R_world_cam``, ``p_world_cam``).

        ``v_world_cam`` (m/s, world NED) and ``w_cam`` (rad/s, camera frame) describe the camera's
        motion during the exposure, used for motion blur when ``options.exposure_s`` > 0.
        ``gain`` multiplies ``options.gain`` for this frame.  ``frame_index`` selects the noise and
        jitter draws (default: a counter of calls), so a frame can be re-rendered identically.
        ``depth=False`` leaves :attr:`Frame.depth` None (the simulator's camera only needs the image).
        """
        R = np.asarray(R_world_cam, float)
        p = np.asarray(p_world_cam, float).reshape(-1)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise InputError("render: R_world_cam must be a finite 3×3 matrix")
        if abs(np.linalg.det(R) - 1.0) > 1e-6 or np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6:
            raise InputError("render: R_world_cam is not a rotation matrix")
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InputError("render: p_world_cam must be 3 finite numbers")
        index = self._counter if frame_index is None else int(frame_index)
        self._counter = index + 1
        opt = self.options
        img, invz, ids = self._render_canvas(R, p)
        n_sub = 1
        if opt.exposure_s > 0 and (v_world_cam is not None or w_cam is not None):
            v = np.zeros(3) if v_world_cam is None else np.asarray(v_world_cam, float).reshape(3)
            w = np.zeros(3) if w_cam is None else np.asarray(w_cam, float).reshape(3)
            n_sub = self._blur_subframes(v, w, invz)
            if n_sub > 1:
                acc = np.zeros(img.shape, _F32)
                for k in range(n_sub):
                    tau = opt.exposure_s * ((k + 0.5) / n_sub - 0.5)
                    if abs(tau) < 1e-12:
                        sub = img
                    else:
                        sub = self._render_canvas(R @ so3_exp(w * tau), p + v * tau)[0]
                    acc += sub
                acc *= 1.0 / n_sub
                img = acc
        image, invz = self._to_output(img, invz, ids)
        rng = np.random.default_rng([opt.seed, index]) if (opt.gain_jitter > 0 or opt.noise_sigma > 0) else None
        g = opt.gain * (1.0 if gain is None else float(gain))
        if opt.gain_jitter > 0:
            g *= math.exp(opt.gain_jitter * rng.standard_normal())
        if opt.noise_sigma > 0 or g != 1.0 or image.dtype != np.uint8:
            f = image.astype(_F32) if image.dtype != _F32 else image
            if g != 1.0:
                f = f * _F32(g)
            noise = 0.0
            if opt.noise_sigma > 0:
                noise = np.empty(f.shape, _F32)
                cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
                cv2.randn(noise, 0.0, float(opt.noise_sigma))
            image = cv2.add(f, noise, dtype=cv2.CV_8U)  # f + noise in float32, rounded and saturated to 0..255
        depth_m = None
        if depth:
            with np.errstate(divide="ignore"):
                depth_m = _F32(1.0) / invz  # the z-buffer is >= 0: sky (0) becomes inf
        return Frame(image, depth_m, R.copy(), p.copy(), g, n_sub, index)

    # ------------------------------------------------------------------------------ output
    def _blur_subframes(self, v: np.ndarray, w: np.ndarray, invz: np.ndarray) -> int:
        opt = self.options
        Wc, Hc = self.canvas_size
        f = self._f_mean
        half_diag = 0.5 * math.hypot(Wc, Hc)
        rot_px = (math.hypot(w[0], w[1]) * f * (1 + (half_diag / f) ** 2) + abs(w[2]) * half_diag) * opt.exposure_s
        near_inv = float(np.max(invz[:: _COARSE // 2, :: _COARSE // 2])) if invz.size else 0.0
        trans_px = float(np.linalg.norm(v)) * opt.exposure_s * f * near_inv * (1 + half_diag / f)
        return int(min(opt.max_blur_subframes, max(1, math.ceil((rot_px + trans_px) / opt.blur_step_px))))

    def _to_output(self, img: np.ndarray, invz: np.ndarray, ids: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        if self._remap is None:
            return img, invz
        (m1, m2), (n1, n2) = self._remap
        rm = lambda a, m, n, how: cv2.remap(a, m, n, how, borderMode=cv2.BORDER_REPLICATE)  # noqa: E731
        out = rm(img, m1, m2, cv2.INTER_LINEAR)
        lin = rm(invz, m1, m2, cv2.INTER_LINEAR)
        near = rm(invz, n1, n2, cv2.INTER_NEAREST)
        # 1/Z interpolates exactly within a plane, but across a silhouette bilinear 1/Z would mix
        # two surfaces: where the four canvas neighbours do not all show the same surface (the
        # interpolated surface id differs from the nearest one), keep the nearest sample
        same = rm(ids, m1, m2, cv2.INTER_LINEAR) == rm(ids, n1, n2, cv2.INTER_NEAREST)
        return out, np.where(same, lin, near)

    # ------------------------------------------------------------------------------ canvas
    def _render_canvas(self, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Wc, Hc = self.canvas_size
        ub, vb = self._ub, self._vb
        # world components of the camera ray m = (x̄, ȳ, 1): affine in pixels
        rows = [(_F32(R[k, 0]) * ub + _F32(R[k, 2])) for k in range(3)]
        cols = [_F32(R[k, 1]) * vb for k in range(3)]
        img = self._sky(R)
        invz = np.zeros((Hc, Wc), _F32)
        # surface ids (0 sky, 1 ground, 2 + obstacle index), only needed to remap depth
        self._ids = np.zeros((Hc, Wc), _F32) if self._remap is not None else None
        if self.world.ground_z is not None and p[2] < self.world.ground_z:
            self._draw_ground(R, p, rows, cols, img, invz)
        self._solids.draw(R, p, img, invz, self._ids)
        return img, invz, self._ids

    def _sky(self, R: np.ndarray) -> np.ndarray:
        Wc, Hc = self.canvas_size
        d = R[:, 0, None, None] * self._cub[None, None, :] + R[:, 1, None, None] * self._cvb[None, :, None] + R[:, 2, None, None]
        s = np.abs(d[2]) / np.sqrt(np.sum(d * d, axis=0))
        sky = (self._sky_h + (self._sky_z - self._sky_h) * s).astype(_F32)
        return cv2.add(cv2.resize(sky, (Wc, Hc), interpolation=cv2.INTER_LINEAR), 0.0, dtype=cv2.CV_8U)

    def _draw_ground(self, R, p, rows, cols, img, invz) -> None:
        Wc, Hc = self.canvas_size
        zg = self.world.ground_z
        h = zg - p[2]  # camera height above the ground (> 0)
        Kc = self.canvas_K
        fx, fy = Kc[0, 0], Kc[1, 1]
        gD = math.hypot(R[2, 0] / fx, R[2, 1] / fy)  # change of the ray's down component per pixel
        # coarse fields: ray down component and level of detail
        cub, cvb = self._cub[None, :], self._cvb[:, None]
        dN = R[0, 0] * cub + R[0, 1] * cvb + R[0, 2]
        dE = R[1, 0] * cub + R[1, 1] * cvb + R[1, 2]
        dD = R[2, 0] * cub + R[2, 1] * cvb + R[2, 2]
        ground_c = dD > -0.5 * gD - 1e-12
        if not np.any(ground_c):
            return
        # pixel footprint on the plane: |∂X/∂u|, |∂X/∂v| with X = p + (h/dD)·d
        with np.errstate(divide="ignore", invalid="ignore"):
            Z = h / np.maximum(dD, 1e-9)
            fp = []
            for j, f in ((0, fx), (1, fy)):
                dd = R[:, j] / f
                gn = Z * (dd[0] - dN * dd[2] / np.maximum(dD, 1e-9))
                ge = Z * (dd[1] - dE * dd[2] / np.maximum(dD, 1e-9))
                fp.append(np.hypot(gn, ge))
            foot = np.maximum(fp[0], fp[1])
        tex = self._tex.ground
        top = len(tex) - 1
        s0 = self._tex.ground_texel_m
        lam_c = np.clip(np.log2(np.maximum(foot, 1e-9) / s0) + self.options.lod_bias, 0.0, top)
        lam_c = np.where(ground_c & np.isfinite(lam_c), lam_c, top).astype(_F32)
        # ground region on the canvas (rows/cols where coverage > 0): from the coarse grid, padded
        rr = np.nonzero(ground_c.any(axis=1))[0]
        cc = np.nonzero(ground_c.any(axis=0))[0]
        y0 = int(self._cv[max(rr[0] - 1, 0)])
        y1 = int(self._cv[min(rr[-1] + 1, len(self._cv) - 1)]) + 1
        x0 = int(self._cu[max(cc[0] - 1, 0)])
        x1 = int(self._cu[min(cc[-1] + 1, len(self._cu) - 1)]) + 1
        Hr, Wr = y1 - y0, x1 - x0
        lam = np.ascontiguousarray(cv2.resize(lam_c, (Wc, Hc), interpolation=cv2.INTER_LINEAR)[y0:y1, x0:x1])
        dD_f = rows[2][:, x0:x1] + cols[2][y0:y1]
        if gD > 1e-12:  # α = clip(dD / gD + ½, 0, 1), in place
            alpha = dD_f * _F32(1.0 / gD)
            alpha += _F32(0.5)
            np.clip(alpha, 0.0, 1.0, out=alpha)
        else:
            alpha = (dD_f > 0).astype(_F32)
        acc = np.zeros((Hr, Wr), _F32)
        tile_m = s0 * tex[0].shape[0]
        levels_c = self._ground_levels
        A = Kc @ R.T
        # rows / columns of the ground region where each level has weight (λ within L ± 1): the
        # first and last of them for every level at once (a few numpy calls per frame, not per level)
        r_lo, r_hi = lam.min(axis=1), lam.max(axis=1)
        c_lo, c_hi = lam.min(axis=0), lam.max(axis=0)
        lmin = int(math.floor(float(r_lo.min())))
        lmax = int(math.ceil(float(r_hi.max())))
        levels = np.arange(lmin, lmax + 1, dtype=float)[:, None]
        bands = []
        for lo, hi in ((r_lo, r_hi), (c_lo, c_hi)):
            has = (hi > levels - 1.0) & (lo < levels + 1.0)  # (levels, rows or columns)
            bands.append((has.any(axis=1).tolist(), has.argmax(axis=1).tolist(), (has.shape[1] - 1 - has[:, ::-1].argmax(axis=1)).tolist()))
        (r_any, r_first, r_last), (c_any, c_first, c_last) = bands
        p_n, p_e = float(p[0]), float(p[1])
        for k, L in enumerate(range(lmin, lmax + 1)):
            if not (r_any[k] and c_any[k]):
                continue
            ya, yb = y0 + r_first[k], y0 + r_last[k] + 1
            xa, xb = x0 + c_first[k], x0 + c_last[k] + 1
            band = (ya - y0, yb - y0, xa - x0, xb - x0)
            t, reps, s, flat = levels_c[L]
            if flat is not None:  # a few texels per period: only the mean grey is left
                ground_level(acc, lam, band, None, L, flat)  # acc += max(1 − |λ − L|, 0) · grey
                continue
            # tile origin (a multiple of the period) that puts the camera near the middle of t
            N0 = round(p_n / tile_m - 0.5 * reps) * tile_m
            E0 = round(p_e / tile_m - 0.5 * reps) * tile_m
            M = np.array([[0.0, s, N0 + 0.5 * s - p_n], [s, 0.0, E0 + 0.5 * s - p_e], [0.0, 0.0, h]])
            Hm = np.array([[1, 0, -xa], [0, 1, -ya], [0, 0, 1.0]]) @ A @ M
            warped = cv2.warpPerspective(t, Hm, (xb - xa, yb - ya), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            ground_level(acc, lam, band, warped, L)  # acc += max(1 − |λ − L|, 0) · texture
        # blend ground over sky with the horizon coverage (sky + α (acc − sky), in place in acc);
        # 1/Z of the plane where the centre sees it
        region = img[y0:y1, x0:x1]
        sky = region.astype(_F32)
        acc -= sky
        acc *= alpha
        acc += sky
        region[...] = cv2.add(acc, 0.0, dtype=cv2.CV_8U)
        iz = invz[y0:y1, x0:x1]
        np.multiply(dD_f, _F32(1.0 / h), out=iz)
        np.abs(iz, out=iz)  # abs: no −0 (1/−0 = −inf)
        iz[alpha < 0.5] = _F32(0.0)
        if self._ids is not None:
            self._ids[y0:y1, x0:x1] = (alpha >= 0.5).astype(_F32)
