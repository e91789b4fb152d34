"""Track manager (DESIGN.md §3.1–§3.2): ids persist, positions follow truth, bounded, bad input."""

import cv2
import numpy as np
import pytest

from companion.core import ncc, tracks
from companion.core.camera import CameraConfig, CameraModel
from companion.core.harris import HarrisConfig
from companion.core.ncc import NCCConfig
from companion.core.tracks import DROP_REASON_NAMES, TrackConfig, TrackManager
from companion.errors import ConfigError, InputError

W, H, SS = 320, 240, 4


class Scene:
    """Band-limited noise, 4× supersampled: render(shift) is the texture moved by ``shift`` px."""

    def __init__(self, seed=0, margin=80):
        rng = np.random.default_rng(seed)
        big = rng.standard_normal(((H + 2 * margin) * SS, (W + 2 * margin) * SS)).astype(np.float32)
        self.big = cv2.GaussianBlur(big, (0, 0), 1.2 * SS)
        self.big /= self.big.std()
        self.m = margin

    def render(self, shift):
        sx, sy = int(round(shift[0] * SS)), int(round(shift[1] * SS))
        y0, x0 = self.m * SS - sy, self.m * SS - sx
        crop = self.big[y0 : y0 + H * SS, x0 : x0 + W * SS]
        img = cv2.resize(crop, (W, H), interpolation=cv2.INTER_AREA)
        return np.clip(128 + 45 * img, 0, 255).round().astype(np.uint8)


@pytest.fixture(scope="module")
def scene():
    return Scene()


def camera():
    return CameraModel(CameraConfig.from_fov(W, H, 60.0))


def manager(max_tracks=120, **kw):
    """A tracker; the plain frame-to-frame one (drift correction off, the 15 × 15 reference these tests were written
    for) unless ``kw`` says otherwise: the tests of the correction turn it on themselves."""
    kw = {"reference_correct_px": 0.0, "reference_half": 7, **kw}
    return TrackManager(camera(), HarrisConfig(), NCCConfig(), TrackConfig(max_tracks=max_tracks, **kw))


def test_tracks_follow_a_translated_texture(scene):
    steps = np.array([[0, 0], [1.25, 0.5], [1.5, -0.75], [2.0, 0.25], [0.75, 1.0], [-1.0, 0.5], [3.0, 0.0], [0.5, -2.25]])
    shifts = np.cumsum(steps, 0)
    tm = manager()
    first = tm.step(scene.render(shifts[0]), 0.0, 0)
    assert len(first.ids) == 120 and np.array_equal(first.ids, first.new_ids)
    assert first.ids.dtype == np.int64 and np.all(first.score == 1.0)
    start = dict(zip(first.ids.tolist(), first.uv))
    for k in range(1, len(shifts)):
        fr = tm.step(scene.render(shifts[k]), k / 30.0, k)
        old = np.isin(fr.ids, first.ids)
        assert old.sum() >= 100, "ids must persist while the points stay visible"
        truth = np.array([start[i] for i in fr.ids[old].tolist()]) + shifts[k]
        err = np.linalg.norm(fr.uv[old] - truth, axis=1)
        assert err.max() < 0.3, f"frame {k}: worst track error {err.max():.3f} px"
        assert np.all(fr.score[old] > 0.8)
        assert tm.n_live <= 120
    # the track's record: anchor, observations with frame index and time
    tid = int(fr.ids[old][0])
    tr = tm.tracks[tid]
    assert tr.anchor_frame == 0 and tr.anchor_t == 0.0 and np.allclose(tr.anchor_uv, start[tid])
    assert [o[0] for o in tr.observations] == list(range(len(shifts)))
    assert np.allclose([o[1] for o in tr.observations], np.arange(len(shifts)) / 30.0)
    assert np.allclose(tr.observations[-1][2], fr.uv[fr.ids == tid][0])
    assert tr.age == len(shifts) - 1 and tr.n_observations == len(shifts) and tr.alive
    again = tm.track(tid)
    assert again.id == tid and again.n_observations == tr.n_observations


