"""Templates of the NCC matcher (seed 004 eq. 13): cut around points of the previous frame, or
resampled at a predicted scale change (docs/derivations/looming.md), and the structure-tensor test
that refuses edges.

* :func:`extract_templates` — the (2·half+1)² patch at the pixel nearest each sub-pixel point, plus
  a 1-px rim for the gradients, and the sub-pixel offset carried over to the match;
* :func:`extract_scaled_templates` — the same patch as it will look after growing by a scale
  (bilinear, :func:`_bilinear`), centred on the sub-pixel point;
* :func:`template_eigen_ratio` — λmin/λmax of each template's structure tensor (``EDGE_TEMPLATE``
  of :mod:`companion.core.ncc`);
* :func:`_check_pts` — the point arrays' shape and finiteness check the matcher's entry points share.

Used by :mod:`companion.core.ncc` (which re-exports the public names) and
:mod:`companion.core.ncc_scale`; the compiled form of :func:`template_eigen_ratio` is
``template_stats`` in :mod:`companion.core.ncc_kernels`.
"""

from __future__ import annotations

import cv2
import numpy as np

from companion.core.harris import as_gray_u8
from companion.errors import InputError


def _check_pts(name: str, pts, n: int | None = None) -> np.ndarray:
    a = np.asarray(pts, dtype=float)
    if a.size == 0 and (n is None or n == 0):
        return np.zeros((0, 2))
    if a.ndim != 2 or a.shape[1] != 2:
        raise InputError(f"{name} must have shape (N, 2), got {a.shape}")
    if n is not None and len(a) != n:
        raise InputError(f"{name} has {len(a)} rows, expected {n}")
    bad = ~np.all(np.isfinite(a), 1)
    if np.any(bad):
        raise InputError(f"{name} contains NaN or inf (rows {np.flatnonzero(bad)[:5].tolist()})")
    return a


def extract_templates(image: np.ndarray, pts: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut templates around the pixels nearest to ``pts`` (one vectorized gather).

    Each template is (2·half+3)²: the (2·half+1)² patch that is matched plus a 1-px rim used
    only for the template gradients of the sub-pixel step.  Returns ``templates`` (N, T+2, T+2)
    uint8 (zeros where they do not fit), ``frac`` (N, 2) = pts − rounded pts (the sub-pixel
    offset carried over to the match) and ``inside`` (N,) bool (template and rim fit).
    """
    image = as_gray_u8(image, "image")
    pts = _check_pts("pts", pts)
    h_img, w_img = image.shape
    r = half + 1
    q = np.rint(pts).astype(np.int64)
    inside = (q[:, 0] >= r) & (q[:, 0] <= w_img - 1 - r) & (q[:, 1] >= r) & (q[:, 1] <= h_img - 1 - r)
    frac = pts - q
    templates = _patches(image, q, r)
    templates[~inside] = 0
    return templates, frac, inside


def _patches(image: np.ndarray, centres: np.ndarray, r: int) -> np.ndarray:
    """(N, 2r+1, 2r+1) copies of the patches around integer ``centres`` (u, v), clamped to the image.

    Indexing a sliding-window view copies whole blocks, ~6× faster than gathering every pixel.
    """
    H, W = image.shape
    size = 2 * r + 1
    if H < size or W < size:
        return np.zeros((len(centres), size, size), image.dtype)
    x = np.clip(centres[:, 0] - r, 0, W - size)
    y = np.clip(centres[:, 1] - r, 0, H - size)
    return np.lib.stride_tricks.sliding_window_view(image, (size, size))[y, x]


def template_eigen_ratio(templates: np.ndarray) -> np.ndarray:
    """λmin/λmax of the structure tensor M = Σ ∇I ∇Iᵀ of each template (N,), in [0, 1].

    ``templates`` (N, T+2, T+2): the matched patch plus its 1-px rim, which the central
    differences use so that every pixel of the T×T patch contributes.  1 for an isotropic corner,
    0 for a straight edge (and for a flat patch).
    """
    t = np.asarray(templates, np.float32)
    gx = t[:, 1:-1, 2:] - t[:, 1:-1, :-2]  # 2·∂I/∂u; the factor cancels in the ratio
    gy = t[:, 2:, 1:-1] - t[:, :-2, 1:-1]
    a = np.einsum("nij,nij->n", gx, gx, dtype=np.float64)
    b = np.einsum("nij,nij->n", gx, gy, dtype=np.float64)
    c = np.einsum("nij,nij->n", gy, gy, dtype=np.float64)
    half_tr = 0.5 * (a + c)
    disc = np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    lmax = half_tr + disc
    lmin = np.maximum(half_tr - disc, 0.0)
    return np.where(lmax > 0, lmin / np.where(lmax > 0, lmax, 1.0), 0.0)


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (float32) of float32 image ``img`` at (x, y) (equal shapes (N, ...)), border
    replicated: one ``cv2.remap`` (for a float32 image its bilinear weights are not quantized)."""
    shape = x.shape
    X = np.ascontiguousarray(x, np.float32).reshape(shape[0], -1)
    Y = np.ascontiguousarray(y, np.float32).reshape(shape[0], -1)
    step = 32000  # cv2.remap wants fewer than SHRT_MAX rows
    out = [cv2.remap(img, X[i : i + step], Y[i : i + step], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
           for i in range(0, len(X), step)]
    return (out[0] if len(out) == 1 else np.concatenate(out)).reshape(shape)


def extract_scaled_templates(image: np.ndarray, pts: np.ndarray, half: int, scale: np.ndarray):
    """Templates like :func:`extract_templates` (with rim) resampled at scale change ``scale`` (N,):
    pixel y of the template is the image at pts + y/scale (bilinear), i.e. the patch as it will look
    after growing by ``scale``.  Centred on the sub-pixel point, so ``frac`` is 0."""
    image = as_gray_u8(image, "image")
    pts = _check_pts("pts", pts)
    scale = np.asarray(scale, float).reshape(len(pts))
    H, W = image.shape
    r = half + 1
    off = np.arange(-r, r + 1, dtype=float)
    ext = r / scale + 1.0
    inside = (pts[:, 0] - ext >= 0) & (pts[:, 0] + ext <= W - 1) & (pts[:, 1] - ext >= 0) & (pts[:, 1] + ext <= H - 1)
    X = pts[:, 0, None, None] + off[None, None, :] / scale[:, None, None]
    Y = pts[:, 1, None, None] + off[None, :, None] / scale[:, None, None]
    X, Y = np.broadcast_arrays(X, Y)
    tpl = np.clip(np.rint(_bilinear(image.astype(np.float32), X, Y)), 0, 255).astype(np.uint8)
    tpl[~inside] = 0
    return tpl, np.zeros((len(pts), 2)), inside
