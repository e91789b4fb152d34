"""Normalized cross-correlation matching in a predicted window (seed 004 eq. 13–14).

For a template f around a point of the previous frame and a candidate patch g of the current
frame (eq. 13)

    k(f, g) = Σ (f − f̄)(g − ḡ) / sqrt( Σ (f − f̄)² · Σ (g − ḡ)² ),

evaluated for every candidate in a search window of the current frame; the match is the argmax
(eq. 14) and is accepted only if k ≥ k_min.  ``cv2.matchTemplate(..., cv2.TM_CCOEFF_NORMED)``
computes exactly this quantity.  As seed 004 notes, the known camera motion shrinks the search
area: the window is centred on the *predicted* pixel (``pts_pred``, from telemetry, see
:mod:`companion.core.prediction`) and its half-size is the prediction's uncertainty radius.

Every point gets a verdict (``reason``), tested in this order:

* ``OUT_OF_IMAGE`` — the template (with its 1-px rim) does not fit in the previous frame, the
  search window does not fit in the current one, or the best match sits on a side of the window
  cut by the image border (the point is leaving the image);
* ``FLAT_TEMPLATE`` — template standard deviation below ``min_template_std`` grey levels (NCC is
  undefined on a flat patch);
* ``EDGE_TEMPLATE`` — the template is an edge, not a corner: the smaller eigenvalue of its
  structure tensor M = Σ ∇I ∇Iᵀ (central differences over the template, using its 1-px rim) is
  below ``min_eigen_ratio`` × the larger.  Along an edge the NCC peak is a ridge, so the match
  slides wherever noise and the predicted window put it (the aperture problem); a track that has
  drifted from a corner onto an edge (e.g. the foreshortened, streaky ground near the horizon)
  would feed the filter a steady false parallax and a confident range far too near;
* ``LOW_SCORE`` — best score below ``k_min``;
* ``AMBIGUOUS`` — another local maximum at least ``ambiguity_min_separation`` px away scores at
  least best − ``ambiguity_margin`` (repeated texture);
* ``PEAK_AT_EDGE`` — the best score lies on the edge of the search window (inside the image), so
  the true peak may lie outside it and the argmax is not a verified maximum;
* ``OK`` — accepted.

Sub-pixel accuracy: the template is cut at the integer pixel nearest to the sub-pixel point and
the point's fractional offset is carried over to the match (exact for a locally translating
patch).  The integer NCC peak is then refined by Lucas–Kanade on the two frames
(``cv2.calcOpticalFlowPyrLK``, one level, started at the peak; ``subpixel_method = "lk"``, the
default) or by a 1-D parabola through the peak and its neighbours on each axis (``"parabola"``,
also the fallback where Lucas–Kanade does not converge within 1 px).  The parabola is biased by
up to ~0.15 px even for a whole-pixel shift (the NCC peak of a finite window is not symmetric),
and since each frame's match becomes the next frame's template, that bias would accumulate
along a track; Lucas–Kanade is exact for whole-pixel shifts and within a few hundredths of a
pixel otherwise.

Scale change (looming, docs/derivations/looming.md).  For each accepted match of two frames,
:func:`estimate_scale` (:mod:`companion.core.ncc_scale`, which states the fit) measures the patch's
scale change s = size now / size before and its σ by a Gauss–Newton fit of a scale + translation
warp.  At most ``max_scale_points`` fits per call (cost bound), the matches with
the least parallax first: by default the image motion nearest the median motion; with
``scale_order = "parallax"`` the smallest ``scale_key`` (the bearing parallax per unit inverse
depth the tracker's predictor computes, which vanishes at the focus of expansion, where looming
is needed).  The
scale is NaN where it cannot be measured: rejected match, window not inside both frames, flat or
edge patch (singular normal matrix), no convergence, |s − 1| > ``max_scale_change`` or
σ_s > ``max_scale_sigma``.  Templates that follow scale: :func:`match_ncc` resamples the template
at a predicted scale (``scale_pred``, e.g. the track's last measured scale) when it departs from 1
by more than ``rescale_threshold``, so NCC still correlates when a patch grows fast (close in).

Cost: windows up to ``batch_search_half`` px are scored for all points at once in numpy
(:func:`_ncc_batch`, ~2× cheaper than one OpenCV call per point at these sizes); larger windows
take one ``cv2.matchTemplate`` per point (the only per-point Python loop).  Everything else —
template extraction, argmax, second-peak test, sub-pixel step — is vectorized over points.

Layout: this module holds the matcher (:func:`match_ncc`, :func:`match_templates`: windows, scores,
verdicts); template extraction and the edge test are in :mod:`companion.core.ncc_templates`, the
Lucas–Kanade sub-pixel step in :mod:`companion.core.ncc_subpixel`, the scale fit in
:mod:`companion.core.ncc_scale` (public names importable from here) and the compiled kernels in
:mod:`companion.core.ncc_kernels`.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from companion.config import require, require_finite
from companion.core import jit
from companion.core import ncc_kernels as _kernels
from companion.core.harris import as_gray_u8
# template extraction and the scale fit, re-exported: every public name stays importable from here
from companion.core.ncc_scale import estimate_scale
from companion.core.ncc_subpixel import _lk_refine, _lk_refine_frames
from companion.core.ncc_templates import _check_pts, extract_scaled_templates, extract_templates, template_eigen_ratio
from companion.errors import InputError

#: Verdicts in :attr:`NCCResult.reason` (int8).
OK = 0
OUT_OF_IMAGE = 1
FLAT_TEMPLATE = 2
LOW_SCORE = 3
AMBIGUOUS = 4
PEAK_AT_EDGE = 5
EDGE_TEMPLATE = 6

REASON_NAMES = {
    OK: "ok",
    OUT_OF_IMAGE: "out_of_image",
    FLAT_TEMPLATE: "flat_template",
    LOW_SCORE: "low_score",
    AMBIGUOUS: "ambiguous",
    PEAK_AT_EDGE: "peak_at_edge",
    EDGE_TEMPLATE: "edge_template",
}

_EMPTY = np.float32(-2.0)  # score of cells outside a point's search window (NCC is in [-1, 1])
_MIN_BATCH = 8  # fewer small-window points than this go through cv2.matchTemplate one by one


@dataclasses.dataclass(frozen=True)
class NCCConfig:
    """The ``[ncc]`` table: template and search sizes, acceptance and ambiguity thresholds."""

    template_half: int = 5  # template is (2h+1)² = 11×11 px
    search_half: int = 8  # default search half-size (px) when no radius is given
    max_search_half: int = 32  # cap on any requested search radius (px)
    batch_search_half: int = 5  # windows up to this radius are scored in one numpy batch (speed only)
    k_min: float = 0.8  # acceptance threshold on the NCC score (eq. 14)
    ambiguity_margin: float = 0.03  # second peak >= best - margin ...
    ambiguity_min_separation: float = 3.0  # ... and at least this far (px) from the best: ambiguous
    subpixel: bool = True  # refine the integer peak to sub-pixel
    subpixel_method: str = "lk"  # "lk" (Lucas–Kanade on the patch) or "parabola" (through the NCC peak)
    lk_iterations: int = 3  # Lucas–Kanade iterations of the sub-pixel step
    min_template_std: float = 3.0  # grey levels; flatter templates are refused
    min_eigen_ratio: float = 0.08  # structure-tensor λmin/λmax below this: an edge, refused (0 = off)
    scale_estimation: bool = True  # estimate each match's scale change (looming) between the two frames
    scale_half: int = 7  # the scale is fitted over (2h+1)² = 15×15 px
    scale_iterations: int = 2  # Gauss–Newton iterations of the scale fit (started from the track's last scale)
    max_scale_points: int = 40  # scale fits per call (cost bound): those with the least parallax first
    scale_order: str = "median_flow"  # which fits first: "median_flow" (image motion nearest the median) or "parallax" (least bearing parallax, given as scale_key)
    scale_sigma_slope: float = 0.06  # σ added in quadrature per unit |s − 1| (resampling / model error)
    max_scale_change: float = 0.3  # |s − 1| beyond this: scale reported NaN
    max_scale_sigma: float = 0.05  # scale σ beyond this: scale reported NaN
    scale_sigma_factor: float = 1.5  # inflation of the Gauss–Newton σ for correlated pixel errors

    def __post_init__(self) -> None:
        for name in ("template_half", "search_half", "max_search_half"):
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and v >= 1, f"{name} must be an integer >= 1, got {v!r}")
        require(self.max_search_half >= self.search_half, "max_search_half must be >= search_half")
        require(
            isinstance(self.batch_search_half, int) and not isinstance(self.batch_search_half, bool) and self.batch_search_half >= 0,
            f"batch_search_half must be an integer >= 0 (0 = always cv2.matchTemplate), got {self.batch_search_half!r}",
        )
        require_finite("k_min", self.k_min)
        require(-1.0 <= self.k_min <= 1.0, f"k_min must lie in [-1, 1], got {self.k_min}")
        require_finite("ambiguity_margin", self.ambiguity_margin, nonnegative=True)
        require_finite("ambiguity_min_separation", self.ambiguity_min_separation, positive=True)
        require(isinstance(self.subpixel, bool), f"subpixel must be true or false, got {self.subpixel!r}")
        require(
            self.subpixel_method in ("lk", "parabola"),
            f"subpixel_method must be 'lk' or 'parabola', got {self.subpixel_method!r}",
        )
        require(
            isinstance(self.lk_iterations, int) and not isinstance(self.lk_iterations, bool) and self.lk_iterations >= 1,
            f"lk_iterations must be an integer >= 1, got {self.lk_iterations!r}",
        )
        require_finite("min_template_std", self.min_template_std, nonnegative=True)
        require_finite("min_eigen_ratio", self.min_eigen_ratio, nonnegative=True)
        require(self.min_eigen_ratio < 1.0, f"min_eigen_ratio must be < 1, got {self.min_eigen_ratio}")
        require(isinstance(self.scale_estimation, bool), f"scale_estimation must be true or false, got {self.scale_estimation!r}")
        for name in ("scale_half", "scale_iterations"):
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and v >= 1, f"{name} must be an integer >= 1, got {v!r}")
        require(self.scale_half >= 2, f"scale_half must be >= 2, got {self.scale_half}")
        require(isinstance(self.max_scale_points, int) and not isinstance(self.max_scale_points, bool) and self.max_scale_points >= 0,
                f"max_scale_points must be an integer >= 0, got {self.max_scale_points!r}")
        require(self.scale_order in ("median_flow", "parallax"),
                f"scale_order must be 'median_flow' or 'parallax', got {self.scale_order!r}")
        require_finite("scale_sigma_slope", self.scale_sigma_slope, nonnegative=True)
        require_finite("max_scale_change", self.max_scale_change, positive=True)
        require(self.max_scale_change < 1.0, f"max_scale_change must be < 1, got {self.max_scale_change}")
        require_finite("max_scale_sigma", self.max_scale_sigma, positive=True)
        require_finite("scale_sigma_factor", self.scale_sigma_factor, positive=True)


@dataclasses.dataclass
class NCCResult:
    """Per point: matched pixel (u, v), best NCC score, accepted flag and verdict code.

    Rejected points keep finite values: ``pts`` is the search centre and ``score`` the best score
    found (0 where nothing was searched).
    """

    pts: np.ndarray  # (N, 2) float64
    score: np.ndarray  # (N,) float64
    ok: np.ndarray  # (N,) bool
    reason: np.ndarray  # (N,) int8, one of the module constants
    scale: np.ndarray | None = None  # (N,) image size now / before (looming), NaN where not measured
    scale_sigma: np.ndarray | None = None  # (N,) its σ, NaN where not measured

    def __post_init__(self) -> None:
        n = len(self.score)
        if self.scale is None:
            self.scale = np.full(n, np.nan)
        if self.scale_sigma is None:
            self.scale_sigma = np.full(n, np.nan)


def _search_half(config: NCCConfig, search_radius, n: int) -> np.ndarray:
    if search_radius is None:
        return np.full(n, config.search_half, np.int64)
    r = np.asarray(search_radius, dtype=float)
    if r.ndim == 0:
        r = np.full(n, float(r))
    if r.shape != (n,):
        raise InputError(f"search_radius must be a scalar or have shape ({n},), got {r.shape}")
    if not np.all(np.isfinite(r)) or np.any(r < 0):
        raise InputError("search_radius must be finite and >= 0")
    return np.clip(np.ceil(r - 1e-9), 1, config.max_search_half).astype(np.int64)


def _ncc_batch(img: np.ndarray, tpl: np.ndarray, centres: np.ndarray, sb: int, h: int) -> np.ndarray:
    """Eq. 13 for B templates (B, T, T) over (2·sb+1)² positions around integer ``centres`` at once.

    With f̂ the zero-mean, unit-norm template, k = Σ f̂·g / sqrt(Σ (g − ḡ)²) (Σ f̂ = 0 removes ḡ
    from the numerator).  Numerator: for each column offset j the windows' columns j … j+T−1
    are copied once, after which every row offset is a contiguous T² block of that copy, so one
    einsum per column offset scores all rows and all points.  Window sums Σ g, Σ g² come from
    ``cv2.integral2`` of the windows laid side by side (valid positions never straddle two
    windows; integer sums, exact).  Same values as
    ``cv2.matchTemplate(..., TM_CCOEFF_NORMED)`` to ~1e-4.  Windows must lie inside the image.
    Returns (B, 2·sb+1, 2·sb+1) float32, 0 where the window is flat.
    """
    t = 2 * h + 1
    size = t + 2 * sb
    rb = 2 * sb + 1
    nb = len(centres)
    win = np.lib.stride_tricks.sliding_window_view(img, (size, size))[centres[:, 1] - sb - h, centres[:, 0] - sb - h]
    f = tpl.reshape(nb, t * t).astype(np.float32)
    f = f - f.mean(axis=1, keepdims=True)
    f = f / np.sqrt(np.einsum("nk,nk->n", f, f))[:, None]
    num = np.empty((nb, rb, rb), np.float32)
    item = np.dtype(np.float32).itemsize
    cols = np.empty((nb, size, t), np.float32)  # reused for every column offset
    blocks = np.ndarray((nb, rb, t * t), np.float32, cols, 0, (size * t * item, t * item, item))  # view of cols
    for j in range(rb):
        np.copyto(cols, win[:, :, j : j + t])  # (B, size, t), uint8 → float32 (exact)
        num[:, :, j] = np.einsum("nik,nk->ni", blocks, f)
    # Σ g and Σ g² over every valid position from integral images of the windows laid side by side
    # (integers: the same values a box filter gives)
    wide = np.ascontiguousarray(win.transpose(1, 0, 2)).reshape(size, nb * size)
    I1, I2 = cv2.integral2(wide, sdepth=cv2.CV_32S, sqdepth=cv2.CV_64F)  # (size+1, nb·size+1)

    def valid(ii: np.ndarray) -> np.ndarray:
        lo = ii[:, : nb * size].reshape(size + 1, nb, size)[:, :, :rb]  # column n·size + j
        hi = ii[:, 1:].reshape(size + 1, nb, size)[:, :, t - 1 : t - 1 + rb]  # column n·size + j + t
        box = hi[t : t + rb] - lo[t : t + rb] - hi[:rb] + lo[:rb]  # rows i … i + t − 1
        return box.transpose(1, 0, 2).astype(np.float64)

    m1 = valid(I1)
    var = valid(I2) - m1 * m1 / (t * t)
    den = np.sqrt(np.maximum(var, 0.0))
    ok = den > 1e-3
    return np.where(ok, num / np.where(ok, den, 1.0), 0.0).astype(np.float32)


def match_templates(
    templates: np.ndarray,
    frac: np.ndarray,
    img_cur: np.ndarray,
    pts_pred: np.ndarray,
    config: NCCConfig,
    search_radius=None,
    valid: np.ndarray | None = None,
    img_prev: np.ndarray | None = None,
    pts_prev: np.ndarray | None = None,
) -> NCCResult:
    """Match templates cut by :func:`extract_templates` in ``img_cur`` around ``pts_pred``.

    ``templates`` (N, T+2, T+2) uint8 with T = 2·template_half + 1, ``frac`` (N, 2) their
    sub-pixel offsets, ``valid`` (N,) which templates exist (False gives ``OUT_OF_IMAGE``).
    If the frame the templates were cut from and the exact points are given (``img_prev``,
    ``pts_prev``), the sub-pixel step runs ``cv2.calcOpticalFlowPyrLK`` on the two frames;
    otherwise a vectorized Lucas–Kanade step on the stored templates.  This is the core of
    :func:`match_ncc`; the track manager calls it directly for tracks that missed a frame,
    with the templates it kept from their last observation.
    """
    img_cur = as_gray_u8(img_cur, "img_cur")
    templates = np.asarray(templates)
    h = config.template_half
    tr = 2 * h + 3
    if templates.ndim != 3 or templates.shape[1:] != (tr, tr) or templates.dtype != np.uint8:
        raise InputError(
            f"templates must be uint8 of shape (N, {tr}, {tr}) for template_half={h} "
            f"(matched patch plus a 1-px rim), got {templates.dtype} {templates.shape}"
        )
    n = len(templates)
    templates = np.ascontiguousarray(templates)
    frac = _check_pts("frac", frac, n)
    pred = _check_pts("pts_pred", pts_pred, n)
    s = _search_half(config, search_radius, n)
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool).reshape(n)
    if (img_prev is None) != (pts_prev is None):
        raise InputError("img_prev and pts_prev must be given together")
    if img_prev is not None:
        img_prev = as_gray_u8(img_prev, "img_prev")
        if img_prev.shape != img_cur.shape:
            raise InputError(f"img_prev and img_cur differ in shape: {img_prev.shape} vs {img_cur.shape}")
        pts_prev = _check_pts("pts_prev", pts_prev, n)

    reason = np.zeros(n, np.int8)
    score = np.zeros(n)
    out_pts = pred.copy()
    if n == 0:
        return NCCResult(out_pts, score, np.zeros(0, bool), reason)
    reason[~valid] = OUT_OF_IMAGE

    if jit.ENABLED:
        var, eig_ratio = _kernels.template_stats(templates)
    else:
        inner = templates[:, 1:-1, 1:-1].reshape(n, -1).astype(np.float32)
        mean = inner.mean(axis=1)
        var = np.einsum("ni,ni->n", inner, inner) / inner.shape[1] - mean * mean
        eig_ratio = template_eigen_ratio(templates) if config.min_eigen_ratio > 0 else None
    reason[(reason == OK) & (var < max(config.min_template_std, 1e-3) ** 2)] = FLAT_TEMPLATE
    if config.min_eigen_ratio > 0:
        reason[(reason == OK) & (eig_ratio < config.min_eigen_ratio)] = EDGE_TEMPLATE

    # Search window of each point: template centres in [c - s, c + s], clipped to the image.
    H, W = img_cur.shape
    big = 4 * max(H, W)  # a prediction this far out is simply out of the image
    c = np.rint(np.clip(pred, -big, big)).astype(np.int64)
    lo = np.maximum(c - s[:, None], h)
    hi = np.minimum(c + s[:, None], np.array([W - 1 - h, H - 1 - h]))
    reason[(reason == OK) & np.any(lo > hi, 1)] = OUT_OF_IMAGE
    run = np.flatnonzero(reason == OK)
    nr = len(run)
    if nr == 0:
        return NCCResult(out_pts, score, np.zeros(n, bool), reason)

    if jit.ENABLED:
        found, r, best, nbrs = _score_kernel(run, templates, img_cur, c, s, lo, hi, config)
    else:
        found, r, best, nbrs = _score_reference(run, templates, img_cur, c, s, lo, hi, h, config)
    reason[run] = r
    score[run] = best
    left, right, up, down = nbrs
    good = r == OK
    peak = found  # integer template centres of the best scores
    found = peak + frac[run]
    if config.subpixel and np.any(good):
        # Parabola through the peak and its neighbours: the answer for subpixel_method
        # "parabola" and the fallback where Lucas–Kanade fails.
        par = np.zeros((nr, 2))
        for axis, (a, b) in enumerate(((left, right), (up, down))):
            den = a - 2.0 * best + b
            sel = good & (den < -1e-12)
            par[sel, axis] = np.clip(0.5 * (a[sel] - b[sel]) / den[sel], -0.5, 0.5)
        g = np.flatnonzero(good)
        refined = found[g] + par[g]
        if config.subpixel_method == "lk":
            if img_prev is not None:
                lk, lk_ok = _lk_refine_frames(img_prev, img_cur, pts_prev[run[g]], found[g], h, config.lk_iterations)
                refined[lk_ok] = lk[lk_ok]
            else:
                refined = found[g] + _lk_refine(templates[run[g]], img_cur, peak[g].astype(np.int64), h, config.lk_iterations)
        found[g] = refined
    out_pts[run[good]] = found[good]
    return NCCResult(out_pts, score, reason == OK, reason)


def _score_kernel(run, templates, img_cur, c, s, lo, hi, config: NCCConfig):
    """The compiled form of :func:`_score_reference` (:func:`companion.core.ncc_kernels.score_peaks`):
    every window scored in one pass, the verdicts judged as in :func:`_score_group`."""
    sr, cr = s[run], c[run]
    bi, bj, b, nbrs, ambiguous = _kernels.score_peaks(
        img_cur, templates[run], cr, sr, lo[run], hi[run], float(config.ambiguity_margin), float(config.ambiguity_min_separation))
    b = np.where(np.isfinite(b), b, -1.0)
    edge_l, edge_r, edge_u, edge_d = (v <= _EMPTY + 0.5 for v in nbrs)
    x0, y0 = lo[run, 0], lo[run, 1]
    x1, y1 = hi[run, 0], hi[run, 1]
    cx, cy = cr[:, 0], cr[:, 1]
    leaving = (edge_l & (x0 > cx - sr)) | (edge_r & (x1 < cx + sr)) | (edge_u & (y0 > cy - sr)) | (edge_d & (y1 < cy + sr))
    v = np.zeros(len(run), np.int8)
    v[leaving] = OUT_OF_IMAGE
    v[(v == OK) & (b < config.k_min)] = LOW_SCORE
    v[(v == OK) & ambiguous] = AMBIGUOUS
    v[(v == OK) & (edge_l | edge_r | edge_u | edge_d)] = PEAK_AT_EDGE
    found = np.stack([cr[:, 0] - sr + bj, cr[:, 1] - sr + bi], 1).astype(np.float64)
    return found, v, b, nbrs


def _score_reference(run, templates, img_cur, c, s, lo, hi, h, config: NCCConfig):
    """Score the windows of points ``run`` and judge each best cell (numpy and OpenCV: the reference).

    Returns ``found`` (integer template centre of the best score), the verdicts, the best scores and
    the four neighbours' scores (left, right, up, down; the sentinel where not searched).
    """
    H, W = img_cur.shape
    nr = len(run)
    # Small windows are scored for all points at once in numpy (cheaper than one OpenCV call
    # per point below ~4 px); a batch needs its common window (its largest radius) inside the image.
    sr = s[run]
    cr = c[run]
    batch = np.zeros(nr, bool)
    sb = int(min(config.batch_search_half, sr.max()))
    if sb >= 1:
        unclipped = (hi[run, 0] - lo[run, 0] == 2 * sr) & (hi[run, 1] - lo[run, 1] == 2 * sr)
        fits = (cr[:, 0] - sb >= h) & (cr[:, 0] + sb <= W - 1 - h) & (cr[:, 1] - sb >= h) & (cr[:, 1] + sb <= H - 1 - h)
        batch = unclipped & (sr <= sb) & fits
        if np.count_nonzero(batch) < _MIN_BATCH:
            batch[:] = False
    # Each group gets a score stack sized by its own largest window (a few wide windows must not
    # make the many small ones pay for a large stack).
    found = np.zeros((nr, 2))
    r = np.zeros(nr, np.int8)
    best = np.zeros(nr)
    nbrs = np.zeros((4, nr))
    for grp in (np.flatnonzero(batch), np.flatnonzero(~batch)):
        if len(grp):
            _score_group(grp, batch[grp[0]], run, templates, img_cur, c, s, lo, hi, h, config, found, r, best, nbrs)
    return found, r, best, nbrs


def _score_group(grp, as_batch, run, templates, img_cur, c, s, lo, hi, h, config, found, r, best, nbrs) -> None:
    """Score the search windows of points ``run[grp]`` (one stack sized by the group's largest
    window), find each best cell and judge it; writes the group's rows of ``found`` (integer
    template centre of the best score), ``r`` (verdict), ``best`` (score) and ``nbrs`` (the four
    neighbours' scores: left, right, up, down; the sentinel where not searched)."""
    k_run = run[grp]
    ng = len(grp)
    sr = s[k_run]
    smax = int(sr.max())
    m = 2 * smax + 1
    # Score stack: cell (k, i, j) is the score of template centre origin_k + (j, i); cells not
    # searched hold the sentinel, and the extra row m of every block is all sentinel.
    stack = np.full((ng, m + 1, m), _EMPTY, np.float32)
    origin = c[k_run] - smax
    x0, y0 = lo[k_run, 0], lo[k_run, 1]
    x1, y1 = hi[k_run, 0], hi[k_run, 1]
    if as_batch:  # every window inside the image and unclipped
        # one batch per radius, each scoring only its own (2·r+1)² cells, written at the block's
        # centre (the cells beyond a point's radius keep the sentinel): cell scores do not depend
        # on the batch they are computed in
        tpl = templates[:, 1:-1, 1:-1]
        for rad in np.unique(sr).tolist():
            sel = np.flatnonzero(sr == rad)
            a, b = smax - rad, smax + rad + 1
            stack[sel, a:b, a:b] = _ncc_batch(img_cur, tpl[k_run[sel]], c[k_run[sel]], rad, h)
    else:
        ox, oy = x0 - origin[:, 0], y0 - origin[:, 1]
        whole = (x1 - x0 == 2 * sr) & (y1 - y0 == 2 * sr) & (sr == smax)  # fills the block: written in place
        tm = cv2.matchTemplate
        method = cv2.TM_CCOEFF_NORMED
        tpl = templates[:, 1:-1, 1:-1]
        for k, i, ya, yb, xa, xb, inplace in zip(
            range(ng), k_run.tolist(), (y0 - h).tolist(), (y1 + h + 1).tolist(),
            (x0 - h).tolist(), (x1 + h + 1).tolist(), whole.tolist(),
        ):
            if inplace:
                tm(img_cur[ya:yb, xa:xb], tpl[i], method, stack[k, :m])
            else:
                stack[k, oy[k] : oy[k] + yb - ya - 2 * h, ox[k] : ox[k] + xb - xa - 2 * h] = tm(img_cur[ya:yb, xa:xb], tpl[i], method)

    flat_stack = stack.reshape(ng, -1)  # cells m·m … of each row are the sentinel row
    idx = np.argmax(flat_stack, axis=1)
    bi, bj = np.divmod(idx, m)
    kk = np.arange(ng)
    b = flat_stack[kk, idx].astype(np.float64)
    b = np.where(np.isfinite(b), b, -1.0)

    # Neighbours of the peak; the sentinel marks cells outside the searched area.
    sent = m * m
    left = flat_stack[kk, np.where(bj > 0, idx - 1, sent)].astype(np.float64)
    right = flat_stack[kk, np.where(bj < m - 1, idx + 1, sent)].astype(np.float64)
    up = flat_stack[kk, np.where(bi > 0, idx - m, sent)].astype(np.float64)
    down = flat_stack[kk, np.where(bi < m - 1, idx + m, sent)].astype(np.float64)
    edge_l, edge_r, edge_u, edge_d = (v <= _EMPTY + 0.5 for v in (left, right, up, down))
    cx, cy = c[k_run, 0], c[k_run, 1]
    leaving = (
        (edge_l & (x0 > cx - sr))
        | (edge_r & (x1 < cx + sr))
        | (edge_u & (y0 > cy - sr))
        | (edge_d & (y1 < cy + sr))
    )
    at_edge = edge_l | edge_r | edge_u | edge_d
    ambiguous = _ambiguous(flat_stack, m, bi, bj, b, config)

    v = np.zeros(ng, np.int8)
    v[leaving] = OUT_OF_IMAGE
    v[(v == OK) & (b < config.k_min)] = LOW_SCORE
    v[(v == OK) & ambiguous] = AMBIGUOUS
    v[(v == OK) & at_edge] = PEAK_AT_EDGE
    r[grp] = v
    best[grp] = b
    nbrs[:, grp] = (left, right, up, down)
    found[grp] = np.stack([origin[:, 0] + bj, origin[:, 1] + bi], 1)


def _ambiguous(flat_stack: np.ndarray, m: int, bi: np.ndarray, bj: np.ndarray, best: np.ndarray, config: NCCConfig) -> np.ndarray:
    """True where a second local maximum ≥ best − margin lies ≥ min_separation from the best.

    Only cells already scoring ≥ best − margin can be such a peak, and any local maximum reached
    by climbing from one of them scores at least as much, so it suffices to test those few
    cells for being a local maximum (3×3, ties allowed) — no dense peak map is needed.
    """
    nr = len(best)
    thr = (best - config.ambiguity_margin).astype(np.float32)
    kc, ic = np.nonzero(flat_stack >= thr[:, None])
    ci, cj = np.divmod(ic, m)
    far = (ci - bi[kc]) ** 2 + (cj - bj[kc]) ** 2 >= config.ambiguity_min_separation**2
    kc, ci, cj = kc[far], ci[far], cj[far]
    out = np.zeros(nr, bool)
    if len(kc) == 0:
        return out
    v = flat_stack[kc, ci * m + cj]
    is_max = np.ones(len(kc), bool)
    sent = m * m
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            ni, nj = ci + di, cj + dj
            inside = (ni >= 0) & (ni < m) & (nj >= 0) & (nj < m)
            is_max &= v >= flat_stack[kc, np.where(inside, ni * m + nj, sent)]
    out[kc[is_max]] = True
    return out


def match_ncc(
    img_prev: np.ndarray,
    img_cur: np.ndarray,
    pts_prev: np.ndarray,
    pts_pred: np.ndarray,
    config: NCCConfig,
    search_radius=None,
    scale_pred=None,
    rescale_threshold: float = 0.0,
    scale_key=None,
) -> NCCResult:
    """Find each point of ``img_prev`` in ``img_cur`` by NCC (seed 004 eq. 13–14).

    Parameters
    ----------
    img_prev, img_cur : 2-D uint8 frames of the same shape.
    pts_prev : (N, 2) sub-pixel points (u, v) in ``img_prev``; templates are cut around them.
    pts_pred : (N, 2) predicted pixels in ``img_cur``; the search window is centred there.
    config : matcher settings.
    search_radius : scalar or (N,) px, the largest displacement from ``pts_pred`` searched
        (rounded up, clipped to [1, ``max_search_half``]); default ``config.search_half``.
    scale_pred : None or (N,) predicted scale change of each patch (e.g. its last measured one);
        where |scale_pred − 1| > ``rescale_threshold`` (> 0) the template is resampled at that
        scale before the search, and the scale fit starts from it.
    scale_key : None or (N,) order of the scale fits when more matches than ``max_scale_points``
        are accepted: smallest first (e.g. :func:`companion.core.prediction.bearing_parallax`, the
        points bearings cannot range); default the image motion's distance from the median motion.

    Returns
    -------
    :class:`NCCResult` with matched pixels, scores, accepted flags, verdicts and (with
    ``config.scale_estimation``) the scale change of each accepted match and its σ.
    """
    img_prev = as_gray_u8(img_prev, "img_prev")
    img_cur = as_gray_u8(img_cur, "img_cur")
    if img_prev.shape != img_cur.shape:
        raise InputError(f"img_prev and img_cur differ in shape: {img_prev.shape} vs {img_cur.shape}")
    pts_prev = _check_pts("pts_prev", pts_prev)
    pts_pred = _check_pts("pts_pred", pts_pred, len(pts_prev))
    n = len(pts_prev)
    if scale_key is not None:
        scale_key = np.asarray(scale_key, float).reshape(-1)
        if scale_key.shape != (n,) or np.any(np.isnan(scale_key)):
            raise InputError(f"scale_key must be ({n},) without NaN")
    if scale_pred is not None:
        scale_pred = np.asarray(scale_pred, float).reshape(-1)
        if scale_pred.shape != (n,) or not np.all(np.isfinite(scale_pred)) or np.any(scale_pred <= 0):
            raise InputError(f"scale_pred must be ({n},) finite and > 0")
    templates, frac, inside = extract_templates(img_prev, pts_prev, config.template_half)
    if scale_pred is not None and rescale_threshold > 0:
        big = np.flatnonzero(np.abs(scale_pred - 1.0) > rescale_threshold)
        if len(big):
            templates[big], frac[big], inside[big] = extract_scaled_templates(
                img_prev, pts_prev[big], config.template_half, scale_pred[big])
    res = match_templates(
        templates, frac, img_cur, pts_pred, config, search_radius, valid=inside, img_prev=img_prev, pts_prev=pts_prev
    )
    if config.scale_estimation and np.any(res.ok) and config.max_scale_points > 0:
        g = np.flatnonzero(res.ok)
        if len(g) > config.max_scale_points:  # least parallax first
            if scale_key is not None:
                key = scale_key[g]
            else:  # image motion nearest the median motion
                flow = res.pts[g] - pts_prev[g]
                key = np.linalg.norm(flow - np.median(flow, axis=0), axis=1)
            g = g[np.argsort(key, kind="stable")[: config.max_scale_points]]
        s0 = None if scale_pred is None else scale_pred[g]
        res.scale[g], res.scale_sigma[g] = estimate_scale(img_prev, img_cur, pts_prev[g], res.pts[g], config, s0)
    return res