def test_leaving_tracks_are_dropped_and_replaced(scene):
    tm = manager(max_tracks=80, redetect_fraction=0.9)
    fr = tm.step(scene.render((0.0, 0.0)), 0.0, 0)
    seen = set(fr.ids.tolist())
    gone = set()
    reasons = []
    for k in range(1, 13):
        fr = tm.step(scene.render((-5.0 * k, 0.0)), float(k), k)  # texture slides left, 5 px per frame
        assert tm.n_live <= 80 and len(fr.ids) <= 80
        assert not (set(fr.ids.tolist()) & gone), "a dropped id came back"
        assert set(fr.dropped_ids.tolist()) <= seen
        assert len(fr.dropped_ids) == len(fr.drop_reason)
        gone |= set(fr.dropped_ids.tolist())
        reasons += fr.drop_reason.tolist()
        seen |= set(fr.new_ids.tolist())
        assert not (set(fr.new_ids.tolist()) & (seen - set(fr.new_ids.tolist())))  # ids are never reused
        # every dropped track is still readable in this frame, not afterwards
        for i in fr.dropped_ids.tolist():
            assert not tm.track(i).alive
    assert len(gone) >= 10, "points that slid out of the image must be dropped"
    assert ncc.OUT_OF_IMAGE in reasons
    assert all(r in DROP_REASON_NAMES for r in reasons)
    assert tm.n_live >= 0.9 * 80 - 10, "dropped tracks must be replaced by new corners"
    old_live = [i for i in tm.live_ids().tolist() if tm.track(i).anchor_frame == 0]
    for i in old_live:  # survivors from the first frame sit in the part of the texture still visible
        assert tm.track(i).anchor_uv[0] > 60 - 1
    with pytest.raises(KeyError):
        tm.track(next(iter(gone - set(fr.dropped_ids.tolist()))))


def test_track_count_is_bounded_and_history_is_capped(scene):
    tm = manager(max_tracks=30, max_history=4, redetect_fraction=1.0)
    for k in range(8):
        fr = tm.step(scene.render((0.5 * k, 0.25 * k)), 0.1 * k, 10 + k)
        assert len(fr.ids) <= 30 and tm.n_live <= 30 and len(tm.tracks) == tm.n_live
    tid = int(tm.live_ids()[0])
    tr = tm.track(tid)
    assert len(tr.observations) == 4 and tr.n_observations == 8 and tr.anchor_frame == 10
    assert [o[0] for o in tr.observations] == [14, 15, 16, 17]
    assert tid in tm.tracks and list(tm.tracks) == tm.live_ids().tolist()


def test_predictor_centres_the_search(scene):
    step = np.array([15.0, -6.0])  # far beyond the default ±8 px window
    blind = manager(max_tracks=60)
    guided = manager(max_tracks=60)
    ids0 = blind.step(scene.render((0, 0)), 0.0, 0).ids
    guided.step(scene.render((0, 0)), 0.0, 0)
    calls = []

    def predict(uv, ids):
        calls.append((uv.shape, ids.copy()))
        return uv + step, np.full(len(uv), 2.0)

    fb = blind.step(scene.render(step), 1.0, 1)
    fg = guided.step(scene.render(step), 1.0, 1, predict=predict)
    assert np.isin(fg.ids, ids0).sum() > 50
    assert np.isin(fb.ids, ids0).sum() < 10
    assert calls and calls[0][0] == (60, 2) and np.array_equal(np.sort(calls[0][1]), np.sort(ids0))


def test_coasting_tracks_survive_one_bad_frame(scene):
    tm = manager(max_tracks=50, max_failures=2)
    ids0 = tm.step(scene.render((0, 0)), 0.0, 0).ids
    noise = np.random.default_rng(5).integers(0, 256, (H, W)).astype(np.uint8)
    bad = tm.step(noise, 1.0, 1)  # e.g. a corrupted frame: every match fails
    assert len(bad.dropped_ids) < 5 and tm.n_live >= 45
    assert all(tm.track(i).failures == 1 for i in ids0.tolist() if i in tm.tracks)
    fr = tm.step(scene.render((1.5, 0.5)), 2.0, 2)  # back: matched from the stored templates
    back = np.isin(fr.ids, ids0)
    assert back.sum() > 40
    start = {}
    for i in fr.ids[back].tolist():
        start[i] = tm.track(i).anchor_uv
    err = np.linalg.norm(fr.uv[back] - (np.array([start[i] for i in fr.ids[back].tolist()]) + (1.5, 0.5)), axis=1)
    assert err.max() < 0.3
    once = manager(max_tracks=50)  # default: dropped at the first failure
    once.step(scene.render((0, 0)), 0.0, 0)
    assert len(once.step(noise, 1.0, 1).dropped_ids) > 45


