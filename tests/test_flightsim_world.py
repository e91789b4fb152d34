"""flightsim.world: world TOMLs, geometry queries and per-frame truth."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import euler_zyx_to_R
from companion.errors import ConfigError
from flightsim.world import (
    GROUND,
    SKY,
    BoxConfig,
    CylinderConfig,
    GroundConfig,
    TargetConfig,
    WallConfig,
    World,
    WorldConfig,
    check_camera_sees_something,
    load_world,
    sector_truth,
    sectors_seen,
    target_truth,
)

WORLDS = Path(__file__).resolve().parent.parent / "configs" / "worlds"
SHIPPED = sorted(WORLDS.glob("*.toml"))
NO_GROUND = GroundConfig(enabled=False)


def _write(tmp_path, text: str) -> Path:
    p = tmp_path / "w.toml"
    p.write_text(text)
    return p


# ---------------------------------------------------------------------------- loading


def test_shipped_worlds_load_and_comment_every_key():
    names = {p.stem for p in SHIPPED}
    assert {"seed004_points", "quad_approach", "fixedwing_pass"} <= names
    for path in SHIPPED:
        w = load_world(path)
        assert w.obstacles
        for i, line in enumerate(path.read_text().splitlines(), 1):
            s = line.strip()
            if "=" in s and not s.startswith("#"):
                assert "#" in s.split("=", 1)[1], f"{path.name}:{i} key without a comment: {s}"


def test_seed004_world_has_the_six_points_at_the_camera_altitude():
    w = load_world(WORLDS / "seed004_points.toml")
    assert w.ground_z is None
    P = np.array([t.centre for t in w.targets])
    np.testing.assert_allclose(P, [[300.0, x, -100.0] for x in (-75, -45, -15, 15, 45, 75)])
    # at 300 m with f = 386 px every target spans more than 16 px and they do not overlap
    size_px = 386.0 * np.array([t.config.size_m for t in w.targets]) / 300.0
    assert np.all(size_px > 16) and np.all(30.0 * 386.0 / 300.0 > size_px)


def test_misspelt_key_is_named_with_its_table_and_file(tmp_path):
    p = _write(tmp_path, '[[box]]\ncentre_ne_m = [10.0, 0.0]\nsize_m = [5.0, 5.0]\nheigth_m = 10.0\n')
    with pytest.raises(ConfigError, match=r"w\.toml.*box\[0\].*'heigth_m'"):
        load_world(p)
    p = _write(tmp_path, "[ground]\nenabeld = false\n")
    with pytest.raises(ConfigError, match=r"\[ground\].*'enabeld'"):
        load_world(p)
    p = _write(tmp_path, "sede = 3\n")
    with pytest.raises(ConfigError, match="'sede'"):
        load_world(p)


def test_malformed_and_invalid_tomls_stop_with_clear_errors(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_world(_write(tmp_path, "[[box]\ncentre_ne_m = [1, 2]\n"))
    with pytest.raises(ConfigError, match="no such world file"):
        load_world(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match=r"\[\[box\]\]"):
        load_world(_write(tmp_path, "[box]\ncentre_ne_m = [1.0, 2.0]\n"))
    with pytest.raises(ConfigError, match=r"cylinder\[0\].*radius_m is required"):
        load_world(_write(tmp_path, "[[cylinder]]\ncentre_ne_m = [1.0, 2.0]\nheight_m = 3.0\n"))
    with pytest.raises(ConfigError, match=r"target\[0\].*cells"):
        load_world(_write(tmp_path, "[[target]]\nposition_ned_m = [1.0, 2.0, -3.0]\ncells = 3\n"))
    with pytest.raises(ConfigError, match=r"box\[0\].*size_m"):
        load_world(_write(tmp_path, "[[box]]\ncentre_ne_m = [1.0, 2.0]\nsize_m = [0.0, 2.0]\nheight_m = 3.0\n"))
    with pytest.raises(ConfigError, match="height_m.*wrong type"):
        load_world(_write(tmp_path, '[[wall]]\nstart_ne_m = [0.0, 0.0]\nend_ne_m = [5.0, 0.0]\nheight_m = "tall"\n'))
    with pytest.raises(ConfigError, match="unique.*'a'"):
        load_world(_write(tmp_path, '[[cylinder]]\nname = "a"\ncentre_ne_m = [1.0, 2.0]\nradius_m = 1.0\nheight_m = 3.0\n'
                                    '[[box]]\nname = "a"\ncentre_ne_m = [9.0, 2.0]\nsize_m = [1.0, 1.0]\nheight_m = 3.0\n'))


# ---------------------------------------------------------------------------- geometry


def _street() -> World:
    return World(
        WorldConfig(
            seed=5,
            box=(BoxConfig(name="house", centre_ne_m=(50.0, 0.0), size_m=(10.0, 30.0), height_m=12.0),),
            cylinder=(CylinderConfig(name="mast", centre_ne_m=(0.0, 30.0), radius_m=2.0, height_m=40.0),),
            wall=(WallConfig(name="fence", start_ne_m=(20.0, -5.0), end_ne_m=(20.0, 5.0), thickness_m=0.2, height_m=20.0),),
        )
    )


def test_raycast_hits_known_surfaces():
    w = _street()
    o = np.array([0.0, 0.0, -10.0])
    d = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, -0.6], [1.0, 0.27, 0.0]])
    h = w.raycast(o, d)
    mast, fence = w.obstacle("mast").index, w.obstacle("fence").index
    np.testing.assert_allclose(h.distance[:3], [19.9, 28.0, 10.0])
    assert list(h.index[:4]) == [fence, mast, GROUND, SKY]
    # over the 20 m fence (at N = 19.9 the ray is 21.9 m up) and the 12 m house
    assert h.index[4] == SKY
    # beside the fence (its end at E = 5 is at bearing 14.1°, this ray at 15.1°) onto the house's south face
    assert h.index[5] == w.obstacle("house").index
    assert h.distance[5] == pytest.approx(45.0)
    # a ray starting inside a solid hits it at 0; max_range turns far hits into misses
    h = w.raycast(np.array([50.0, 0.0, -1.0]), np.array([[1.0, 0.0, 0.0]]))
    assert h.distance[0] == 0.0
    h = w.raycast(o, np.array([[1.0, 0.0, 0.0]]), max_range=10.0)
    assert h.index[0] == SKY and np.isinf(h.distance[0])


def test_start_position_inside_or_near_an_obstacle_is_refused_by_name():
    w = _street()
    with pytest.raises(ConfigError, match=r"inside obstacle 'house' \(box\[0\]\)"):
        w.check_start_clear([50.0, 3.0, -5.0])
    with pytest.raises(ConfigError, match=r"0\.50 m from obstacle 'mast' \(cylinder\[0\]\)"):
        w.check_start_clear([0.0, 27.5, -10.0], min_clearance_m=2.0)
    with pytest.raises(ConfigError, match="below the ground"):
        w.check_start_clear([0.0, 0.0, 3.0])
    w.check_start_clear([0.0, 0.0, -10.0], min_clearance_m=2.0)
    w.check_start_clear([0.0, 0.0, 0.0])  # a quad on its gear
    d, ob = w.clearance([0.0, 0.0, -10.0])
    assert ob.name == "fence" and d == pytest.approx(19.9)


# ---------------------------------------------------------------------------- sector truth


def _wall_and_cylinder() -> World:
    return World(
        WorldConfig(
            ground=NO_GROUND,
            wall=(WallConfig(name="wall", start_ne_m=(20.0, -5.0), end_ne_m=(20.0, 5.0), thickness_m=0.2, height_m=30.0),),
            cylinder=(CylinderConfig(name="cyl", centre_ne_m=(0.0, 30.0), radius_m=2.0, height_m=30.0),),
        )
    )


def test_sector_truth_matches_hand_computed_wall_and_cylinder():
    w = _wall_and_cylinder()
    R = np.eye(3)
    p = np.array([0.0, 0.0, -10.0])
    s = sector_truth(w, R, p, None, 100.0)
    c = math.cos
    r = math.radians
    # wall across the path: its south face is at 19.9 m; a ±2.5° wedge's nearest point is on its
    # centre line for sector 0, on the wedge edge nearer the path for the others
    assert s[0] == pytest.approx(19.9)
    assert s[1] == pytest.approx(19.9 / c(r(2.5)))
    assert s[2] == pytest.approx(19.9 / c(r(7.5)))
    assert s[3] == pytest.approx(19.9 / c(r(12.5)))  # the wall ends at 14.1°, inside this wedge
    assert s[71] == pytest.approx(19.9 / c(r(2.5)))
    assert np.isinf(s[4]) and np.isinf(s[68])
    # cylinder due east at 30 m, radius 2: closest point in sector 18; edge rays at 87.5° / 92.5°
    assert s[18] == pytest.approx(28.0)
    d, de = 30.0, r(2.5)
    hit = d * c(de) - math.sqrt(4.0 - (d * math.sin(de)) ** 2)
    assert s[17] == pytest.approx(hit) and s[19] == pytest.approx(hit)
    assert np.isinf(s[16]) and np.isinf(s[20])  # the circle spans only 90 ± 3.8°
    assert np.all(np.isinf(np.delete(s, [0, 1, 2, 3, 71, 70, 69, 17, 18, 19])))
    # the vehicle's yaw turns the sectors: facing east, the cylinder is dead ahead
    s_e = sector_truth(w, euler_zyx_to_R(0.0, 0.0, math.pi / 2), p, None, 100.0)
    assert s_e[0] == pytest.approx(28.0)
    assert s_e[54] == pytest.approx(19.9)  # the wall is now at −90°
    # roll and pitch do not tilt the sectors
    np.testing.assert_allclose(sector_truth(w, euler_zyx_to_R(0.3, -0.2, 0.0), p, None, 100.0), s)
    # max distance and the vertical band
    s_near = sector_truth(w, R, p, None, 25.0)
    assert s_near[0] == pytest.approx(19.9) and np.isinf(s_near[18])
    high = sector_truth(w, R, np.array([0.0, 0.0, -60.0]), None, 100.0, band_half_height_m=10.0)
    assert np.all(np.isinf(high))  # 30 m obstacles, the vehicle at 60 m
    assert sector_truth(w, R, np.array([0.0, 0.0, -60.0]), None, 100.0, band_half_height_m=None)[0] == pytest.approx(19.9)


def test_sector_truth_is_the_minimum_over_each_wedge():
    rng = np.random.default_rng(3)
    boxes = tuple(
        BoxConfig(centre_ne_m=tuple(rng.uniform(-60, 60, 2)), size_m=tuple(rng.uniform(2, 15, 2)), height_m=20.0, yaw_deg=float(rng.uniform(0, 90)))
        for _ in range(8)
    )
    cyls = tuple(CylinderConfig(centre_ne_m=tuple(rng.uniform(-60, 60, 2)), radius_m=float(rng.uniform(0.3, 4)), height_m=20.0) for _ in range(6))
    w = World(WorldConfig(ground=NO_GROUND, box=boxes, cylinder=cyls))
    p = np.array([1.0, -2.0, -5.0])
    if w.clearance(p)[0] < 1.0:
        pytest.skip("random obstacle on the vehicle")
    R = euler_zyx_to_R(0.0, 0.0, 0.4)
    truth = sector_truth(w, R, p, None, 200.0)
    # dense fan of horizontal rays inside each wedge
    fan = np.linspace(-2.5, 2.5, 401)
    for i in range(72):
        b = 0.4 + np.radians(5.0 * i + fan)
        sampled = np.min(w.horizontal_distances(p, b))
        sampled = np.inf if sampled > 200.0 else sampled
        if np.isinf(truth[i]):
            assert np.isinf(sampled), i
        else:
            assert truth[i] <= sampled + 1e-9, i
            assert sampled - truth[i] < 0.01 * truth[i] + 1e-6, i


def test_unseen_sectors_are_nan_and_follow_the_camera_mount():
    w = _wall_and_cylinder()
    p = np.array([0.0, 0.0, -10.0])
    cam = CameraConfig()  # 60° horizontal field of view, forward
    s = sector_truth(w, np.eye(3), p, cam, 100.0)
    seen = sectors_seen(np.eye(3), p, cam)
    assert np.array_equal(np.isnan(s), ~seen)
    assert set(np.nonzero(seen)[0]) == set(range(0, 6)) | set(range(67, 72))  # ±27.5° inside 60°
    assert s[0] == pytest.approx(19.9) and np.isnan(s[18])
    right = CameraConfig(mount_rpy_deg=(0.0, 0.0, 90.0))  # camera looking right
    s_r = sector_truth(w, np.eye(3), p, right, 100.0)
    assert s_r[18] == pytest.approx(28.0) and np.isnan(s_r[0])
    down = CameraConfig(mount_rpy_deg=(0.0, -60.0, 0.0))  # looking 60° down: horizon out of view
    assert not sectors_seen(np.eye(3), p, down).any()


def test_sector_truth_360_knows_every_sector_and_the_view():
    """The distance of all 72 sectors (in view or not) and the in-view mask apart."""
    from flightsim.world.truth import sector_truth_360

    w = _wall_and_cylinder()
    p = np.array([0.0, 0.0, -10.0])
    cam = CameraConfig()
    dist, view = sector_truth_360(w, np.eye(3), p, cam, 100.0)
    assert not np.isnan(dist).any() and view.dtype == bool
    np.testing.assert_array_equal(dist, sector_truth(w, np.eye(3), p, None, 100.0))
    np.testing.assert_array_equal(view, sectors_seen(np.eye(3), p, cam))
    np.testing.assert_array_equal(np.where(view, dist, np.nan), sector_truth(w, np.eye(3), p, cam, 100.0))
    assert not view[18] and dist[18] == pytest.approx(28.0)  # the cylinder on the right: out of view, still known
    d_all, v_all = sector_truth_360(w, np.eye(3), p, None, 100.0)
    assert v_all.all() and np.array_equal(d_all, dist)


# ---------------------------------------------------------------------------- targets and views


def test_target_truth_positions_ranges_pixels_and_occlusion():
    w = load_world(WORLDS / "seed004_points.toml")
    cam = CameraConfig(width=320, height=240, fx=386.0, fy=386.0, cx=159.5, cy=119.5)
    R_wc, p_wc = CameraModel(cam).camera_pose(np.eye(3), np.array([0.0, 0.0, -100.0]))
    tt = target_truth(w, p_wc, R_wc, cam)
    xs = np.array([-75, -45, -15, 15, 45, 75], float)
    np.testing.assert_allclose(tt.range_m, np.hypot(300.0, xs))
    np.testing.assert_allclose(tt.depth_m, 300.0)
    np.testing.assert_allclose(tt.pixel[:, 0], 159.5 + 386.0 * xs / 300.0)
    np.testing.assert_allclose(tt.pixel[:, 1], 119.5)
    assert tt.visible.all()
    assert tt.names == ("P1", "P2", "P3", "P4", "P5", "P6")
    # a building in front of P3 hides it
    cfg = w.config
    blocked = World(WorldConfig(ground=cfg.ground, target=cfg.target, box=(BoxConfig(centre_ne_m=(150.0, -7.5), size_m=(4.0, 4.0), height_m=200.0),)))
    tt = target_truth(blocked, p_wc, R_wc, cam)
    assert list(tt.occluded) == [False, False, True, False, False, False]


def test_camera_that_sees_nothing_is_refused():
    w = load_world(WORLDS / "seed004_points.toml")
    cam = CameraConfig(width=320, height=240, fx=386.0, fy=386.0, cx=159.5, cy=119.5)
    model = CameraModel(cam)
    R_wc, p_wc = model.camera_pose(np.eye(3), np.array([0.0, 0.0, -100.0]))
    check_camera_sees_something(w, cam, R_wc, p_wc)  # only the six targets, but they are in view
    R_up, _ = model.camera_pose(euler_zyx_to_R(0.0, math.radians(60.0), 0.0), np.zeros(3))
    with pytest.raises(ConfigError, match=r"elevation \+60\.0° sees nothing but sky"):
        check_camera_sees_something(w, cam, R_up, p_wc)
    R_back, _ = model.camera_pose(euler_zyx_to_R(0.0, 0.0, math.pi), np.zeros(3))
    with pytest.raises(ConfigError, match="seed004_points.*sees nothing"):
        check_camera_sees_something(w, cam, R_back, p_wc)
    # with a ground plane, looking level already sees the ground below the horizon
    g = World(WorldConfig(ground=GroundConfig(tile_px=64)))
    assert check_camera_sees_something(g, cam, R_wc, p_wc) > 0.4


def test_world_config_is_frozen_and_names_default_to_kind_and_index():
    w = _street()
    assert [o.label for o in w.obstacles] == ["'house' (box[0])", "'fence' (wall[0])", "'mast' (cylinder[0])"]
    unnamed = World(WorldConfig(target=(TargetConfig(position_ned_m=(1.0, 2.0, -3.0)),)))
    assert unnamed.obstacles[0].label == "target[0]"
    with pytest.raises(Exception):
        w.config.seed = 3  # type: ignore[misc]
    with pytest.raises(KeyError, match="no obstacle named 'shed'"):
        w.obstacle("shed")
    assert re.search("3 obstacles", repr(w))


def test_texture_moments_do_not_depend_on_memory_alignment():
    """The grey-level normalization of every texture uses moments that are exact integer sums, so
    a seed gives the same world whatever the process allocated before (numpy's own float32 mean
    can change in the last bit with the array's address)."""
    from flightsim.world.textures import _moments, blocks_texture

    rng = np.random.default_rng(5)
    x = (rng.random((301, 257)) * 3.7 - 0.4).astype(np.float32)
    results = set()
    for offset in range(8):  # the same values at 8 different alignments
        buf = np.empty(x.size + 8, np.float32)
        view = buf[offset : offset + x.size].reshape(x.shape)
        view[...] = x
        results.add(_moments(view))
    assert len(results) == 1
    mu, sd = results.pop()
    assert mu == pytest.approx(float(np.mean(x, dtype=np.float64)), rel=1e-4)
    assert sd == pytest.approx(float(np.std(x, dtype=np.float64)), rel=1e-4)
    assert _moments(np.zeros((4, 4), np.float32)) == (0.0, 0.0)
    a = blocks_texture(np.random.default_rng(11), 64, 96, 0.1)
    b = blocks_texture(np.random.default_rng(11), 64, 96, 0.1)
    np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------- texture cache
def test_texture_cache_returns_exactly_what_a_build_makes(tmp_path, monkeypatch):
    """The disk cache of world textures: first call builds and stores, the second reads the file back
    (no build), and every mip level of every surface is identical to a fresh build; another world
    (a different ground seed) gets its own entry; ``off`` disables the cache."""
    from flightsim.world import textures as T

    monkeypatch.setenv(T.CACHE_ENV, str(tmp_path / "cache"))
    world = World(WorldConfig(
        seed=3, ground=GroundConfig(tile_px=256),
        cylinder=(CylinderConfig(name="pole", centre_ne_m=(10.0, 0.0), radius_m=0.3, height_m=6.0),),
        wall=(WallConfig(name="wall", start_ne_m=(20.0, -5.0), end_ne_m=(20.0, 5.0), height_m=4.0),)))
    ref = T.build_world_textures(world)
    first = T.cached_world_textures(world)
    files = list((tmp_path / "cache").glob("*.npz"))
    assert len(files) == 1
    built = []
    monkeypatch.setattr(T, "build_world_textures", lambda w: built.append(w))
    second = T.cached_world_textures(world)
    assert built == []  # read from the file
    for got in (first, second):
        assert len(got.ground) == len(ref.ground) and got.ground_texel_m == ref.ground_texel_m
        for a, b in zip(got.ground, ref.ground):
            np.testing.assert_array_equal(a, b)
        assert got.faces.keys() == ref.faces.keys()
        for k in ref.faces:
            assert len(got.faces[k]) == len(ref.faces[k])
            for a, b in zip(got.faces[k], ref.faces[k]):
                assert a.dtype == b.dtype and a.flags.c_contiguous
                np.testing.assert_array_equal(a, b)
    other = World(WorldConfig(seed=4, ground=GroundConfig(tile_px=256)))
    assert T.texture_cache_key(other) != T.texture_cache_key(world)
    monkeypatch.setenv(T.CACHE_ENV, "off")
    assert T.texture_cache_dir() is None


def test_damaged_texture_cache_file_is_rebuilt(tmp_path, monkeypatch):
    from flightsim.world import textures as T

    monkeypatch.setenv(T.CACHE_ENV, str(tmp_path))
    world = World(WorldConfig(seed=5, ground=GroundConfig(tile_px=128)))
    path = tmp_path / f"{T.texture_cache_key(world)}.npz"
    path.write_bytes(b"not an npz")
    tex = T.cached_world_textures(world)
    np.testing.assert_array_equal(tex.ground[0], T.build_world_textures(world).ground[0])
    with np.load(path) as arrays:  # replaced by a good file
        assert "ground/0" in arrays.files


@pytest.mark.parametrize("distortion", [(0.0, 0.0, 0.0, 0.0, 0.0), (-0.28, 0.09, 0.0012, -0.0008, -0.01)])
def test_directions_in_image_equal_the_polygon_test_of_every_point(distortion):
    """The bounding-box shortcut of the in-image test (sector and target truth) gives exactly
    OpenCV's pointPolygonTest verdict for every direction, on and near the outline too."""
    import cv2

    from flightsim.world.truth import _directions_in_image, _image_border_normalized

    cam = CameraConfig(width=320, height=240, fx=277.1, fy=277.1, cx=159.5, cy=119.5, distortion=distortion)
    rng = np.random.default_rng(3)
    d = np.concatenate([rng.normal(0, 1, (20000, 3)),  # every way, behind the camera too
                        np.c_[rng.uniform(-1, 1, (20000, 2)), np.ones(20000)]])  # in front, across the edges
    border = _image_border_normalized(cam)  # points on the outline itself and just beside it
    d = np.concatenate([d, np.c_[border, np.ones(len(border))], np.c_[border * 1.0000001, np.ones(len(border))]])
    poly = border.astype(np.float32).reshape(-1, 1, 2)
    ref = np.array([z > 1e-9 and cv2.pointPolygonTest(poly, (float(x / z), float(y / z)), False) >= 0 for x, y, z in d])
    got = _directions_in_image(cam, d)
    assert np.array_equal(got, ref)
    assert 0.05 < ref.mean() < 0.6


def test_clearance_equals_the_first_minimum_of_the_signed_distances():
    """World.clearance (Python floats, once per physics step) gives bit for bit signed_distances'
    first minimum, for every shipped world and random points outside, on and inside the solids."""
    import glob

    from flightsim.world.geometry import load_world

    rng = np.random.default_rng(11)
    worlds = [load_world(p) for p in sorted(glob.glob(str(Path(__file__).resolve().parents[1] / "configs" / "worlds" / "*.toml")))]
    assert len(worlds) >= 8
    n = 0
    for w in worlds:
        if not w.obstacles:
            assert w.clearance(np.zeros(3)) == (math.inf, None)
            continue
        centres = np.array([o.centre for o in w.obstacles])
        for _ in range(1500):
            c = centres[rng.integers(len(centres))]
            p = c + rng.normal(0.0, rng.choice([0.3, 3.0, 30.0]), 3)
            if rng.random() < 0.05:
                p = c.copy()  # the centre: inside, ties possible
            sd = w.signed_distances(p)
            k = int(np.argmin(sd))
            d, ob = w.clearance(p)
            assert type(d) is float and d == float(sd[k]) and ob is w.obstacles[k]
            n += 1
    assert n > 10000
