"""The compiled detection-priority kernel against the pure-numpy reference (docs/derivations/sectors.md;
companion/core/priority.py).  The mask is boolean: kernel and reference must agree on every pixel.

The kernel takes the reference's decisions per grid ray with the same expressions (a fixed order of
summation for the levelled ray, libm's atan2 for its bearing: each ≤ 1 ulp from numpy's), so a pixel
could differ only for a ray within an ulp of the band's edge, the travel window's edge or a sector
edge; seeded inputs never put one there, so the comparison is exact.  The enlargement to full size
must equal ``cv2.resize`` (INTER_NEAREST) plus the replicated border for every stride and size.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from companion.core import jit
from companion.core import priority as PRI
from companion.core.camera import CameraConfig, CameraModel
from companion.core.priority import detection_priority
from companion.core.sectors import SECTOR_COUNT, SectorConfig

N_CASES = 150 if jit.ENABLED else 15
CAMERAS = [
    CameraConfig.from_fov(640, 480, 60.0),
    CameraConfig.from_fov(320, 240, 90.0, mount_rpy_deg=(0.0, 10.0, -20.0)),
    CameraConfig(width=650, height=490, fx=500.0, fy=505.0, cx=330.0, cy=240.0, distortion=(-0.2, 0.05, 0.001, 0.0, 0.0),
                 mount_rpy_deg=(3.0, -5.0, 90.0)),
]


def both(monkeypatch, *args, **kwargs):
    out = []
    for enabled in (True, False):
        monkeypatch.setattr(jit, "ENABLED", enabled)
        out.append(detection_priority(*args, **kwargs))
    monkeypatch.setattr(jit, "ENABLED", True)
    return out


@pytest.mark.parametrize("cam_i", range(len(CAMERAS)))
def test_kernel_equals_reference_on_seeded_cases(monkeypatch, cam_i):
    cam = CameraModel(CAMERAS[cam_i])
    rng = np.random.default_rng(cam_i)
    marked = 0
    for i in range(N_CASES):
        cfg = dataclasses.replace(SectorConfig(), band_mode=rng.choice(["metres", "degrees"]),
                                  band_half_height_m=float(rng.uniform(0.5, 3.0)), band_half_angle_deg=float(rng.uniform(3, 20)))
        kw = dict(roll_pitch_rad=tuple(rng.normal(0, 0.3, 2)),
                  velocity_body=None if rng.random() < 0.2 else rng.normal(0, 4, 3) * rng.choice([0.1, 1.0]),
                  live_points=None if rng.random() < 0.2 else rng.integers(0, 3, SECTOR_COUNT) * (rng.random(SECTOR_COUNT) < 0.5),
                  band_range_m=float(rng.uniform(3, 20)), path_half_width_deg=float(rng.uniform(5, 40)),
                  stride=None if rng.random() < 0.5 else int(rng.integers(1, 12)))
        k, r = both(monkeypatch, cam, cfg, **kw)
        assert k.dtype == r.dtype == bool and k.shape == r.shape == (cam.config.height, cam.config.width)
        assert np.array_equal(k, r), f"camera {cam_i} case {i}: {np.count_nonzero(k != r)} pixels differ"
        marked += int(r.any()) + int(not r.all())
    assert marked > N_CASES  # masks neither all empty nor all full: the comparison discriminates


@pytest.mark.parametrize("stride", [1, 2, 3, 4, 5, 7, 8, 9, 16, 24])
def test_enlarge_equals_cv2_resize_and_border(stride):
    """The kernel's nearest-neighbour enlargement is the reference's cv2.resize + replicated border."""
    rng = np.random.default_rng(stride)
    for width, height in ((640, 480), (650, 490), (321, 241), (stride, stride), (7 * stride + 3, 2 * stride + 1)):
        n_u, n_v = len(range(stride // 2, width, stride)), len(range(stride // 2, height, stride))
        small = (rng.random((n_v, n_u)) < 0.4).astype(np.uint8)
        if stride == 1:
            continue
        ref = cv2.resize(small, (n_u * stride, n_v * stride), interpolation=cv2.INTER_NEAREST)[:height, :width]
        if ref.shape != (height, width):
            ref = cv2.copyMakeBorder(ref, 0, height - ref.shape[0], 0, width - ref.shape[1], cv2.BORDER_REPLICATE)
        np.testing.assert_array_equal(PRI._enlarge_k(small, stride, width, height), ref)


def test_edge_cases(monkeypatch):
    """No previous frame (everything in the band wanted), hovering (no direction of travel), every
    sector held, a vertical flight path at the clamp."""
    cam = CameraModel(CAMERAS[0])
    cfg = SectorConfig()
    for kw in (dict(), dict(velocity_body=[0.1, 0.0, 0.0], live_points=np.zeros(SECTOR_COUNT, int)),
               dict(velocity_body=[3.0, 1.0, 0.0], live_points=np.ones(SECTOR_COUNT, int)),
               dict(velocity_body=[0.0, 0.0, -5.0], live_points=np.ones(SECTOR_COUNT, int)),
               dict(roll_pitch_rad=(0.0, math.radians(80.0)), stride=1)):
        k, r = both(monkeypatch, cam, cfg, **kw)
        assert np.array_equal(k, r), kw
    with pytest.raises(Exception, match="live_points"):
        detection_priority(cam, cfg, live_points=np.zeros(5))


@pytest.mark.skipif(not jit.ENABLED, reason="whole flight: compiled kernels only")
def test_kernel_equals_reference_on_a_flight(monkeypatch):
    import companion.pipeline as P
    from flight_inputs import fly

    orig = P.detection_priority
    calls = []

    def both_paths(*a, **kw):
        k, r = both(monkeypatch, *a, **kw)
        assert np.array_equal(k, r), f"frame {len(calls)}"
        calls.append(int(r.sum()))
        return k

    monkeypatch.setattr(P, "detection_priority", both_paths)
    fly(frames=30)
    assert len(calls) >= 29 and min(calls) < max(calls)


def test_warm_up_is_registered():
    assert PRI._warm_up in jit._WARMUPS
    PRI._warm_up()
