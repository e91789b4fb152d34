"""The anchored EKF's compiled kernels (companion/core/ekf_anchored_kernels.py) against the numpy reference.

Both paths run in this process: ``jit.ENABLED`` is what the filter dispatches on at each call, so
the tests set it to False (reference) or True (kernels).  Without numba (or with
COMPANION_KERNELS=numpy) the "kernels" are the same loops run as plain Python: slower, same results.

Tolerance.  The kernels do the reference's arithmetic one landmark at a time in another order
(scalar sums instead of einsum / matmul, R_cᵀ (E W) as (R_cᵀ E) W, …), so the two differ by float
rounding only: a few ulp per operation, amplified by the conditioning of S and P over up to three
relinearizations and many updates.  Observed: ≤ 2e-10 relative over the 180 frames of the
benchmark flight, ≤ 1e-12 in the tests here.  ``RTOL`` = 1e-8 leaves that margin and stays far
below a real difference (one relinearization more or less moves the state by ~1e-4 relative:
:func:`test_the_tolerance_sees_one_relinearization`).  Discrete outcomes (accepted, reason,
counts, the diverged flag) must be identical.
"""

import numpy as np
import pytest

from companion.core import ekf_anchored_kernels, jit
from companion.core.ekf_anchored import (
    BEHIND, GATED, LOOM_NAN, LOOM_NONPOSITIVE, UPDATED, AnchoredEKFConfig, AnchoredInverseDepthEKF,
)
from companion.core.frames import so3_exp
from companion.errors import InputError

RTOL = 1e-8
STATE_FIELDS = ("x", "P")
COUNT_FIELDS = ("n_updates", "n_rejects", "diverged", "nis_count", "n_looming")

#: the shipped [ekf_anchored] table's model (3 iterations, drift states, position noise, NIS retirement)
SHIPPED = dict(iterations=3, attitude_drift_deg_s=0.03, position_sigma_m=0.1, max_mean_nis=4.0)
#: the filter without the optional models the shipped table turns on (3 inverse-depth states, no position
#: noise, no NIS retirement): flight_bank's base, so each case below adds just what it exercises
BARE = dict(attitude_drift_deg_s=0.0, position_sigma_m=0.0, max_mean_nis=0.0)


@pytest.fixture
def path(monkeypatch):
    """``path(kernels)`` switches the filter to the compiled kernels (True) or the numpy reference (False)."""
    return lambda kernels: monkeypatch.setattr(jit, "ENABLED", kernels)


def flight_bank(n=30, seed=0, frames=12, **cfg):
    """A bank of ``n`` landmarks at 8–60 m, anchored at frame 0 of a forward flight with sway and
    rotation, and the (noisy, a few outliers) pixels of the later frames: (bank, ids, xy (K,n,2), R, C, t)."""
    g = np.random.default_rng(seed)
    f = 400.0
    bank = AnchoredInverseDepthEKF(AnchoredEKFConfig(**{**BARE, **cfg}), f, f)
    ids = np.arange(100, 100 + n)
    p = np.stack([g.uniform(-8, 8, n), g.uniform(-4, 4, n), g.uniform(8, 60, n)], 1)
    k = np.arange(frames)
    t = 0.05 * k
    C = np.stack([0.3 * np.sin(t), 0.1 * np.cos(2 * t), 1.5 * k * 0.05 * 6], 1)
    R = so3_exp(np.stack([0.02 * np.sin(3 * t), 0.03 * np.sin(2 * t), 0.01 * k], 1))
    pc = np.einsum("kji,knj->kni", R, p[None] - C[:, None])
    xy = pc[..., :2] / pc[..., 2:] + g.normal(scale=1.0 / f, size=(frames, n, 2))
    xy[g.integers(1, frames, 4), g.integers(0, n, 4)] += 0.2  # a few outliers for the gate
    bank.add(ids, xy[0], R[0], C[0], t[0], g.uniform(0.005, 0.05, n), 0.03)
    return bank, ids, xy, R, C, t