def test_tracks_converging_on_one_point_keep_the_oldest(scene):
    tm = manager(max_tracks=40)
    ids0 = tm.step(scene.render((0, 0)), 0.0, 0).ids
    a, b, c = (int(i) for i in ids0[:3])
    target = tm.track(a).anchor_uv

    def predict(uv, ids):  # a (bad) prediction sending tracks b and c onto track a's point
        out = uv.copy()
        out[np.isin(ids, [b, c])] = target
        return out, np.where(np.isin(ids, [b, c]), 1.0, 8.0)

    fr = tm.step(scene.render((0, 0)), 1.0, 1, predict=predict)
    # b and c cannot match a's texture (low score) — unless they do, then they are duplicates of a
    assert a in fr.ids.tolist()
    assert b not in fr.ids.tolist() and c not in fr.ids.tolist()
    assert set(fr.dropped_ids.tolist()) >= {b, c}
    # direct check of the duplicate rule on two live tracks placed 0.4 px apart
    sa, sb = tm._slot_of[a], tm._slot_of[int(fr.ids[fr.ids != a][0])]
    tm._uv[sb] = tm._uv[sa] + 0.4
    dup = tm._duplicates(np.array([sa, sb]), 1.0)
    assert dup.tolist() == [sb]


def test_bad_input_names_the_problem(scene):
    tm = manager(max_tracks=20)
    img = scene.render((0, 0))
    tm.step(img, 1.0, 0)
    with pytest.raises(InputError, match="strictly increasing"):
        tm.step(img, 1.0, 1)
    with pytest.raises(InputError, match="strictly increasing"):
        tm.step(img, 0.5, 1)
    with pytest.raises(InputError, match="frame_index must increase"):
        tm.step(img, 2.0, 0)
    with pytest.raises(InputError, match="finite"):
        tm.step(img, float("nan"), 1)
    with pytest.raises(InputError, match="shape"):
        tm.step(img[:100], 2.0, 1)
    with pytest.raises(InputError, match="empty"):
        tm.step(img[:0], 2.0, 1)
    with pytest.raises(InputError, match="uint8"):
        tm.step(img.astype(np.float32), 2.0, 1)
    with pytest.raises(InputError, match="colour"):
        tm.step(np.dstack([img] * 3), 2.0, 1)
    with pytest.raises(InputError, match="NaN"):
        tm.step(img, 2.0, 1, predict=lambda uv, ids: (uv * np.nan, 3.0))
    with pytest.raises(InputError, match="uv_pred"):
        tm.step(img, 2.0, 1, predict=lambda uv, ids: (uv[:1], 3.0))
    with pytest.raises(InputError, match="radius"):
        tm.step(img, 2.0, 1, predict=lambda uv, ids: (uv, -1.0))
    # a rejected frame leaves the manager usable
    fr = tm.step(img, 2.0, 1)
    assert len(fr.ids) == 20
    with pytest.raises(ConfigError, match="max_tracks"):
        TrackConfig(max_tracks=0)
    with pytest.raises(ConfigError, match="border"):
        TrackManager(camera(), HarrisConfig(border=4), NCCConfig(), TrackConfig())


def test_killed_tracks_end_for_good(scene):
    tm = manager(max_tracks=60)
    first = tm.step(scene.render(np.zeros(2)), 0.0, 0)
    victims = first.ids[:10]
    assert tm.kill(np.concatenate([victims, [999_999]])) == 10  # unknown ids are ignored
    assert tm.n_live == 50 and not np.any(np.isin(tm.live_ids(), victims))
    fr = tm.step(scene.render(np.array([1.0, 0.5])), 1 / 30, 1)
    assert not np.any(np.isin(fr.ids, victims)), "a killed track must not be observed again"
    assert tm.n_live <= 60 and set(fr.ids.tolist()) <= set(first.ids[10:].tolist()) | set(fr.new_ids.tolist())


# ---- the reference-patch check (feature monitoring: occlusion edges and drift) ---------------------

def _layers(fg, bg, k, x0=160):
    """A static near layer left of column ``x0`` over a far texture sliding right by 1 px per frame:
    corners on the boundary are T-junctions whose two halves move apart."""
    img = bg.render((1.0 * k, 0.0))
    img[:, :x0] = fg.render((0.0, 0.0))[:, :x0]
    return img


