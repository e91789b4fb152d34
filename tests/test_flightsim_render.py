"""flightsim.render: analytic pixels, depth against ray casting, occlusion, seeds and effects."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import euler_zyx_to_R
from companion.errors import ConfigError, InputError
from flightsim.render import Renderer, RenderOptions
from flightsim.render.bench import bench_world, measure_fps
from flightsim.world import (
    BoxConfig,
    CylinderConfig,
    GroundConfig,
    TargetConfig,
    WallConfig,
    World,
    WorldConfig,
)

NO_GROUND = GroundConfig(enabled=False)
SMALL_GROUND = GroundConfig(tile_px=512, texel_m=0.1)
CAM = CameraConfig(width=320, height=240, fx=277.0, fy=277.0, cx=159.5, cy=119.5)
CAM_DIST = CameraConfig(width=320, height=240, fx=277.0, fy=279.0, cx=161.3, cy=118.2, distortion=(-0.28, 0.09, 0.0012, -0.0008, -0.01))


def _pose(cam: CameraConfig, roll=0.0, pitch=0.0, yaw=0.0, p=(0.0, 0.0, -10.0)):
    return CameraModel(cam).camera_pose(euler_zyx_to_R(math.radians(roll), math.radians(pitch), math.radians(yaw)), np.array(p, float))


def _scene(seed: int = 2, ground: GroundConfig = SMALL_GROUND) -> World:
    return World(
        WorldConfig(
            seed=seed,
            texel_m=0.1,
            ground=ground,
            box=(
                BoxConfig(name="near", centre_ne_m=(30.0, -6.0), size_m=(8.0, 6.0), height_m=14.0, yaw_deg=25.0),
                BoxConfig(name="far", centre_ne_m=(70.0, 12.0), size_m=(20.0, 14.0), height_m=30.0, yaw_deg=-10.0),
                BoxConfig(name="float", centre_ne_m=(45.0, -20.0), size_m=(6.0, 6.0), height_m=4.0, base_altitude_m=12.0),
            ),
            cylinder=(
                CylinderConfig(name="mast", centre_ne_m=(25.0, 4.0), radius_m=0.4, height_m=25.0),
                CylinderConfig(name="tank", centre_ne_m=(40.0, 16.0), radius_m=4.0, height_m=8.0),
            ),
            wall=(WallConfig(name="wall", start_ne_m=(18.0, -12.0), end_ne_m=(20.0, -2.0), thickness_m=0.4, height_m=3.0),),
            target=(TargetConfig(name="t", position_ned_m=(22.0, 1.0, -9.0), size_m=2.0, facing_deg=190.0),),
        )
    )


def _checker_world(position, size=4.0, facing=180.0) -> World:
    return World(WorldConfig(ground=NO_GROUND, target=(TargetConfig(name="m", position_ned_m=tuple(position), size_m=size, cells=2, facing_deg=facing),)))


def _find_corner(img: np.ndarray, guess: np.ndarray, win: int = 6) -> np.ndarray:
    pts = np.array([[guess]], np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    return cv2.cornerSubPix(img, pts, (win, win), (-1, -1), crit).reshape(2)


# ---------------------------------------------------------------------------- geometry of the image


@pytest.mark.parametrize("cam", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_known_point_renders_at_its_analytic_pixel(cam):
    model = CameraModel(cam)
    R_wc, p_wc = _pose(cam, roll=4.0, pitch=-3.0, yaw=6.0)
    worst = 0.0
    # the centre corner of a checker marker, placed centrally and towards a corner of the image
    for xy in ((0.02, 0.01), (0.42, 0.3), (-0.45, -0.3), (0.45, -0.32)):
        d_cam = np.array([xy[0], xy[1], 1.0])
        P = p_wc + R_wc @ (d_cam * 25.0)
        w = _checker_world(P, size=3.0, facing=math.degrees(math.atan2(p_wc[1] - P[1], p_wc[0] - P[0])))
        img = Renderer(w, cam).render(R_wc, p_wc).image
        uv = model.project(model.world_to_camera(P[None], R_wc, p_wc))[0]
        assert model.in_image(uv[None], margin=15)[0]
        found = _find_corner(img, uv)
        worst = max(worst, float(np.linalg.norm(found - uv)))
    assert worst < 0.5, worst


def test_depth_equals_independent_ray_cast():
    w = _scene()
    for cam, tol, share in ((CAM, 1e-4, 0.999), (CAM_DIST, 2e-3, 0.97)):
        model = CameraModel(cam)
        R_wc, p_wc = _pose(cam, roll=3.0, pitch=-6.0, yaw=4.0)
        f = Renderer(w, cam).render(R_wc, p_wc)
        assert f.depth.dtype == np.float32 and f.depth.shape == (cam.height, cam.width)
        rng = np.random.default_rng(0)
        uv = np.stack([rng.integers(0, cam.width, 3000), rng.integers(0, cam.height, 3000)], 1)
        rays = model.unproject(uv.astype(float))
        rays = rays / rays[:, 2:3]  # unit optical-axis component: distance = depth Z
        hits = w.raycast(p_wc, rays @ R_wc.T)
        z_img = f.depth[uv[:, 1], uv[:, 0]].astype(float)
        z_ray = hits.distance
        # with distortion the depth is resampled from the pinhole canvas (bilinear in 1/Z, exact
        # inside a plane, at OpenCV's 1/32-px remap positions; nearest sample across a silhouette
        # or a box edge): allow the depth change over half a pixel there
        d = f.depth.astype(float)
        H, W = d.shape
        grad = np.zeros(len(uv))
        for du, dv in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nb = d[np.clip(uv[:, 1] + dv, 0, H - 1), np.clip(uv[:, 0] + du, 0, W - 1)]
            with np.errstate(invalid="ignore"):
                grad = np.fmax(grad, np.abs(nb - z_img))
        slack = grad / 2.0 if cam.has_distortion else 0.0
        with np.errstate(invalid="ignore"):
            same = np.where(np.isinf(z_ray), np.isinf(z_img), np.abs(z_img - z_ray) <= tol * z_ray + slack)
        # every pixel centre sees exactly the surface the ray cast finds, except the odd one right
        # on a silhouette; with distortion, depth at a silhouette is the nearest canvas sample (≤ ½ px)
        assert np.mean(same) >= share, np.mean(same)
        # pixels whose 3×3 neighbourhood sees one surface (by the ray cast) must all match
        interior = np.ones(len(uv), bool)
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                nb = np.stack([uv[:, 0] + du, uv[:, 1] + dv], 1).astype(float)
                nrays = model.unproject(nb)
                interior &= w.raycast(p_wc, nrays @ R_wc.T).index == hits.index
        assert interior.mean() > 0.8
        assert np.all(same[interior]), np.nonzero(~same & interior)
        # the scene really has sky, ground and several solids in view
        kinds = set(hits.index.tolist())
        assert {-1, -2} <= kinds and len(kinds - {-1, -2}) >= 4


def test_occlusion_hides_a_box_behind_another_in_image_and_depth():
    near = BoxConfig(name="front", centre_ne_m=(20.0, 0.0), size_m=(4.0, 12.0), height_m=20.0)
    hidden = BoxConfig(name="back", centre_ne_m=(40.0, 0.0), size_m=(4.0, 6.0), height_m=12.0)
    both = World(WorldConfig(ground=SMALL_GROUND, box=(near, hidden)))
    alone = World(WorldConfig(ground=SMALL_GROUND, box=(near,)))
    R_wc, p_wc = _pose(CAM, p=(0.0, 0.0, -6.0))
    a = Renderer(both, CAM).render(R_wc, p_wc)
    b = Renderer(alone, CAM).render(R_wc, p_wc)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth)
    # half hidden: the back box shows beside the front one, never through it
    R_wc, p_wc = _pose(CAM, yaw=-20.0, p=(0.0, 15.0, -6.0))
    a = Renderer(both, CAM).render(R_wc, p_wc)
    b = Renderer(alone, CAM).render(R_wc, p_wc)
    front = np.isclose(b.depth, a.depth) & (b.depth < 30)
    changed = ~np.isclose(a.depth, b.depth)
    assert changed.sum() > 500  # the back box is visible somewhere
    assert np.all(a.depth[changed] < b.depth[changed])  # ...only where it is nearer than the background
    assert np.all(np.abs(a.depth[changed] - 38.0) < 25.0)
    assert front.sum() > 2000 and np.array_equal(a.image[front & ~_dilate(changed)], b.image[front & ~_dilate(changed)])


def _dilate(m: np.ndarray) -> np.ndarray:
    return cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def test_sky_is_smooth_and_textures_are_corner_rich():
    w = _scene()
    R_up, p = _pose(CAM, pitch=75.0)
    sky = Renderer(w, CAM).render(R_up, p).image
    assert np.isinf(Renderer(w, CAM).render(R_up, p).depth).all()
    assert cv2.cornerHarris(sky.astype(np.float32), 3, 3, 0.04).max() < 1e-3 * 255**4
    assert np.ptp(sky) < 40 and np.abs(np.diff(sky.astype(int), axis=0)).max() <= 2
    R_wc, p_wc = _pose(CAM, pitch=-6.0)
    img = Renderer(w, CAM).render(R_wc, p_wc).image
    pts = cv2.goodFeaturesToTrack(img, 500, 0.01, 5)
    assert pts is not None and len(pts) > 200


# ---------------------------------------------------------------------------- seeds and effects


def test_same_seed_same_images_different_seed_different():
    R_wc, p_wc = _pose(CAM, pitch=-5.0)
    opts = RenderOptions(noise_sigma=2.0, gain_jitter=0.05, seed=7)
    a = Renderer(_scene(seed=2), CAM, opts).render(R_wc, p_wc, frame_index=3)
    b = Renderer(_scene(seed=2), CAM, opts).render(R_wc, p_wc, frame_index=3)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth)
    c = Renderer(_scene(seed=3), CAM, opts).render(R_wc, p_wc, frame_index=3)
    assert not np.array_equal(a.image, c.image)
    assert np.array_equal(a.depth, c.depth)  # the seed changes textures, not geometry
    d = Renderer(_scene(seed=2), CAM, RenderOptions(noise_sigma=2.0, gain_jitter=0.05, seed=8)).render(R_wc, p_wc, frame_index=3)
    assert not np.array_equal(a.image, d.image)
    r = Renderer(_scene(seed=2), CAM, opts)
    assert not np.array_equal(r.render(R_wc, p_wc).image, r.render(R_wc, p_wc).image)  # fresh noise per frame


def test_noise_gain_and_motion_blur():
    w = _scene()
    R_wc, p_wc = _pose(CAM, pitch=-5.0)
    clean = Renderer(w, CAM).render(R_wc, p_wc).image.astype(float)
    noisy = Renderer(w, CAM, RenderOptions(noise_sigma=4.0)).render(R_wc, p_wc).image.astype(float)
    mid = (clean > 20) & (clean < 235)
    assert np.std((noisy - clean)[mid]) == pytest.approx(4.0, rel=0.1)
    assert abs(np.mean((noisy - clean)[mid])) < 0.1
    bright = Renderer(w, CAM, RenderOptions(gain=1.2)).render(R_wc, p_wc).image.astype(float)
    assert np.abs(bright - np.clip(np.rint(clean * 1.2), 0, 255)).max() <= 1
    frame = Renderer(w, CAM).render(R_wc, p_wc, gain=0.5)
    assert frame.gain == 0.5 and np.abs(frame.image - np.rint(clean * 0.5)).max() <= 1
    blur = Renderer(w, CAM, RenderOptions(exposure_s=0.02, max_blur_subframes=6))
    f = blur.render(R_wc, p_wc, v_world_cam=np.array([8.0, 0.0, 0.0]), w_cam=np.array([0.0, 0.8, 0.0]))
    assert f.subframes > 1
    sharp = np.mean(np.abs(np.diff(clean, axis=1)))
    blurred = np.mean(np.abs(np.diff(f.image.astype(float), axis=1)))
    assert blurred < 0.8 * sharp  # a horizontal pan smears horizontal detail
    still = blur.render(R_wc, p_wc, v_world_cam=np.zeros(3), w_cam=np.zeros(3))
    assert still.subframes == 1 and np.array_equal(still.image, clean.astype(np.uint8))


def test_bad_render_inputs_are_refused():
    r = Renderer(_scene(ground=NO_GROUND), CAM)
    with pytest.raises(InputError, match="rotation"):
        r.render(np.eye(3) * 2.0, np.zeros(3))
    with pytest.raises(InputError, match="p_world_cam"):
        r.render(np.eye(3), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ConfigError, match="noise_sigma"):
        RenderOptions(noise_sigma=-1.0)


def test_benchmark_entry_point_runs():
    w = bench_world(6)
    fps = measure_fps(w, CameraConfig.from_fov(160, 120, 60.0), frames=3, warmup=1)
    assert fps > 0


def test_seed004_targets_give_companion_corners_at_300_m():
    from pathlib import Path

    from companion.core.harris import HarrisConfig, detect_harris
    from flightsim.world import load_world, target_truth

    w = load_world(Path(__file__).resolve().parent.parent / "configs" / "worlds" / "seed004_points.toml")
    cam = CameraConfig(width=320, height=240, fx=386.0, fy=386.0, cx=159.5, cy=119.5)
    R_wc, p_wc = CameraModel(cam).camera_pose(np.eye(3), np.array([0.0, 0.0, -100.0]))
    img = Renderer(w, cam).render(R_wc, p_wc).image
    pts = np.asarray(detect_harris(img, HarrisConfig())[0]).reshape(-1, 2)
    px = target_truth(w, p_wc, R_wc, cam).pixel
    d = np.linalg.norm(pts[:, None, :] - px[None], axis=2)
    assert np.all((d < 16.0).sum(axis=0) >= 5)  # several corners on every target
    assert np.all(d.min(axis=0) < 1.0)  # including the target's centre, the point P_i itself


def test_a_large_face_seen_close_head_on_keeps_its_fine_texture():
    """The mip level of a face comes from its nearest point, not only its corners: 4 m in front of a
    60 m wide facade the image must be about as sharp as with the finest level forced everywhere
    (before, the corners 30 m away chose a level ~3 octaves too coarse and the wall was a blur)."""
    world = World(WorldConfig(seed=3, texel_m=0.03, ground=NO_GROUND,
                              box=(BoxConfig(name="w", centre_ne_m=(9.0, 0.0), size_m=(10.0, 60.0), height_m=20.0),)))

    def sharpness(lod_bias):
        opts = RenderOptions(noise_sigma=0.0, lod_bias=lod_bias)
        img = Renderer(world, CAM, opts).render(*_pose(CAM, p=(0.0, 0.0, -10.0))).image
        return float(img[60:180, 80:240].astype(float).std())  # texture contrast left after filtering

    default, finest = sharpness(RenderOptions().lod_bias), sharpness(-4.0)
    assert default > 0.8 * finest, (default, finest)  # the corner-only level kept ~40 %


def test_compiled_kernels_match_the_numpy_reference_bit_for_bit(monkeypatch):
    """flightsim.render.kernels: the numba loops give the same float32 bits as the numpy passes they
    replace (ground mip-level blend, silhouette coverage), NaN and the clamps included, and a whole
    frame renders to the same pixels with the kernels and with COMPANION_KERNELS=numpy."""
    from companion.core import jit
    from flightsim.render import kernels

    rng = np.random.default_rng(7)
    for trial in range(20):
        h, w = rng.integers(1, 60, 2)
        lam = (rng.normal(3.0, 2.0, (h, w))).astype(np.float32)
        lam[rng.random((h, w)) < 0.05] = np.float32(3.0)  # weight exactly 1 and 0 (|λ − L| = 1) both occur
        lam[rng.random((h, w)) < 0.05] = np.float32(2.0)
        r0, c0 = rng.integers(0, h), rng.integers(0, w)
        r1, c1 = rng.integers(r0 + 1, h + 1), rng.integers(c0 + 1, w + 1)
        tex = rng.integers(0, 256, (r1 - r0, c1 - c0), dtype=np.uint8)
        base = (rng.random((h, w)) * 50).astype(np.float32)
        for t, grey in ((tex, None), (None, np.float32(rng.random() * 200))):
            monkeypatch.setattr(jit, "ENABLED", True)
            a = base.copy()
            kernels.ground_level(a, lam, (r0, r1, c0, c1), t, 3, grey)
            monkeypatch.setattr(jit, "ENABLED", False)
            b = base.copy()
            kernels.ground_level(b, lam, (r0, r1, c0, c1), t, 3, grey)
            assert a.tobytes() == b.tobytes()
        n = int(rng.integers(3, 9))
        rows = (rng.normal(0, 20, (n, w))).astype(np.float32)
        cols = (rng.normal(0, 20, (n, h))).astype(np.float32)
        if trial % 5 == 0:
            rows[0, 0] = np.nan
        monkeypatch.setattr(jit, "ENABLED", True)
        a = kernels.coverage(rows, cols)
        monkeypatch.setattr(jit, "ENABLED", False)
        b = kernels.coverage(rows, cols)
        assert a.dtype == b.dtype == np.float32 and a.tobytes() == b.tobytes()
    # a whole frame: ground across many levels, boxes, walls, cylinders, noise
    world = bench_world(8)
    r = Renderer(world, CAM, RenderOptions(noise_sigma=1.0))
    R, p = _pose(CAM, pitch=-8.0, yaw=3.0, p=(20.0, 1.0, -10.0))
    monkeypatch.setattr(jit, "ENABLED", True)
    img_k = r.render(R, p, frame_index=3).image
    monkeypatch.setattr(jit, "ENABLED", False)
    img_n = r.render(R, p, frame_index=3).image
    assert np.array_equal(img_k, img_n)