def same_banks(a, b, rtol=RTOL):
    for name in STATE_FIELDS + ("nis_avg", "nis_C"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=rtol, atol=1e-300, err_msg=name)
    for name in COUNT_FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def same_results(ra, rb):
    np.testing.assert_array_equal(ra.accepted, rb.accepted)
    np.testing.assert_array_equal(ra.reason, rb.reason)
    np.testing.assert_allclose(ra.nis, rb.nis, rtol=RTOL)


@pytest.mark.parametrize("cfg", [SHIPPED, dict(iterations=1), dict(iterations=2, attitude_sigma_deg=0.05),
                                 dict(iterations=3, attitude_drift_deg_s=0.3, max_mean_nis=2.0, max_consecutive_rejects=2),
                                 dict(SHIPPED, max_mean_nis=2.0, nis_min_baseline_deg=1.0)])
def test_frame_updates_match_the_reference(path, cfg):
    """update() and update_banks() frame by frame (shared pose, subsets of landmarks): states,
    covariances, NIS, reasons and the bookkeeping agree; some updates are gated, some accepted."""
    runs = []
    for kernels in (False, True):
        path(kernels)
        bank, ids, xy, R, C, t = flight_bank(**cfg)
        other, *_ = flight_bank(seed=1, **cfg)
        results = []
        for k in range(1, len(t)):
            sel = ids[(np.arange(len(ids)) + k) % 5 != 0]  # a few landmarks miss each frame
            results.append(bank.update(sel, xy[k, sel - 100], R[k], C[k], t[k]))
            results += AnchoredInverseDepthEKF.update_banks([(other, sel[::2], xy[k, sel[::2] - 100])], R[k], C[k], t[k])
        runs.append((bank, other, results))
    (ref, ref_o, ref_r), (ker, ker_o, ker_r) = runs
    same_banks(ref, ker)
    same_banks(ref_o, ker_o)
    for a, b in zip(ref_r, ker_r):
        same_results(a, b)
    reasons = np.concatenate([r.reason for r in ref_r])
    assert np.any(reasons == GATED) and np.mean(reasons == UPDATED) > 0.5  # both branches exercised


@pytest.mark.parametrize("cfg", [SHIPPED, dict(SHIPPED, nis_min_baseline_deg=1.0)])
def test_per_landmark_poses_and_sequences_match_the_reference(path, cfg):
    """update() with a pose per landmark, and update_sequence() replaying buffers of different lengths."""
    out = []
    for kernels in (False, True):
        path(kernels)
        bank, ids, xy, R, C, t = flight_bank(**cfg)
        k = np.arange(len(ids)) % (len(t) - 1) + 1  # each landmark seen from another frame
        r1 = bank.update(ids, xy[k, np.arange(len(ids))], R[k], C[k], t[k])
        seq, *_ = flight_bank(**cfg)
        count = np.arange(len(ids)) % len(t)
        acc = seq.update_sequence(ids, np.swapaxes(xy[1:], 0, 1), np.broadcast_to(R[1:], (len(ids),) + R[1:].shape),
                                  np.broadcast_to(C[1:], (len(ids),) + C[1:].shape),
                                  np.broadcast_to(t[1:], (len(ids), len(t) - 1)), count)
        out.append((bank, r1, seq, acc))
    (b0, r0, s0, a0), (b1, r1, s1, a1) = out
    same_banks(b0, b1)
    same_results(r0, r1)
    same_banks(s0, s1)
    np.testing.assert_array_equal(a0, a1)
    assert a0.max() > 5 and a0.min() == 0