def _fates(tm, frames, R=lambda k: None):
    f0 = tm.step(frames(0), 0.0, 0, R_world_cam=R(0))
    x0 = dict(zip(f0.ids.tolist(), f0.uv[:, 0]))
    fate = {}
    for k in range(1, 16):
        fr = tm.step(frames(k), k / 30.0, k, R_world_cam=R(k))
        for i, r in zip(fr.dropped_ids.tolist(), fr.drop_reason.tolist()):
            fate.setdefault(i, r)
    return x0, fate


@pytest.mark.parametrize("threshold", [0.5, 0.7])
def test_reference_check_drops_t_junctions_and_keeps_surface_points(threshold):
    fg, bg = Scene(seed=1), Scene(seed=2)
    frames = lambda k: _layers(fg, bg, k)  # noqa: E731
    kw = dict(max_tracks=200, redetect_fraction=0.0)
    x_off, fate_off = _fates(manager(reference_min_ncc=0.0, **kw), frames)
    x_on, fate_on = _fates(manager(reference_min_ncc=threshold, **kw), frames)
    assert x_off == x_on  # same corners either way
    edge = [i for i, x in x_on.items() if abs(x - 160) < 5]
    inner = [i for i, x in x_on.items() if abs(x - 160) > 15]
    assert len(edge) >= 4 and len(inner) >= 100
    # frame-to-frame matching keeps the T-junctions: the template is re-cut where the track sits
    assert not any(fate_off.get(i) == tracks.DROP_REFERENCE for i in x_off)
    assert sum(i not in fate_off for i in edge) >= 0.8 * len(edge)
    # the reference check drops them, and no point inside either layer
    assert sum(fate_on.get(i) == tracks.DROP_REFERENCE for i in edge) >= 0.8 * len(edge)
    assert not any(fate_on.get(i) == tracks.DROP_REFERENCE for i in inner)
    assert DROP_REASON_NAMES[tracks.DROP_REFERENCE] == "reference mismatch"


def _rolled(base, k, deg):
    M = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), deg * k, 1.0)
    return cv2.warpAffine(base, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _Rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_reference_check_undoes_the_camera_rotation(scene):
    """The camera rolls 1.5° per frame about its optical axis (the image turns the other way):
    with the attitude the check warps each reference by the rotation's homography and keeps every
    track; without it the turned patches stop matching; with a wrong attitude all of them go."""
    base = scene.render((0.0, 0.0))
    frames = lambda k: _rolled(base, k, 1.5)  # noqa: E731
    kw = dict(max_tracks=150, redetect_fraction=0.0, reference_min_ncc=0.5)
    for R, expect in ((lambda k: _Rz(np.radians(1.5 * k)), "none"), (lambda k: None, "some"),
                      (lambda k: _Rz(np.radians(-1.5 * k)), "all")):
        x, fate = _fates(manager(**kw), frames, R)
        n_ref = sum(r == tracks.DROP_REFERENCE for r in fate.values())
        if expect == "none":
            assert n_ref == 0
        elif expect == "some":
            assert n_ref >= 10
        else:
            assert n_ref >= 0.8 * len(x)


def test_reference_check_keeps_tracks_through_a_zoom(scene):
    """Looming: the image grows 1.5 % per frame about its centre; the reference is compared at the
    scale change since it was cut, so only tracks that leave the image end."""
    base = scene.render((0.0, 0.0))

    def frames(k):
        M = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), 0.0, 1.015 ** k)
        return cv2.warpAffine(base, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    x, fate = _fates(manager(max_tracks=150, redetect_fraction=0.0, reference_min_ncc=0.5), frames)
    assert len(x) == 150 and not any(r == tracks.DROP_REFERENCE for r in fate.values())


def test_reference_check_on_a_translation_changes_nothing(scene):
    steps = np.array([[0, 0], [1.25, 0.5], [1.5, -0.75], [2.0, 0.25], [0.75, 1.0], [-1.0, 0.5], [3.0, 0.0], [0.5, -2.25]])
    shifts = np.cumsum(np.tile(steps, (3, 1)), 0)
    out = []
    for thr in (0.0, 0.7):
        tm = manager(reference_min_ncc=thr)
        fr = [tm.step(scene.render(s), k / 30.0, k) for k, s in enumerate(shifts)]
        assert not any(np.any(f.drop_reason == tracks.DROP_REFERENCE) for f in fr)
        out.append(fr[-1])
    assert np.array_equal(out[0].ids, out[1].ids) and np.array_equal(out[0].uv, out[1].uv)


def test_zncc_patches():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(3, 7, 7))
    b = np.stack([2 * a[0] + 5, -a[1], rng.normal(size=(7, 7))])
    r = tracks.zncc_patches(a, b)
    assert r[0] == pytest.approx(1.0) and r[1] == pytest.approx(-1.0)
    ref = np.corrcoef(a[2].ravel(), b[2].ravel())[0, 1]
    assert r[2] == pytest.approx(ref, rel=1e-5)
    flat = tracks.zncc_patches(np.ones((1, 5, 5)), a[:1, :5, :5])
    assert np.isnan(flat[0])


