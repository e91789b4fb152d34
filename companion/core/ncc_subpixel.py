"""Sub-pixel refinement of the NCC matcher's integer peaks by Lucas–Kanade (the "Sub-pixel
accuracy" paragraph of :mod:`companion.core.ncc`; seed 004 eq. 13 for the normalization).

* :func:`_lk_refine_frames` — with both frames at hand: one single-level ``cv2.calcOpticalFlowPyrLK``
  for all points, started at the peak (:func:`companion.core.lk_kernel.lk_track`, its compiled copy,
  docs/derivations/compute.md "Sub-pixel step");
* :func:`_lk_refine` — with only the templates kept from a track's last observation (a track that
  missed a frame): an inverse-compositional Lucas–Kanade step on the zero-mean, unit-norm patches.

:func:`companion.core.ncc.match_templates` calls them after the integer peak; the parabola through
the peak (``subpixel_method = "parabola"`` and the fallback where Lucas–Kanade fails) stays there.
"""

from __future__ import annotations

import numpy as np

from companion.core.lk_kernel import lk_track
from companion.core.ncc_templates import _patches


def _lk_refine(templates: np.ndarray, img: np.ndarray, peak: np.ndarray, h: int, iterations: int) -> np.ndarray:
    """Sub-pixel offsets (M, 2) of stored templates (M, T+2, T+2) around their integer NCC peaks.

    Used when the frame the templates were cut from is no longer available (a track that missed
    a frame).  Lucas–Kanade, inverse-compositional form: minimizes Σ (ĝ(x + δ) − f̂(x))² over the
    translation δ, with f̂, ĝ the zero-mean, unit-norm template and current patch (the
    normalization of eq. 13, so the step has the same gain/offset invariance as the score).  The
    template gradients (from the 1-px rim) and the 2×2 normal matrix are computed once; each
    iteration resamples the current patch bilinearly at the grid + δ and takes a Gauss–Newton
    step; |δ| ≤ 1 px.  Exact (δ = 0) for an integer shift.
    """
    m = len(peak)
    tpl = templates.astype(np.float32)
    f = tpl[:, 1:-1, 1:-1]
    f = f - f.mean(axis=(1, 2), keepdims=True)
    nf = np.sqrt(np.einsum("nij,nij->n", f, f))[:, None, None]
    nf = np.where(nf > 1e-6, nf, np.float32(1.0))
    f = f / nf
    gx = (tpl[:, 1:-1, 2:] - tpl[:, 1:-1, :-2]) * (0.5 / nf)
    gy = (tpl[:, 2:, 1:-1] - tpl[:, :-2, 1:-1]) * (0.5 / nf)
    axx = np.einsum("nij,nij->n", gx, gx)
    axy = np.einsum("nij,nij->n", gx, gy)
    ayy = np.einsum("nij,nij->n", gy, gy)
    det = axx * ayy - axy * axy
    solvable = det > 1e-6 * np.maximum(axx * ayy, 1e-30)
    det = np.where(solvable, det, 1.0)

    patch = _patches(img, peak, h + 1).astype(np.float32)  # (M, t+2, t+2)
    d = np.zeros((m, 2), np.float32)
    for it in range(iterations):
        if it == 0:
            g = patch[:, 1:-1, 1:-1]
        else:
            dx = d[:, 0, None, None]
            dy = d[:, 1, None, None]
            c = patch[:, :, 1:-1]
            hor = c + np.abs(dx) * (np.where(dx >= 0, patch[:, :, 2:], patch[:, :, :-2]) - c)
            c = hor[:, 1:-1, :]
            g = c + np.abs(dy) * (np.where(dy >= 0, hor[:, 2:, :], hor[:, :-2, :]) - c)
        g = g - g.mean(axis=(1, 2), keepdims=True)
        ng = np.sqrt(np.einsum("nij,nij->n", g, g))[:, None, None]
        res = g / np.where(ng > 1e-6, ng, np.float32(1.0)) - f
        bx = np.einsum("nij,nij->n", gx, res)
        by = np.einsum("nij,nij->n", gy, res)
        step = np.stack([(ayy * bx - axy * by) / det, (axx * by - axy * bx) / det], 1)
        d = np.clip(d - np.where(solvable[:, None], step, 0.0), -1.0, 1.0)
    return d.astype(np.float64)


def _lk_refine_frames(
    img_prev: np.ndarray, img_cur: np.ndarray, pts_prev: np.ndarray, guess: np.ndarray, h: int, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel match of ``pts_prev`` (exact sub-pixel points of ``img_prev``) starting from ``guess``.

    One ``cv2.calcOpticalFlowPyrLK`` for all points (single level, window = the template,
    bilinear interpolation of both frames, so the template sits exactly on the sub-pixel point).
    Returns the refined points and a mask of those that converged within 1 px of the guess.
    """
    # lk_track is the compiled copy of cv2.calcOpticalFlowPyrLK (same floats on x86; calls OpenCV
    # itself when kernels are off): companion/core/lk_kernel.py
    nxt, status = lk_track(img_prev, img_cur, pts_prev, guess, h, iterations, 0.01)
    ok = status & np.all(np.isfinite(nxt), 1) & np.all(np.abs(nxt - guess) <= 1.0, 1)
    return nxt, ok