def test_the_tolerance_sees_one_relinearization(path):
    """The comparison can fail: 2 instead of 3 relinearizations is far outside RTOL."""
    banks = []
    for kernels, iterations in ((False, 3), (True, 2)):
        path(kernels)
        bank, ids, xy, R, C, t = flight_bank(**dict(SHIPPED, iterations=iterations))
        for k in range(1, 4):
            bank.update(ids, xy[k], R[k], C[k], t[k])
        banks.append(bank)
    with pytest.raises(AssertionError):
        same_banks(*banks)


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning", "ignore:invalid value:RuntimeWarning")
def test_edge_cases_match_the_reference(path):
    """Empty updates, one landmark, a point behind the camera, an outlier, an overflowing covariance
    and an iterate that crosses behind the camera: the same verdicts and untouched states both ways."""
    def scenario():
        cfg = AnchoredEKFConfig(iterations=3, **BARE)  # the 3-state filter: P[3] below is 3×3
        bank = AnchoredInverseDepthEKF(cfg, 400.0, 400.0)
        bank.add([1, 2, 3, 4], [[0.1, 0.0], [0.0, 0.05], [0.11806848, -0.25301274], [0.0, 0.0]], np.eye(3), np.zeros(3),
                 0.0, [0.05, 0.05, 0.16981100, 0.05], [0.02, 0.02, 0.22739021, 0.02])
        bank.P[3] = np.diag([1e308, 1e308, 1e308])  # P Hᵀ overflows: S⁻¹ = 0 passes the gate, K is NaN → GATED, unchanged
        empty = bank.update([], np.zeros((0, 2)), np.eye(3), np.zeros(3), 1.0)
        banks_empty = AnchoredInverseDepthEKF.update_banks([(bank, [], np.zeros((0, 2)))], np.eye(3), np.zeros(3), 1.0)
        one = bank.update([1], [[0.1, 0.001]], np.eye(3), [0.0, 0.0, 1.0], 1.0)
        behind = bank.update([2], [[0.0, 0.05]], np.eye(3), [0.0, 0.0, 100.0], 2.0)  # camera far past the point
        crossing = bank.update([3], [[0.88787208, -0.44188047]], np.eye(3), [-0.06725524, -0.83540167, 3.78495355], 2.0)
        outlier = bank.update([1], [[0.4, 0.3]], np.eye(3), [0.0, 0.0, 1.5], 3.0)
        overflow = bank.update([4], [[0.01, 0.0]], np.eye(3), [0.5, 0.0, 1.0], 3.0)
        return bank, empty, banks_empty[0], one, behind, crossing, outlier, overflow

    path(False)
    ref = scenario()
    path(True)
    ker = scenario()
    same_banks(ref[0], ker[0])
    for a, b in zip(ref[1:], ker[1:]):
        same_results(a, b)
    _, empty, banks_empty, one, behind, crossing, outlier, overflow = ker
    assert len(empty.accepted) == 0 and len(banks_empty.accepted) == 0
    assert one.accepted[0]
    assert behind.reason[0] == BEHIND and np.isinf(behind.nis[0])
    assert crossing.reason[0] == UPDATED and not crossing.accepted[0]  # dropped by the behind test of an iterate
    assert outlier.reason[0] == GATED
    assert overflow.reason[0] == GATED and not overflow.accepted[0] and overflow.nis[0] == 0.0
    assert np.all(np.isfinite(ker[0].x)) and ker[0].P[3, 0, 0] == 1e308


@pytest.mark.parametrize("iterations", [1, 2])
def test_looming_matches_the_reference(path, iterations):
    """update_looming_banks over two banks: NaN and non-positive scales, gated and accepted ones."""
    out = []
    for kernels in (False, True):
        path(kernels)
        cfg = dict(SHIPPED, looming_iterations=iterations)
        a, ids, xy, R, C, t = flight_bank(**cfg)
        b, *_ = flight_bank(seed=4, **cfg)
        g = np.random.default_rng(5)
        results = []
        for k in range(1, len(t)):
            s = 1.0 + 0.03 * (C[k, 2] - C[k - 1, 2]) * g.uniform(0.5, 1.5, len(ids))
            s[k % len(ids)] = np.nan
            s[(k + 3) % len(ids)] = -1.0
            s[(k + 7) % len(ids)] = 1.5  # gated
            sig = np.full(len(ids), 0.004)
            sig[(k + 9) % len(ids)] = np.inf
            results += AnchoredInverseDepthEKF.update_looming_banks(
                [(a, ids, s, sig), (b, ids[::3], s[::3], None)], R[k - 1], C[k - 1], t[k - 1], R[k], C[k], t[k])
        out.append((a, b, results))
    (a0, b0, r0), (a1, b1, r1) = out
    same_banks(a0, a1)
    same_banks(b0, b1)
    for x, y in zip(r0, r1):
        np.testing.assert_array_equal(x.accepted, y.accepted)
        np.testing.assert_array_equal(x.reason, y.reason)
        np.testing.assert_allclose(x.nis, y.nis, rtol=RTOL)  # NaN where not measured, both ways
    reasons = np.concatenate([r.reason for r in r0])
    for code in (UPDATED, GATED, LOOM_NAN, LOOM_NONPOSITIVE):
        assert np.any(reasons == code), code


