"""Harris corner detector with grid bucketing and sub-pixel refinement (seed 004 eq. 11–12).

For every pixel the structure tensor of the image gradients summed over a ``block_size`` window,

    D = Σ_w [[Ix², Ix·Iy], [Ix·Iy, Iy²]],

gives the Harris response (eq. 12)

    Har = det D − k (tr D)²,        k = 0.04,

computed by ``cv2.cornerHarris`` (Sobel gradients of aperture ``aperture``).  A corner is a local
maximum of Har over a (2·min_distance + 1)² square (non-maximum suppression with ``cv2.dilate``)
that reaches ``rel_threshold`` × the strongest response of its grid cell (and a tiny
``global_rel_threshold`` × the strongest of the frame).  The threshold is per cell because Har
grows with the fourth power of contrast: a global one would silence a dim half of the image
entirely, whatever the bucketing.  The survivors are spread over a ``grid_rows`` × ``grid_cols``
grid: the strongest corner of every cell is taken first,
then the second strongest of every cell, and so on (round robin, at most ``cell_cap`` per cell),
so that a richly textured patch cannot take every slot.  The chosen corners are refined to
sub-pixel accuracy by the gradient-orthogonality condition that ``cv2.cornerSubPix`` also uses:
for every pixel x near a corner q, the image gradient is orthogonal to x − q, so q solves the
2×2 weighted least-squares system

    (Σ w ∇I ∇Iᵀ) q = Σ w ∇I ∇Iᵀ x      (w: Gaussian window of half-size ``subpix_window``),

here solved for all corners at once with numpy (re-centred ``subpix_iterations`` times), which
is several times cheaper than the per-point iterative OpenCV call and at least as accurate on an
anti-aliased checkerboard (≤ 0.07 px against ≤ 0.11 px).

Input images: this module accepts **2-D uint8 grayscale arrays only** (an ``(H, W, 1)`` array is
squeezed).  Colour or float frames raise :class:`~companion.errors.InputError` instead of being
converted silently: the colour order (BGR / RGB) and the float scale (0–1 or 0–255) are known
only to the frame source, which converts once per frame (``cv2.cvtColor(frame,
cv2.COLOR_BGR2GRAY)``).  :func:`as_gray_u8` is the check, shared by the NCC matcher and the
track manager.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from companion.config import require, require_finite
from companion.errors import InputError


@dataclasses.dataclass(frozen=True)
class HarrisConfig:
    """The ``[harris]`` table: Harris response, non-maximum suppression, bucketing, sub-pixel."""

    k: float = 0.04  # seed 004 eq. 12
    block_size: int = 3  # structure-tensor window (px)
    aperture: int = 3  # Sobel aperture (1, 3, 5 or 7)
    rel_threshold: float = 0.01  # keep responses >= rel_threshold × the strongest response of their grid cell
    global_rel_threshold: float = 1e-5  # ... and > this × the strongest response of the frame
    min_distance: int = 7  # NMS radius: corners are local maxima over a (2r+1)² square
    grid_rows: int = 6  # bucketing grid
    grid_cols: int = 8
    max_corners: int = 300  # default number of corners returned
    cell_cap: int = 16  # at most this many corners per grid cell (0 = no cap)
    border: int = 8  # no corners closer than this to the image edge (px)
    subpix_window: int = 3  # half-size of the sub-pixel refinement window; 0 disables refinement
    subpix_iterations: int = 2
    priority_min_distance: int = 6  # NMS radius inside the caller's priority region (denser corners there); 0 = min_distance
    priority_rel_threshold: float = -1.0  # per-cell relative threshold inside the priority region; < 0 = rel_threshold

    def __post_init__(self) -> None:
        require_finite("k", self.k, positive=True)
        require(self.k < 0.25, f"k must be < 0.25 (Harris k is usually 0.04–0.06), got {self.k}")
        require(
            isinstance(self.block_size, int) and self.block_size >= 2,
            f"block_size must be an integer >= 2, got {self.block_size!r}",
        )
        require(self.aperture in (1, 3, 5, 7), f"aperture must be 1, 3, 5 or 7, got {self.aperture!r}")
        require_finite("rel_threshold", self.rel_threshold, nonnegative=True)
        require(self.rel_threshold < 1, f"rel_threshold must be < 1, got {self.rel_threshold}")
        require_finite("global_rel_threshold", self.global_rel_threshold, nonnegative=True)
        require(self.global_rel_threshold < 1, f"global_rel_threshold must be < 1, got {self.global_rel_threshold}")
        for name in ("min_distance", "grid_rows", "grid_cols", "max_corners"):
            v = getattr(self, name)
            require(isinstance(v, int) and v >= 1, f"{name} must be an integer >= 1, got {v!r}")
        for name in ("cell_cap", "border", "subpix_window"):
            v = getattr(self, name)
            require(isinstance(v, int) and v >= 0, f"{name} must be an integer >= 0, got {v!r}")
        require(
            isinstance(self.subpix_iterations, int) and self.subpix_iterations >= 1,
            f"subpix_iterations must be an integer >= 1, got {self.subpix_iterations!r}",
        )
        require(isinstance(self.priority_min_distance, int) and not isinstance(self.priority_min_distance, bool)
                and 0 <= self.priority_min_distance, f"priority_min_distance must be an integer >= 0, got {self.priority_min_distance!r}")
        require_finite("priority_rel_threshold", self.priority_rel_threshold)
        require(self.priority_rel_threshold < 1, f"priority_rel_threshold must be < 1, got {self.priority_rel_threshold}")
        require(
            self.subpix_window == 0 or self.border >= self.subpix_window + 2,
            f"border ({self.border}) must be >= subpix_window + 2 ({self.subpix_window + 2})",
        )


def as_gray_u8(image, name: str = "image") -> np.ndarray:
    """Check that ``image`` is a non-empty 2-D uint8 grayscale frame and return it C-contiguous.

    An ``(H, W, 1)`` array is squeezed.  Everything else raises :class:`InputError` naming the
    problem (empty, colour, float, wrong number of dimensions); see the module docstring for why
    colour and float frames are not converted here.
    """
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name} must be a numpy array, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        raise InputError(
            f"{name} is a colour image of shape {image.shape}; convert it to grayscale first, "
            "e.g. cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)"
        )
    if image.ndim != 2:
        raise InputError(f"{name} must be a 2-D grayscale array, got shape {image.shape}")
    if image.size == 0:
        raise InputError(f"{name} is empty (shape {image.shape})")
    if image.dtype != np.uint8:
        raise InputError(
            f"{name} must have dtype uint8, got {image.dtype}; scale to 0–255 and convert "
            "(e.g. np.clip(img * 255, 0, 255).astype(np.uint8) for a 0–1 float image)"
        )
    return np.ascontiguousarray(image)


def _points(name: str, pts, allow_none: bool = True) -> np.ndarray | None:
    if pts is None:
        return None
    a = np.asarray(pts, dtype=float)
    if a.size == 0:
        return np.zeros((0, 2))
    if a.ndim != 2 or a.shape[1] != 2:
        raise InputError(f"{name} must have shape (N, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} contains NaN or inf (rows {np.flatnonzero(~np.all(np.isfinite(a), 1))[:5].tolist()})")
    return a


def _exclusion_mask(shape: tuple[int, int], pts: np.ndarray, radius: float) -> np.ndarray:
    """uint8 image, 255 where some point of ``pts`` is within ``radius`` in both u and v.

    A square (Chebyshev) neighbourhood: one separable ``cv2.dilate`` of a point image, several
    times cheaper than a disc, and everything outside it is at least ``radius`` away.
    """
    h, w = shape
    out = np.zeros((h, w), np.uint8)
    ij = np.rint(pts).astype(np.int64)
    keep = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    out[ij[keep, 1], ij[keep, 0]] = 255
    r = int(np.ceil(radius))
    if r > 0:
        out = cv2.dilate(out, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1)))
    return out


def _dedupe_ties(xs: np.ndarray, ys: np.ndarray, resp: np.ndarray, radius: int) -> np.ndarray:
    """Keep-mask that removes plateau duplicates: equal responses within ``radius`` of each other.

    ``cv2.dilate`` NMS keeps every pixel equal to its neighbourhood maximum, so two pixels with
    exactly the same response (a plateau, or a symmetric synthetic pattern) both survive.  Such
    ties are rare in real images; ``resp`` is sorted descending, so each run of equal values is
    handled greedily (one small loop per tied run, never per pixel).
    """
    keep = np.ones(len(resp), bool)
    if len(resp) < 2:
        return keep
    eq = resp[1:] == resp[:-1]
    if not np.any(eq):
        return keep
    starts = np.flatnonzero(np.diff(np.concatenate([[False], eq, [False]]).astype(np.int8)) == 1)
    ends = np.flatnonzero(np.diff(np.concatenate([[False], eq, [False]]).astype(np.int8)) == -1)
    for s, e in zip(starts, ends):  # run covers indices s .. e (inclusive)
        idx = np.arange(s, e + 1)
        if len(idx) <= 2048:  # skip runs whose members are all far apart (the usual case)
            dx = np.abs(xs[idx, None] - xs[None, idx])
            dy = np.abs(ys[idx, None] - ys[None, idx])
            close = np.maximum(dx, dy) <= radius
            np.fill_diagonal(close, False)
            if not np.any(close):
                continue
        kept: list[int] = []
        for i in idx:
            if all(max(abs(xs[i] - xs[j]), abs(ys[i] - ys[j])) > radius for j in kept):
                kept.append(int(i))
            else:
                keep[i] = False
    return keep


def refine_corners(gray: np.ndarray, pts: np.ndarray, window: int, iterations: int = 2) -> np.ndarray:
    """Sub-pixel corner positions (N, 2) from approximate ones, vectorized over corners.

    Solves (Σ w ∇I ∇Iᵀ) q = Σ w ∇I ∇Iᵀ x over a (2·window+1)² neighbourhood of the nearest
    pixel (3×3 Sobel gradients, Gaussian weights σ = window/1.5), up to ``iterations`` times,
    each time re-centred on the pixel nearest the previous solution (a point whose nearest pixel
    did not change is done: the same window gives the same answer).  Corners whose system is singular
    (flat or straight-edge neighbourhoods) come back as NaN so that the caller can drop them.
    Points closer than ``window + 1`` px to the image edge are clamped inside (callers keep a border).
    """
    gray = as_gray_u8(gray, "gray")
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    H, W = gray.shape
    r = window + 1
    size = 2 * r + 1
    k = (2 * window + 1) ** 2
    off = np.arange(-window, window + 1, dtype=np.float32)
    xo = np.broadcast_to(off[None, :], (len(off), len(off))).reshape(k)
    yo = np.broadcast_to(off[:, None], (len(off), len(off))).reshape(k)
    wgt = np.exp(-(xo**2 + yo**2) / (2.0 * (window / 1.5) ** 2)).astype(np.float32)
    view = np.lib.stride_tricks.sliding_window_view(gray, (size, size))
    iq = ((yo.astype(np.int64) + r) * size + (xo.astype(np.int64) + r))  # window pixels in a flat patch
    p = pts.copy()
    bad = np.zeros(n, bool)
    todo = np.arange(n)
    centre = np.full((n, 2), -1, np.int64)
    for _ in range(iterations):
        c = np.rint(p[todo]).astype(np.int64)
        c[:, 0] = np.clip(c[:, 0], r, W - 1 - r)
        c[:, 1] = np.clip(c[:, 1], r, H - 1 - r)
        moved = np.any(c != centre[todo], axis=1)  # same centre as last time: same answer
        todo, c = todo[moved], c[moved]
        if len(todo) == 0:
            break
        centre[todo] = c
        m = len(todo)
        # 3×3 Sobel (÷8) on the flattened patches: a central difference along one axis, then
        # [1 2 1] across, gathered at the window's pixels (contiguous rows are much faster
        # than (M, 9, 7) strided slices).
        P = view[c[:, 1] - r, c[:, 0] - r].reshape(m, size * size).astype(np.float32)
        dx = P[:, 2:] - P[:, :-2]  # dx[:, q - 1] = P[q + 1] − P[q − 1]
        dy = P[:, 2 * size :] - P[:, : -2 * size]  # dy[:, q − size] = P[q + size] − P[q − size]
        gx = (dx[:, iq - 1 - size] + dx[:, iq - 1 + size] + 2.0 * dx[:, iq - 1]) * np.float32(0.125)
        gy = (dy[:, iq - size - 1] + dy[:, iq - size + 1] + 2.0 * dy[:, iq - size]) * np.float32(0.125)
        wgx = gx * wgt
        wgy = gy * wgt
        proj = gx * xo + gy * yo  # ∇Iᵀ (x − c)
        axx = np.einsum("nk,nk->n", wgx, gx).astype(np.float64)
        axy = np.einsum("nk,nk->n", wgx, gy).astype(np.float64)
        ayy = np.einsum("nk,nk->n", wgy, gy).astype(np.float64)
        rx = np.einsum("nk,nk->n", wgx, proj).astype(np.float64)
        ry = np.einsum("nk,nk->n", wgy, proj).astype(np.float64)
        det = axx * ayy - axy * axy
        sing = ~(det > 1e-9 * np.maximum(axx * ayy, 1e-30))
        det = np.where(sing, 1.0, det)
        p[todo] = c + np.stack([(ayy * rx - axy * ry) / det, (axx * ry - axy * rx) / det], 1)
        bad[todo] |= sing
    p[bad] = np.nan
    return p


def harris_response(gray: np.ndarray, config: HarrisConfig) -> np.ndarray:
    """Harris response map Har = det D − k (tr D)² (eq. 12), float32, same shape as ``gray``."""
    gray = as_gray_u8(gray, "gray")
    return cv2.cornerHarris(gray, config.block_size, config.aperture, config.k)


def _candidates(R: np.ndarray, cand: np.ndarray, b: int, radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (x, y) and responses of the non-zero entries of ``cand`` (offset by the border
    ``b``), strongest first, plateau ties within ``radius`` removed."""
    nz = cv2.findNonZero(cand)
    if nz is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    nz = nz.reshape(-1, 2)
    xs = nz[:, 0].astype(np.int64) + b
    ys = nz[:, 1].astype(np.int64) + b
    resp = R[ys, xs].astype(np.float64)
    order = np.argsort(-resp, kind="stable")
    xs, ys, resp = xs[order], ys[order], resp[order]
    keep = _dedupe_ties(xs, ys, resp, radius)
    return xs[keep], ys[keep], resp[keep]