@pytest.mark.parametrize("bad", [dict(reference_min_ncc=-0.1), dict(reference_min_ncc=1.0), dict(reference_min_ncc=float("nan")),
                                 dict(reference_half=1), dict(reference_half=2.5), dict(reference_refresh_frames=0),
                                 dict(reference_refresh_frames=True)])
def test_reference_settings_are_validated(bad):
    with pytest.raises(ConfigError):
        TrackConfig(**bad)


def test_reference_check_rejects_a_bad_attitude(scene):
    tm = manager(reference_min_ncc=0.5)
    with pytest.raises(InputError, match="R_world_cam"):
        tm.step(scene.render((0.0, 0.0)), 0.0, 0, R_world_cam=np.full((3, 3), np.nan))


def test_reference_kernel_equals_the_numpy_reference(scene):
    """The compiled check (companion/core/tracks_kernels.py) against _warped_patches + zncc_patches:
    the same in-image verdicts, NCC equal to float rounding, on warped, scaled and partly outside grids."""
    from companion.core import tracks_kernels

    img = scene.render((0.0, 0.0))
    rng = np.random.default_rng(7)
    n = 200
    tm = manager(max_tracks=n, reference_min_ncc=0.5)
    slots = np.arange(n)
    tm._uv[:] = np.column_stack([rng.uniform(-5, W + 5, n), rng.uniform(-5, H + 5, n)])  # some grids leave the image
    A = np.eye(2)[None] * rng.uniform(0.7, 1.4, (n, 1, 1)) + rng.normal(0, 0.15, (n, 2, 2))
    cur, inside = tm._warped_patches(img, slots, A)
    noise = rng.uniform(5, 120, (n, 1, 1)) * rng.standard_normal(cur.shape)
    tm._ref[:] = (cur + noise).astype(np.float32)  # related patches, more or less: NCC spread over (0, 1)
    ref_ncc = tracks.zncc_patches(tm._ref, cur)
    ncc, ins = np.empty(n), np.empty(n, bool)
    tracks_kernels.reference_ncc_k(img, tm._ref, np.ascontiguousarray(tm._uv), A, ncc, ins)
    assert np.array_equal(ins, inside) and 20 < inside.sum() < n
    assert np.all(np.isnan(ncc[~ins]))
    assert np.max(np.abs(ncc[ins] - ref_ncc[ins])) < 1e-5
    assert np.ptp(ncc[ins]) > 0.3
    flat = np.full((1, 15, 15), 7.0, np.float32)
    one = np.empty(1)
    tracks_kernels.reference_ncc_k(img, flat, np.array([[160.0, 120.0]]), np.eye(2)[None], one, np.empty(1, bool))
    assert np.isnan(one[0])


