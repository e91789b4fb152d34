"""The compiled multi-view triangulation (triangulation._multiview_kernel) against the numpy reference.

Tolerance: the kernel solves the 3×3 normal equations by the adjugate where the reference calls
LAPACK (LU), and sums the projectors in another order, so points differ by rounding amplified by
the conditioning of Σ A_k (~1/parallax², ≤ 1e4 for the 1° gate): RTOL = 1e-8 relative, observed
≤ 1e-12.  The gate verdicts (reason codes) must be identical; the inputs stay away from the gate
thresholds except where a test puts them exactly on one side.
"""

import numpy as np
import pytest

from companion.core import jit, triangulation
from companion.core.frames import so3_exp
from companion.core.triangulation import Reject, TriangulationConfig, triangulate_multiview

RTOL = 1e-8
CFG = TriangulationConfig()


@pytest.fixture
def path(monkeypatch):
    return lambda kernels: monkeypatch.setattr(jit, "ENABLED", kernels)


def tracks(n=60, k=8, seed=0, sigma=0.002):
    """Rays, centres and masks of n tracks over k views of a forward flight (gaps, short tracks,
    far points, points behind, a NaN view, parallel rays): a mix of every gate verdict."""
    g = np.random.default_rng(seed)
    C = np.stack([np.linspace(0, 2, k), np.linspace(0, 0.3, k), np.linspace(0, 6, k)], 1)
    R = so3_exp(g.normal(scale=0.02, size=(k, 3)))
    p = np.stack([g.uniform(-20, 20, n), g.uniform(-8, 8, n), g.uniform(5, 300, n)], 1)
    p[:4, 2] = -20.0  # behind the cameras
    p[4:8] *= 30  # beyond max_range or low parallax
    cam = np.einsum("kji,nkj->nki", R, p[:, None] - C[None])  # camera-frame points
    xy = cam[..., :2] / cam[..., 2:] + g.normal(scale=sigma, size=(n, k, 2))
    rays = np.einsum("kij,nkj->nki", R, np.concatenate([xy, np.ones((n, k, 1))], 2))
    mask = g.uniform(size=(n, k)) < 0.8
    mask[8:12, 1:] = False  # one view only
    mask[12:14] = False  # no view
    rays[14, 2] = np.nan  # a NaN ray in a used view
    mask[14, 2] = True
    rays[15, 3] = np.nan  # a NaN ray in an unused view: ignored
    mask[15, 3] = False
    rays[16] = rays[16, 0]  # parallel rays
    rays[17, :] = 0.0  # zero-length rays
    mask[17] = True
    return rays, np.broadcast_to(C, (n, k, 3)).copy(), mask


@pytest.mark.parametrize("sigma_xy", [0.0, 0.006])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kernel_matches_the_reference(path, seed, sigma_xy):
    rays, C, mask = tracks(seed=seed)
    out = []
    for kernels in (False, True):
        path(kernels)
        out.append(triangulate_multiview(rays, C, mask, CFG, sigma_xy=sigma_xy))
    ref, ker = out
    np.testing.assert_array_equal(ker.reason, ref.reason)
    for name in ("p", "depth", "range_sigma", "parallax_rad"):
        np.testing.assert_allclose(getattr(ker, name), getattr(ref, name), rtol=RTOL, atol=1e-12, err_msg=name)
    codes = set(ref.reason.tolist())
    assert {Reject.OK, Reject.NON_FINITE, Reject.SHORT_BASELINE, Reject.LOW_PARALLAX, Reject.BEHIND_CAMERA} <= codes
    if sigma_xy:
        assert Reject.TOO_UNCERTAIN in codes
    assert np.all(np.isfinite(ker.p)) and np.all(ker.p[ker.reason != Reject.OK] == 0)


def test_empty_and_single_track(path):
    for kernels in (False, True):
        path(kernels)
        empty = triangulate_multiview(np.zeros((0, 5, 3)), np.zeros((0, 5, 3)), np.zeros((0, 5), bool), CFG)
        assert empty.p.shape == (0, 3) and empty.reason.shape == (0,)
    rays, C, mask = tracks(n=20)
    one = []
    for kernels in (False, True):
        path(kernels)
        one.append(triangulate_multiview(rays[19:20], C[19:20], mask[19:20], CFG))
    np.testing.assert_array_equal(one[0].reason, one[1].reason)
    np.testing.assert_allclose(one[1].p, one[0].p, rtol=RTOL)


def test_the_tolerance_sees_a_small_error(path):
    """The comparison can fail: 1e-6 relative on one view's ray moves the point well beyond RTOL."""
    rays, C, mask = tracks()
    path(False)
    ref = triangulate_multiview(rays, C, mask, CFG)
    path(True)
    bumped = rays.copy()
    bumped[:, -1, 0] *= 1 + 1e-6
    ker = triangulate_multiview(bumped, C, mask, CFG)
    with pytest.raises(AssertionError):
        np.testing.assert_allclose(ker.p, ref.p, rtol=RTOL, atol=1e-12)


def test_warm_up_compiles_the_kernel():
    if not jit.ENABLED:
        pytest.skip("compiled kernels are off in this process")
    jit.warm_up()
    assert len(triangulation._multiview_kernel.signatures) >= 1