def _bucketed(xs: np.ndarray, ys: np.ndarray, resp: np.ndarray, config: HarrisConfig, h: int, w: int,
              rel_threshold: float | None = None) -> np.ndarray:
    """Selection order of candidates sorted by descending ``resp``: round robin over the grid cells
    (every cell's strongest first, then every cell's second, ...), keeping responses >=
    ``rel_threshold`` (default ``config.rel_threshold``) × their cell's strongest and at most
    ``cell_cap`` per cell."""
    rel = config.rel_threshold if rel_threshold is None else rel_threshold
    cell = (ys * config.grid_rows // h) * config.grid_cols + (xs * config.grid_cols // w)
    by_cell = np.lexsort((-resp, cell))
    cell_sorted = cell[by_cell]
    first = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.empty(len(cell), np.int64)
    rank[by_cell] = np.arange(len(cell)) - first
    cell_max = np.empty(len(cell))
    cell_max[by_cell] = resp[by_cell][first]
    sel = np.lexsort((-resp, rank))
    sel = sel[resp[sel] >= rel * cell_max[sel]]
    if config.cell_cap > 0:
        sel = sel[rank[sel] < config.cell_cap]
    return sel


def detect_harris(
    gray: np.ndarray,
    config: HarrisConfig,
    mask: np.ndarray | None = None,
    exclude_pts: np.ndarray | None = None,
    exclude_radius: float | None = None,
    max_corners: int | None = None,
    priority: np.ndarray | None = None,
    priority_max: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Harris corners of ``gray`` (seed 004 eq. 11–12).

    Parameters
    ----------
    gray : (H, W) uint8 grayscale frame (see :func:`as_gray_u8`).
    config : detector settings.
    mask : optional (H, W) array, non-zero where corners are allowed.
    exclude_pts : optional (K, 2) pixels (u, v); no corner is returned within ``exclude_radius``
        of any of them in both u and v (a square around each, so every corner returned is at
        least that far away); the track manager passes its live tracks so new corners start
        elsewhere.
    exclude_radius : px, default ``config.min_distance``.
    max_corners : how many corners at most, default ``config.max_corners`` (0 returns none).
    priority : optional (H, W) array, non-zero in a region whose corners are taken first: up to
        ``priority_max`` of them (default: all ``max_corners``), bucketed among themselves (so
        weak corners there are not cut by the per-cell threshold of strong ones beside them);
        the remaining budget goes to the usual ranking over the whole (masked) image.
    priority_max : corners at most taken first from ``priority``.

    Returns
    -------
    pts : (N, 2) float64 sub-pixel corner positions (u, v), in selection order (bucketing round
        robin: every cell's strongest corner first, then every cell's second, ...).
    response : (N,) float64 Harris response at the (integer) maximum of each corner.
    """
    gray = as_gray_u8(gray, "gray")
    h, w = gray.shape
    n_max = config.max_corners if max_corners is None else max_corners
    if not isinstance(n_max, (int, np.integer)) or isinstance(n_max, bool) or n_max < 0:
        raise InputError(f"max_corners must be a non-negative integer, got {max_corners!r}")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != gray.shape:
            raise InputError(f"mask must have the image's shape {gray.shape}, got {mask.shape}")
    if priority is not None:
        priority = np.asarray(priority)
        if priority.shape != gray.shape:
            raise InputError(f"priority must have the image's shape {gray.shape}, got {priority.shape}")
    n_pri = n_max if priority_max is None else priority_max
    if not isinstance(n_pri, (int, np.integer)) or isinstance(n_pri, bool) or n_pri < 0:
        raise InputError(f"priority_max must be a non-negative integer, got {priority_max!r}")
    n_pri = min(int(n_pri), int(n_max))
    exclude_pts = _points("exclude_pts", exclude_pts)
    radius = float(config.min_distance if exclude_radius is None else exclude_radius)
    if not np.isfinite(radius) or radius < 0:
        raise InputError(f"exclude_radius must be finite and >= 0, got {exclude_radius!r}")
    empty = (np.zeros((0, 2)), np.zeros(0))
    b = config.border
    if n_max == 0 or h <= 2 * b or w <= 2 * b:
        return empty

    R = cv2.cornerHarris(gray, config.block_size, config.aperture, config.k)
    inner = R[b : h - b, b : w - b]
    r_max = float(cv2.minMaxLoc(inner)[1])
    if not r_max > 0:
        return empty  # flat or edge-only image: no corner anywhere
    d = 2 * config.min_distance + 1
    dil = cv2.dilate(R, cv2.getStructuringElement(cv2.MORPH_RECT, (d, d)))[b : h - b, b : w - b]
    cand = cv2.bitwise_and(cv2.compare(inner, dil, cv2.CMP_GE), cv2.compare(inner, config.global_rel_threshold * r_max, cv2.CMP_GT))
    if mask is not None:
        cand[mask[b : h - b, b : w - b] == 0] = 0
    excl = None
    if exclude_pts is not None and len(exclude_pts) and radius > 0:
        excl = _exclusion_mask((h, w), exclude_pts, radius)[b : h - b, b : w - b] != 0
        cand[excl] = 0
    xs, ys, resp = _candidates(R, cand, b, config.min_distance)
    # Grid bucketing: rank of each corner inside its cell (0 = strongest), then round robin.
    sel = _bucketed(xs, ys, resp, config, h, w)
    is_pri = None
    # A few spares: refinement drops corners whose neighbourhood turns out edge-like.
    spare = max(8, n_max // 10) if config.subpix_window > 0 else 0
    if priority is not None and n_pri > 0:
        # Priority region first: its own (optionally denser) non-maximum suppression and its own
        # bucketing (per-cell thresholds relative to the region's corners only, so weak corners
        # there are not silenced by strong ones beside them); then the rest of the ranking.
        pd = config.priority_min_distance or config.min_distance
        pcand = cand
        if pd != config.min_distance:
            dp = 2 * pd + 1
            dil_p = cv2.dilate(R, cv2.getStructuringElement(cv2.MORPH_RECT, (dp, dp)))[b : h - b, b : w - b]
            pcand = cv2.bitwise_and(cv2.compare(inner, dil_p, cv2.CMP_GE), cv2.compare(inner, config.global_rel_threshold * r_max, cv2.CMP_GT))
            if mask is not None:
                pcand[mask[b : h - b, b : w - b] == 0] = 0
            if excl is not None:
                pcand[excl] = 0
        pcand = pcand.copy()
        pcand[priority[b : h - b, b : w - b] == 0] = 0
        px, py, pr = _candidates(R, pcand, b, pd)
        if len(px):
            prel = config.rel_threshold if config.priority_rel_threshold < 0 else config.priority_rel_threshold
            psel = _bucketed(px, py, pr, config, h, w, prel)[: n_pri + min(spare, n_pri)]
            px, py, pr = px[psel], py[psel], pr[psel]
            # the usual ranking without the corners already taken (same pixel) or too near them
            near = _exclusion_mask((h, w), np.stack([px, py], 1).astype(float), pd)[ys, xs] != 0
            rest = sel[~near[sel]]
            xs = np.concatenate([px, xs[rest]])
            ys = np.concatenate([py, ys[rest]])
            resp = np.concatenate([pr, resp[rest]])
            sel = np.arange(len(xs))
            is_pri = np.zeros(len(xs), bool)
            is_pri[: len(px)] = True
    sel = sel[: n_max + spare]
    if is_pri is not None:
        is_pri = is_pri[: len(sel)]
    xs, ys, resp = xs[sel], ys[sel], resp[sel]

    pts = np.stack([xs, ys], 1).astype(np.float64)
    if config.subpix_window > 0 and len(pts):
        ref = refine_corners(gray, pts, config.subpix_window, config.subpix_iterations)
        # A refinement that runs away from its window (flat or edge-like neighbourhood) is dropped.
        ok = (
            np.all(np.isfinite(ref), 1)
            & np.all(np.abs(ref - pts) <= config.subpix_window, 1)
            & (ref[:, 0] >= b)
            & (ref[:, 0] <= w - 1 - b)
            & (ref[:, 1] >= b)
            & (ref[:, 1] <= h - 1 - b)
        )
        pts, resp = ref[ok], resp[ok]
        if is_pri is not None:
            is_pri = is_pri[: len(ok)][ok]
    if is_pri is not None:
        # at most n_pri from the region first (spares beyond it go back behind the rest)
        p_idx = np.flatnonzero(is_pri[: len(pts)])
        order = np.concatenate([p_idx[:n_pri], np.flatnonzero(~is_pri[: len(pts)]), p_idx[n_pri:]])
        pts, resp = pts[order], resp[order]
    return pts[:n_max], resp[:n_max]
