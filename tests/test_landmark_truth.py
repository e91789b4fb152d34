"""flightsim.score.landmarks (python -m bench landmark_truth): each landmark's range against the truth, on exact geometry.

A wall at x = 10 m (NED north) and a camera looking north: a landmark logged exactly on the wall has z = 0,
one logged 2σ beyond it z = +2; the measured ray is taken in the camera frame, so an attitude error of the
telemetry (the logged pose) does not move the true point; the young and axis filters and the bins select
what they say."""

import numpy as np
import pytest

from flightsim.score.landmarks import landmark_z, markdown, summarize
from companion.core.frames import so3_exp

#: camera axes (x right, y down, z forward) → NED world: forward = north, right = east, down = down
R_NORTH = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def wall_raycast(origin, dirs):
    """Distance along each unit direction to the plane x = 10 (inf when looking away)."""
    with np.errstate(divide="ignore"):
        t = (10.0 - origin[0]) / dirs[:, 0]
    return np.where(t > 0, t, np.inf)


def frame(t, p_cam, R_cam, bearings_cam, ranges, sigmas, ids, converged=None):
    """A landmark-log frame: points at ``ranges`` along camera-frame bearings from the logged pose."""
    u = np.asarray(bearings_cam, float)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    p = p_cam + (u @ R_cam.T) * np.asarray(ranges, float)[:, None]
    n = len(ids)
    return {"t": t, "p_world_cam": np.asarray(p_cam, float), "R_world_cam": R_cam, "ids": np.asarray(ids),
            "p_world": p, "range": np.asarray(ranges, float), "range_sigma": np.asarray(sigmas, float),
            "mean_nis": np.full(n, np.nan), "converged": np.ones(n, bool) if converged is None else np.asarray(converged),
            "valid": np.ones(n, bool)}


def true_ranges(p_cam, R_cam, bearings_cam):
    u = np.asarray(bearings_cam, float)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return wall_raycast(p_cam, u @ R_cam.T)


def test_z_against_a_wall_on_exact_geometry():
    p = np.array([2.0, 0.0, -4.0])
    b = [[0.0, 0.0, 1.0], [0.3, -0.1, 1.0], [-0.5, 0.2, 1.0]]
    truth = true_ranges(p, R_NORTH, b)
    sig = np.array([0.5, 0.2, 1.0])
    frames = [frame(10.0, p, R_NORTH, b, truth, sig, [1, 2, 3]),
              frame(10.1, p, R_NORTH, b, truth + 2 * sig, sig, [1, 2, 3], converged=[True, True, False])]
    z = landmark_z(frames, np.array([10.0, 10.1]), np.stack([R_NORTH] * 2), np.stack([p, p]), wall_raycast)
    assert z.shape == (5, 6)  # the unconverged landmark of the second frame is left out
    only = landmark_z(frames, np.array([10.0, 10.1]), np.stack([R_NORTH] * 2), np.stack([p, p]), wall_raycast, converged=False)
    assert only.shape == (1, 6) and only[0, 4] == 3 and only[0, 0] == pytest.approx(2.0)  # ... and it alone here
    both = landmark_z(frames, np.array([10.0, 10.1]), np.stack([R_NORTH] * 2), np.stack([p, p]), wall_raycast, converged=None)
    assert both.shape == (6, 6)
    np.testing.assert_allclose(z[:3, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(z[3:, 0], 2.0, atol=1e-9)
    np.testing.assert_allclose(z[:3, 1], truth, rtol=1e-12)
    np.testing.assert_array_equal(z[:, 4], [1, 2, 3, 1, 2])


def test_the_ray_is_taken_in_the_camera_frame_from_the_true_pose():
    """The telemetry's attitude is 2° off: the logged point lies along the *camera-frame* bearing of the pixel,
    which the true camera sees at the true range; z stays 0 where a world-frame ray would not."""
    p_true = np.array([0.0, 0.0, -4.0])
    R_tel = R_NORTH @ so3_exp(np.radians([0.0, 2.0, 0.0]))
    p_tel = p_true + np.array([0.05, -0.03, 0.0])
    b = [[0.4, 0.0, 1.0], [-0.4, 0.1, 1.0]]
    truth = true_ranges(p_true, R_NORTH, b)
    f = frame(5.0, p_tel, R_tel, b, truth, [0.3, 0.3], [7, 8])
    z = landmark_z([f], np.array([5.0]), R_NORTH[None], p_true[None], wall_raycast)
    np.testing.assert_allclose(z[:, 0], 0.0, atol=1e-9)


def test_young_axis_and_missing_truth_select_what_they_say():
    p = np.array([0.0, 0.0, -4.0])
    b = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]  # on the axis, and 45° off it
    truth = true_ranges(p, R_NORTH, b)
    frames = [frame(0.0, p, R_NORTH, b[:1], truth[:1], [0.5], [1]),
              frame(5.0, p, R_NORTH, b, truth, [0.5, 0.5], [1, 2]),
              frame(5.5, p, R_NORTH, b, truth, [0.5, 0.5], [1, 2])]  # no truth pose at 5.5 s
    t, R, P = np.array([0.0, 5.0]), np.stack([R_NORTH] * 2), np.stack([p, p])
    assert len(landmark_z(frames, t, R, P, wall_raycast)) == 3
    young = landmark_z(frames, t, R, P, wall_raycast, young_s=1.0)
    np.testing.assert_array_equal(young[:, 4], [1, 2])  # landmark 1 is 5 s old at 5 s
    axis = landmark_z(frames, t, R, P, wall_raycast, axis_deg=10.0)
    np.testing.assert_array_equal(axis[:, 4], [1, 1])


def test_summary_bins_and_table():
    s = np.array([[0.0, 2.0, 2.0, 0.1, 1, 0.0], [4.0, 4.0, 4.4, 0.1, 2, 0.0], [-4.0, 4.5, 4.1, 0.1, 3, 0.0]])
    rows = summarize(s, (0.0, 3.0, 5.0, 8.0))
    assert [r["n"] for r in rows] == [1, 2, 0]
    assert rows[1]["mean_z"] == pytest.approx(0.0) and rows[1]["nees"] == pytest.approx(16.0)
    assert rows[1]["long_3sigma"] == pytest.approx(0.5) and rows[1]["short_3sigma"] == pytest.approx(0.5)
    assert rows[1]["within_2sigma"] == 0.0 and rows[0]["within_2sigma"] == 1.0
    assert rows[1]["median_rel_sigma"] == pytest.approx(np.median([0.1 / 4.4, 0.1 / 4.1]))
    assert rows[1]["median_rel_error"] == pytest.approx(np.median([0.4 / 4.0, 0.4 / 4.5]))
    text = markdown(rows)
    assert "| 3–5 m | 2 (2) | +0.00 |" in text and "| 5–8 m | 0 |" in text and "| 0.024 | 0.094 |" in text