def _half_textured(scene, textured_right: bool):
    """The scene's texture on the left half (and on the right half too when ``textured_right``), flat grey elsewhere."""
    img = scene.render((0.0, 0.0))
    if not textured_right:
        img = img.copy()
        img[:, W // 2 :] = 128
    return img


@pytest.mark.parametrize("backoff", [0, 3])
def test_refill_backs_off_while_the_image_holds_no_free_texture(scene, monkeypatch, backoff):
    """A refill that finds (almost) nothing pauses the refills for ``refill_backoff_frames`` frames; new
    texture is taken up at the next refill, and refills that find plenty do not back off."""
    calls = []
    real = tracks.detect_harris

    def counting(gray, *a, **kw):
        pts, resp = real(gray, *a, **kw)
        calls.append((len(calls), kw.get("max_corners"), len(pts)))
        return pts, resp

    monkeypatch.setattr(tracks, "detect_harris", counting)
    tm = manager(max_tracks=300, redetect_fraction=1.0, refill_backoff_frames=backoff, refill_backoff_yield=0.25)
    refill_frames = []
    for k in range(14):
        n_before = len(calls)
        fr = tm.step(_half_textured(scene, textured_right=k >= 7), k / 30.0, k)
        if len(calls) > n_before:
            refill_frames.append(k)
            assert fr.refill == tracks.REFILL_RUN
        else:  # always short of tracks here: a frame without a refill is one the back-off held
            assert fr.refill == tracks.REFILL_PAUSED
        if k == 0:
            n_first = len(fr.new_ids)
            assert 0.25 * 300 < n_first < 200  # the left half holds far fewer corners than 300
        if k >= 1 and k < 7 and len(calls) > n_before:
            assert calls[-1][2] < 0.25 * calls[-1][1], "with the left half taken, a refill finds little"
    if backoff == 0:
        assert refill_frames == list(range(14)), "without back-off every short frame refills"
    else:
        # 0: the first fill (plenty, no back-off); 1: finds little -> 2, 3, 4 skipped; 5 -> 6, 7, 8 skipped;
        # 9: the right half's new texture is found (plenty) -> no back-off, 10 refills again
        assert refill_frames[:4] == [0, 1, 5, 9], refill_frames
        assert 10 in refill_frames
    assert tm.n_live > n_first + 50, "the texture that appeared is tracked after the back-off"


@pytest.mark.parametrize("bad", [dict(refill_backoff_frames=-1), dict(refill_backoff_frames=2.5), dict(refill_backoff_frames=True),
                                 dict(refill_backoff_yield=1.5), dict(refill_backoff_yield=float("nan")),
                                 dict(refill_backoff_priority=1)])
def test_refill_backoff_settings_are_validated(bad):
    with pytest.raises(ConfigError):
        TrackConfig(**bad)


@pytest.mark.parametrize("topup", [True, False])
def test_refill_pause_spares_the_priority_region_top_up(scene, topup):
    """During a pause the priority region's own top-up still runs (``refill_backoff_priority``): texture that
    appears there is seeded at once, not after the pause."""
    tm = manager(max_tracks=300, redetect_fraction=1.0, refill_backoff_frames=3, refill_backoff_yield=0.25,
                 refill_backoff_priority=topup, priority_min_tracks=20)
    region = np.zeros((H, W), bool)
    region[:, W // 2 + 20 :] = True  # the right half, where texture appears at frame 7
    seeded_at = None
    for k in range(10):
        fr = tm.step(_half_textured(scene, textured_right=k >= 7), k / 30.0, k, priority_mask=region)
        q = np.rint(fr.uv[np.isin(fr.ids, fr.new_ids)]).astype(int)  # the new corners, in id order as new_ids
        n_in_region = int(np.count_nonzero(region[q[:, 1], q[:, 0]]))
        if k >= 7 and seeded_at is None and n_in_region >= 10:
            seeded_at = k
    # frames 1, 5 pause (found little) -> 6, 7, 8 held for the plain refill; 9 runs it
    assert seeded_at == (7 if topup else 9), seeded_at


# ---- drift correction: matches re-aligned to the reference patch (the template update problem) --------------------
def _zoom_frames(scene, n=120, rate=1.006, shift=(0.37, -0.21), noise=2.0, seed=1):
    """The texture zooming about a point off the image centre while it translates, with pixel noise:
    frame k is the similarity x → c0 + s_k (x − c0) + t_k of frame 0 (exactly known)."""
    base = scene.render((0.0, 0.0)).astype(np.float32)
    rng = np.random.default_rng(seed)
    c0 = np.array([(W - 1) / 2 + 7.3, (H - 1) / 2 - 4.1])

    def M(k):
        return rate**k, np.array(shift) * k

    frames = []
    for k in range(n):
        s, t = M(k)
        A = np.array([[s, 0, (1 - s) * c0[0] + t[0]], [0, s, (1 - s) * c0[1] + t[1]]])
        img = cv2.warpAffine(base, A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        frames.append(np.clip(img + noise * rng.standard_normal(img.shape), 0, 255).round().astype(np.uint8))
    return frames, lambda k, uv0: c0 + M(k)[0] * (uv0 - c0) + M(k)[1]


def _errors_at_end(tm, frames, truth):
    f0 = tm.step(frames[0], 0.0, 0, R_world_cam=np.eye(3))
    start = dict(zip(f0.ids.tolist(), f0.uv))
    for k in range(1, len(frames)):
        fr = tm.step(frames[k], k / 30.0, k, R_world_cam=np.eye(3))
    old = [(i, uv) for i, uv in zip(fr.ids.tolist(), fr.uv) if i in start]
    err = np.array([np.linalg.norm(uv - truth(len(frames) - 1, start[i])) for i, uv in old])
    return err, tm.tracks[old[0][0]], fr


def test_drift_correction_holds_tracks_on_their_points(scene):
    """Four seconds of zoom (×2) and translation with pixel noise: re-cutting the template every frame lets each
    track random-walk off its point (median 0.5 px after 120 frames); re-aligned to the reference patch, with the
    scale estimated alongside, the tracks stay within a few hundredths of a pixel.  The corrected pixels are what
    the track's history records."""
    frames, truth = _zoom_frames(scene)
    err_off, _, _ = _errors_at_end(manager(max_tracks=150, redetect_fraction=0.0), frames, truth)
    err_on, tr, fr = _errors_at_end(manager(max_tracks=150, redetect_fraction=0.0, reference_correct_px=1.0,
                                        reference_refresh_scale=1.3), frames, truth)
    assert len(err_on) >= 0.9 * len(err_off) and len(err_on) >= 20
    assert np.median(err_off) > 0.3  # the drift the correction is for
    assert np.median(err_on) < 0.08 and np.percentile(err_on, 90) < 0.15
    last = tr.observations[-1][2]
    assert np.array_equal(last, fr.uv[fr.ids == tr.id][0])  # the history holds the corrected pixel
    assert np.linalg.norm(last - truth(len(frames) - 1, tr.anchor_uv)) < 0.1


def test_drift_correction_off_changes_nothing(scene):
    """reference_correct_px = 0 (as shipped) is the plain tracker, pixel for pixel, with or without the check."""
    frames, _ = _zoom_frames(scene, n=20)
    out = []
    for kw in (dict(), dict(reference_correct_px=0.0, reference_correct_min_ncc=0.3, reference_refresh_scale=1.5)):
        tm = manager(max_tracks=100, **kw)
        out.append([tm.step(f, k / 30.0, k, R_world_cam=np.eye(3)) for k, f in enumerate(frames)][-1])
    assert np.array_equal(out[0].ids, out[1].ids) and np.array_equal(out[0].uv, out[1].uv)


def test_drift_correction_kernel_equals_the_numpy_reference(scene):
    """The compiled inverse-compositional Gauss–Newton (companion/core/tracks_kernels.py, correct_drift_k) against
    TrackManager._drift_parameters: the same verdicts, parameters and NCC equal to float rounding, on shifted,
    scaled and partly outside patches, and flat ones."""
    from companion.core import tracks_kernels

    frames, truth = _zoom_frames(scene, n=2, rate=1.03)
    img0, img1 = frames
    rng = np.random.default_rng(3)
    n = 150
    tm = manager(max_tracks=n, reference_correct_px=1.5)
    slots = np.arange(n)
    uv0 = np.column_stack([rng.uniform(-10, W + 10, n), rng.uniform(-10, H + 10, n)])
    tm._uv[:] = uv0
    tm._cut_reference(img0, slots, 0)
    tm._ref[:3] = 9.0  # flat
    tm._ref_scale[:] = 1.03 * rng.uniform(0.95, 1.05, n)
    uv1 = truth(1, uv0) + rng.normal(0, 0.4, (n, 2))
    tm._uv[:] = uv1
    A = np.ascontiguousarray(tm._reference_warp(slots))
    par_r, ncc_r = tm._drift_parameters(img1, slots, uv1, A, 2)
    par_k, ncc_k = np.empty((n, 3)), np.empty(n)
    tracks_kernels.prepare_reference_k(tm._ref, slots, tm._ref_T, tm._ref_G, tm._ref_Nc, tm._ref_fit)
    assert not tm._ref_fit[:3].any()  # flat references cannot be aligned
    tracks_kernels.correct_drift_k(img1, tm._ref_T, tm._ref_G, tm._ref_Nc, tm._ref_fit, slots, np.ascontiguousarray(uv1),
                                   A, 1.5, tracks._MAX_DRIFT_SCALE, 2, par_k, ncc_k)
    ok_r, ok_k = np.isfinite(ncc_r), np.isfinite(ncc_k)
    assert np.array_equal(ok_k, ok_r) and 30 < ok_r.sum() < n - 10
    assert not ok_r[:3].any()
    assert np.max(np.abs(par_k - par_r)) < 1e-4 and np.max(np.abs(ncc_k[ok_k] - ncc_r[ok_r])) < 1e-5
    assert np.all(par_r[~ok_r] == [0.0, 0.0, 1.0])
    # the corrections move the matches towards the truth, and the reference then correlates well
    moved = uv1[ok_r] + par_r[ok_r, :2]
    before = np.linalg.norm(uv1[ok_r] - truth(1, uv0[ok_r]), axis=1)
    after = np.linalg.norm(moved - truth(1, uv0[ok_r]), axis=1)
    assert np.median(after) < 0.5 * np.median(before)
    assert np.median(ncc_r[ok_r]) > 0.9


@pytest.mark.parametrize("bad", [dict(reference_correct_px=-1.0), dict(reference_correct_px=float("nan")),
                                 dict(reference_correct_min_ncc=1.0), dict(reference_correct_min_ncc=-1.5),
                                 dict(reference_refresh_scale=1.0), dict(reference_refresh_scale=0.5),
                                 dict(reference_refresh_scale=float("inf"))])
def test_drift_correction_settings_are_validated(bad):
    with pytest.raises(ConfigError):
        TrackConfig(**bad)


def test_reference_cut_and_warp_kernels_equal_the_numpy_reference(scene, monkeypatch):
    """The compiled reference cut and reference warp (companion/core/tracks_kernels.py: cut_reference_k,
    reference_warp_k) against TrackManager's numpy lines (extract_scaled_templates at scale 1; the einsum warp):
    the same in-image verdicts, patches within one grey level (the reference's remap puts the sub-pixel point on a
    1/32 px grid), warps equal to float rounding, with rotated and unknown attitudes, points near and behind the
    camera's plane and slots in any order."""
    from companion.core import jit

    if not jit.ENABLED:
        pytest.skip("compiled kernels off: nothing to compare")
    img = scene.render((0.0, 0.0))
    rng = np.random.default_rng(7)
    n = 200
    slots = rng.permutation(n)
    uv0 = np.column_stack([rng.uniform(-5, W + 5, n), rng.uniform(-5, H + 5, n)])
    out = {}
    for kernels in (False, True):
        monkeypatch.setattr(jit, "ENABLED", kernels)
        tm = manager(max_tracks=n, reference_correct_px=0.5)
        tm._uv[:] = uv0
        tm._cut_reference(img, slots, 0)
        warps = []
        for trial in range(40):
            r = np.random.default_rng(100 + trial)
            Q, _ = np.linalg.qr(r.normal(size=(3, 3)))
            tm._ref_R[:] = Q @ (np.eye(3) + r.normal(0, 0.3 if trial % 4 == 0 else 0.05, (n, 3, 3)))
            tm._ref_R_ok[:] = r.random(n) > 0.1
            tm._ref_uv[:] = np.column_stack([r.uniform(0, W, n), r.uniform(0, H, n)])
            tm._ref_scale[:] = r.uniform(0.8, 1.3, n)
            tm._R_now = None if trial % 10 == 0 else Q @ (np.eye(3) + r.normal(0, 0.05, (3, 3)))
            warps.append(tm._reference_warp(slots))
        out[kernels] = dict(ref=tm._ref.copy(), ok=tm._ref_ok.copy(), A=np.stack(warps))
    ref_np, ref_k = out[False], out[True]
    assert np.array_equal(ref_np["ok"], ref_k["ok"]) and 20 < ref_np["ok"].sum() < n
    assert np.all(ref_k["ref"][~ref_k["ok"]] == 0)
    d = np.abs(ref_np["ref"].astype(float) - ref_k["ref"])
    assert d.max() <= 1.0 and (d > 0).mean() < 0.1
    A_np, A_k = ref_np["A"], ref_k["A"]
    assert np.all(np.isfinite(A_k))
    assert np.max(np.abs(A_np - A_k)) < 1e-12
    eye = np.all(A_np == np.eye(2) * A_np[..., :1, :1], axis=(2, 3))
    assert eye.any() and not eye.all()  # unknown attitudes and turned-away points stay at S·I; others are warped