def test_estimates_match_the_reference(path):
    """Ranges, σ, points and the valid / converged flags, including ρ ≤ 0, a diverged landmark and
    a landmark whose range is capped."""
    bank, ids, xy, R, C, t = flight_bank(**SHIPPED)
    for k in range(1, len(t)):
        bank.update(ids, xy[k], R[k], C[k], t[k])
    bank.x[0, 2] = -0.5  # significantly negative: invalid
    bank.x[1, 2] = 0.0  # at infinity: range capped at max_range_m
    bank.x[2, 2] = 1e-6
    bank.diverged[3] = True
    path(False)
    ref = bank.estimates(C[-1])
    path(True)
    ker = bank.estimates(C[-1])
    for name in ("p_world", "range", "range_sigma", "inv_depth", "inv_depth_sigma"):
        np.testing.assert_allclose(getattr(ker, name), getattr(ref, name), rtol=RTOL, err_msg=name)
    np.testing.assert_array_equal(ker.valid, ref.valid)
    np.testing.assert_array_equal(ker.converged, ref.converged)
    np.testing.assert_array_equal(ker.ids, ref.ids)
    assert not ref.valid[0] and not ref.valid[3] and ref.range[1] > 0.99 * bank.config.max_range_m
    assert ref.converged.any() and not ref.converged.all()
    empty = AnchoredInverseDepthEKF(AnchoredEKFConfig(), 400.0, 400.0).estimates(np.zeros(3))
    assert len(empty.range) == 0


@pytest.mark.parametrize("kernels", [False, True])
def test_an_id_twice_in_one_update_is_refused(path, kernels):
    """One observation per landmark and call (the kernels update rows in place, one after the other)."""
    path(kernels)
    bank, ids, xy, R, C, t = flight_bank(n=4)
    with pytest.raises(InputError, match="more than once"):
        bank.update([100, 101, 100], xy[1, [0, 1, 0]], R[1], C[1], t[1])
    with pytest.raises(InputError, match="more than once"):
        AnchoredInverseDepthEKF.update_banks([(bank, [102, 102], xy[1, [2, 2]])], R[1], C[1], t[1])
    with pytest.raises(InputError, match="more than once"):
        bank.update_looming([101, 101], [1.0, 1.0], None, R[0], C[0], t[0], R[1], C[1], t[1])


def test_warm_up_compiles_every_kernel():
    """The registered warm-up compiles the kernels for the layouts the filter passes (no compile on the first frame)."""
    if not jit.ENABLED:
        pytest.skip("compiled kernels are off in this process")
    assert jit.warm_up() >= 1
    for fn in (ekf_anchored_kernels.update_pixel_rows, ekf_anchored_kernels.update_pixel_sequences,
               ekf_anchored_kernels.update_looming_rows, ekf_anchored_kernels.estimates):
        assert len(fn.signatures) >= 1, fn  # (one signature serves n = 3 and n = 6)
    bank, ids, xy, R, C, t = flight_bank(**SHIPPED)
    n_sig = len(ekf_anchored_kernels.update_pixel_rows.signatures)
    bank.update(ids, xy[1], R[1], C[1], t[1])
    bank.estimates(C[1])
    assert len(ekf_anchored_kernels.update_pixel_rows.signatures) == n_sig  # no new compilation
