"""Obstacles on the renderer's canvas: steps 3 and 4 of the pipeline in :mod:`flightsim.render.renderer`.

:class:`Solids` holds the world's obstacles as arrays (per solid: its 8 corners and faces; all
planar faces stacked, so the per-frame face maths is one batch) and draws those in view far to
near into the canvas, its z-buffer (``1/Z``) and, with lens distortion, the surface-id buffer:

* **Boxes, walls, targets** (convex polyhedra): the solid's ``1/Z`` is the minimum over its
  front-facing planes of their affine ``1/Z``; coverage α = clamp(0.5 + signed distance to the
  silhouette, the convex hull of the near-clipped projected corners); each face texture is warped
  with the plane's homography from the mip level its footprint needs.
* **Cylinders**: exact per-pixel ray–circle (and top / bottom disc) intersection inside their
  screen rectangle, textured with ``cv2.remap``; edge coverage from the ray's distance to the axis.

Every solid's layer is composited over the canvas (opaque inside, α-blended on its edge pixels;
its ``1/Z`` written where the pixel centre is inside, α ≥ ½).  Frames: docs/derivations/frames.md
(``R`` = R_world_cam, ``p`` = p_world_cam, world NED, camera OpenCV).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from flightsim.render.kernels import coverage

_F32 = np.float32
#: Box corners joined by the 12 edges (corner index bits: a, b, down).
_BOX_EDGES = [(i, i ^ b) for i in range(8) for b in (1, 2, 4) if i < i ^ b]
_EI = np.array([e[0] for e in _BOX_EDGES])
_EJ = np.array([e[1] for e in _BOX_EDGES])


class _Solid:
    """Render-time data of one obstacle, precomputed as arrays (few numpy calls per frame)."""

    __slots__ = ("ob", "corners", "O", "E1", "E2", "n", "quad", "texel", "mips", "two_sided", "cyl", "cyl_texel")

    def __init__(self, ob, textures):
        self.ob = ob
        self.corners = ob.corners()
        self.cyl = None
        if ob.is_cylinder:
            mips = textures.faces
            self.cyl = (mips[(ob.index, "side")], mips[(ob.index, "top")], mips[(ob.index, "bottom")])
            side0 = self.cyl[0][0]
            self.cyl_texel = max(2 * math.pi * ob.radius / (side0.shape[1] - 2), 2 * ob.half[2] / side0.shape[0])
            return
        faces = ob.faces()
        self.O = np.array([f[1] for f in faces])
        self.E1 = np.array([f[2] for f in faces])
        self.E2 = np.array([f[3] for f in faces])
        self.n = np.array([f[4] for f in faces])
        self.quad = np.stack([self.O, self.O + self.E1, self.O + self.E1 + self.E2, self.O + self.E2], 1)  # (F, 4, 3)
        self.mips = [textures.faces[(ob.index, f[0])] for f in faces]
        self.texel = np.array(
            [max(np.linalg.norm(e1) / m[0].shape[1], np.linalg.norm(e2) / m[0].shape[0]) for e1, e2, m in zip(self.E1, self.E2, self.mips)]
        )
        self.two_sided = ob.kind == "target"


class Solids:
    """The world's obstacles on the canvas of one :class:`~flightsim.render.Renderer` (see module docstring).

    Built once from the world, its textures, the render options and the canvas geometry the
    renderer set up (``canvas_K``, ``canvas_size``, the per-column / per-row ray components ``ub``,
    ``vb``, the canvas frustum and the mean focal length); :meth:`draw` draws one frame.
    """

    def __init__(self, world, textures, options, canvas_K: np.ndarray, canvas_size: tuple[int, int], ub: np.ndarray,
                 vb: np.ndarray, frustum: tuple[float, float, float, float], f_mean: float):
        self.world = world
        self.options = options
        self.canvas_K = canvas_K
        self.canvas_size = canvas_size
        self._ub, self._vb = ub, vb
        self._frustum = frustum
        self._f_mean = f_mean
        Wc, Hc = canvas_size
        self._uf = np.arange(Wc, dtype=float)
        self._vf = np.arange(Hc, dtype=float)
        self._ids: np.ndarray | None = None  # the frame's surface-id buffer, set by draw
        self._solids = [_Solid(ob, textures) for ob in world.obstacles]
        self._corners = np.array([s.corners for s in self._solids], float).reshape(-1, 8, 3)
        # every planar face of every box/wall/target, stacked: per-frame face maths is one batch
        poly = [s for s in self._solids if s.cyl is None]
        self._face_slice = {}
        k = 0
        for s in poly:
            self._face_slice[s.ob.index] = (k, k + len(s.O))
            k += len(s.O)
        cat = lambda name: np.concatenate([getattr(s, name) for s in poly], 0) if poly else np.zeros((0, 3))  # noqa: E731
        self._fO, self._fE1, self._fE2, self._fn = cat("O"), cat("E1"), cat("E2"), cat("n")
        self._fquad = np.concatenate([s.quad for s in poly], 0) if poly else np.zeros((0, 4, 3))
        self._ftexel = np.concatenate([s.texel for s in poly]) if poly else np.zeros(0)
        self._ftwo = np.concatenate([np.full(len(s.O), s.two_sided) for s in poly]) if poly else np.zeros(0, bool)

    def draw(self, R, p, img, invz, ids) -> None:
        """Draw the obstacles seen from the camera pose (``R`` = R_world_cam, ``p`` = p_world_cam)
        into the canvas ``img`` (uint8), its z-buffer ``invz`` (1/Z) and ``ids`` (surface ids, or None)."""
        self._ids = ids
        if not self._solids:
            return
        near = self.options.near_m
        cam = np.einsum("mki,ij->mkj", self._corners - p, R)  # (M, 8, 3) camera frame
        X, Y, Z = cam[..., 0], cam[..., 1], cam[..., 2]
        xl, xr, yt, yb = self._frustum
        out = (
            np.all(Z < near, axis=1)
            | np.all(X < xl * Z, axis=1)
            | np.all(X > xr * Z, axis=1)
            | np.all(Y < yt * Z, axis=1)
            | np.all(Y > yb * Z, axis=1)
        )
        vis = np.nonzero(~out)[0]
        if len(vis) == 0:
            return
        K = self.canvas_K
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = cam[..., :2] / cam[..., 2:3] * (K[0, 0], K[1, 1]) + (K[0, 2], K[1, 2])
        faces = self._face_batch(R, p) if len(self._fO) else None
        dist = self.world.signed_distances(p)[vis]
        for k in vis[np.argsort(-dist)]:  # far to near: edges blend over what lies behind
            s = self._solids[k]
            if s.cyl is not None:
                self._draw_cylinder(s, R, p, cam[k], img, invz, uv[k])
            else:
                self._draw_polyhedron(s, R, p, cam[k], img, invz, uv[k], faces)

    def _face_batch(self, R, p):
        """Per-frame quantities of all planar faces at once: which side the camera is on, the
        plane's 1/Z coefficients, mip levels at its corners and R^T [E1 E2 O − p]."""
        side = np.einsum("ij,ij->i", self._fn, p - self._fO)  # > 0: camera outside the face
        sign = np.where(self._ftwo & (side < 0), -1.0, 1.0)  # two-sided faces turn to the camera
        n_c = (self._fn * sign[:, None]) @ R
        dist = -np.abs(side)  # n_c · X on the plane (< 0: camera outside)
        with np.errstate(divide="ignore", invalid="ignore"):
            coef = (n_c / dist[:, None]).astype(_F32)
        Cc = (self._fquad - p) @ R  # (F, 4, 3)
        np.maximum(Cc[..., 2], self.options.near_m, out=Cc[..., 2])
        rng = np.sqrt(np.sum(Cc * Cc, axis=2))
        cos = np.abs(np.einsum("kcj,kj->kc", Cc, n_c)) / rng
        lam = np.log2(rng / (self._f_mean * self._ftexel[:, None] * np.maximum(cos, 1e-3))) + self.options.lod_bias
        # the face's point nearest the camera (the foot of the perpendicular, clamped into the
        # rectangle) has the finest level; for a large face seen close up it lies inside, far from the corners
        rel = p - self._fO
        e1, e2 = self._fE1, self._fE2
        a1 = np.clip(np.einsum("ij,ij->i", rel, e1) / np.einsum("ij,ij->i", e1, e1), 0.0, 1.0)
        a2 = np.clip(np.einsum("ij,ij->i", rel, e2) / np.einsum("ij,ij->i", e2, e2), 0.0, 1.0)
        near = self._fO + a1[:, None] * e1 + a2[:, None] * e2 - p
        r2 = np.maximum(np.einsum("ij,ij->i", near, near), self.options.near_m**2)
        lam_near = np.log2(r2 / (self._f_mean * self._ftexel * np.maximum(np.abs(dist), self.options.near_m))) + self.options.lod_bias
        lam_lo, lam_hi = np.rint(np.minimum(lam.min(axis=1), lam_near)), np.rint(lam.max(axis=1))
        G = np.einsum("ji,kjc->kic", R, np.stack([self._fE1, self._fE2, self._fO - p], 2))
        front = (side > 1e-9) | (self._ftwo & (np.abs(side) >= 1e-9))
        return front, coef, dist, lam_lo, lam_hi, G

    def _hull(self, cam8: np.ndarray, uv8: np.ndarray | None = None) -> np.ndarray | None:
        """Projected silhouette (convex hull, canvas pixels, positive area) of a convex solid
        given its 8 box corners in the camera frame (and their pixels), clipped at the near plane."""
        near = self.options.near_m
        Z = cam8[:, 2]
        if Z.min() >= near:
            P = cam8
            if uv8 is not None:
                return self._hull_uv(uv8.copy())
        else:
            front = Z >= near
            zi, zj = Z[_EI], Z[_EJ]
            cross = (zi >= near) != (zj >= near)
            t = (near - zi[cross]) / (zj[cross] - zi[cross])
            a, b = cam8[_EI[cross]], cam8[_EJ[cross]]
            P = np.concatenate([cam8[front], a + t[:, None] * (b - a)], 0)
            if len(P) < 3:
                return None
        K = self.canvas_K
        return self._hull_uv(P[:, :2] / P[:, 2:3] * (K[0, 0], K[1, 1]) + (K[0, 2], K[1, 2]))

    @staticmethod
    def _hull_uv(uv: np.ndarray) -> np.ndarray | None:
        np.clip(uv, -1e7, 1e7, out=uv)
        uv32 = uv.astype(np.float32)
        idx = cv2.convexHull(uv32, returnPoints=False)
        if idx is None or len(idx) < 3:
            return None
        idx = idx.reshape(-1)
        area = cv2.contourArea(uv32[idx], oriented=True)
        if abs(area) < 1e-4:
            return None
        hull = uv[idx]
        return hull[::-1] if area < 0 else hull

    def _roi(self, hull: np.ndarray, pad: int = 2):
        Wc, Hc = self.canvas_size
        lo = np.floor(hull.min(axis=0))
        hi = np.ceil(hull.max(axis=0))
        x0, y0 = max(int(lo[0]) - pad, 0), max(int(lo[1]) - pad, 0)
        x1, y1 = min(int(hi[0]) + pad + 1, Wc), min(int(hi[1]) + pad + 1, Hc)
        if x0 >= x1 or y0 >= y1:
            return None
        return x0, x1, y0, y1

    def _coverage(self, hull: np.ndarray, x0, x1, y0, y1) -> np.ndarray:
        """α = clamp(0.5 + signed distance in pixels to the convex polygon ``hull``), on the ROI.

        ``hull`` (distinct vertices, positive shoelace area in pixel axes) has its interior where
        cross(e, q − a) > 0 for every edge a → b = a + e."""
        e = np.concatenate([hull[1:], hull[:1]]) - hull
        inv_len = 1.0 / np.hypot(e[:, 0], e[:, 1])
        ex, ey = e[:, 0:1] * inv_len[:, None], e[:, 1:2] * inv_len[:, None]
        rows = (ey * (hull[:, 0:1] - self._uf[x0:x1]) - ex * hull[:, 1:2]).astype(_F32)  # (n, w)
        cols = (ex * self._vf[y0:y1]).astype(_F32)  # (n, h)
        return coverage(rows, cols)  # clamp(0.5 + minᵢ (rows[i][x] + cols[i][y]), 0, 1)

    def _draw_polyhedron(self, s: _Solid, R, p, cam8, img, invz, uv8, faces) -> None:
        hull = self._hull(cam8, uv8)
        if hull is None:
            return
        roi = self._roi(hull)
        if roi is None:
            return
        x0, x1, y0, y1 = roi
        ub, vb = self._ub[:, x0:x1], self._vb[y0:y1]
        f0, f1 = self._face_slice[s.ob.index]
        b_front, b_coef, b_dist, b_lo, b_hi, b_G = faces
        front = np.nonzero(b_front[f0:f1])[0]
        if len(front) == 0:
            return
        gi = front + f0  # indices into the frame's face batch
        dist = b_dist[gi]
        # 1/Z of each plane: (n_c · m) / dist, affine in pixels
        coef = b_coef[gi]
        rows = coef[:, 0:1] * ub + coef[:, 2:3]  # (k, w)
        cols = coef[:, 1:2] * vb.T  # (k, h)
        invs = [rows[i][None, :] + cols[i][:, None] for i in range(len(front))]
        if len(invs) == 1:
            layer_inv = invs[0]
        else:  # the farther plane is the entry point of a convex solid
            layer_inv = np.minimum(invs[0], invs[1])
            for f in invs[2:]:
                np.minimum(layer_inv, f, out=layer_inv)
        alpha = self._coverage(hull, x0, x1, y0, y1)
        zbuf = invz[y0:y1, x0:x1]
        zpass = layer_inv > zbuf  # the z-buffer is >= 0, so this also drops planes behind the camera
        if not zpass.any():
            return
        layer = np.empty(layer_inv.shape, np.uint8)
        # texture levels at the (near-clamped) face corners: λ = log2(range / (f · texel · cos θ))
        lam_lo, lam_hi, G = b_lo[gi], b_hi[gi], b_G[gi]
        Kc = self.canvas_K
        for i, f in enumerate(front):
            sel = zpass if len(front) == 1 else (zpass & (invs[i] == layer_inv))
            bx, by, bw, bh = cv2.boundingRect(sel.view(np.uint8))
            if bw == 0:
                continue
            fy0, fy1, fx0, fx1 = by, by + bh, bx, bx + bw
            sub_sel = sel[fy0:fy1, fx0:fx1]
            mips = s.mips[f]
            top = len(mips) - 1
            lo_l, hi_l = int(min(max(lam_lo[i], 0), top)), int(min(max(lam_hi[i], 0), top))
            if lo_l == hi_l:
                plan = [(lo_l, None)]
            else:
                # per-pixel level: λ = log2(q / (f s |dist|)) with q = |m|² Z²; level L where
                # λ rounds to L, i.e. q in [2^(L−½), 2^(L+½)) · f s |dist| / 2^bias
                iz = np.maximum(invs[i][fy0:fy1, fx0:fx1], _F32(1e-12))
                q = (ub[:, fx0:fx1] ** 2 + vb[fy0:fy1] ** 2 + _F32(1.0)) / (iz * iz)
                k = self._f_mean * s.texel[f] * abs(dist[i]) / 2.0**self.options.lod_bias
                plan = []
                for L in range(lo_l, hi_l + 1):
                    m = None
                    if L > lo_l:
                        m = q >= _F32(k * 2.0 ** (L - 0.5))
                    if L < hi_l:
                        m2 = q < _F32(k * 2.0 ** (L + 0.5))
                        m = m2 if m is None else (m & m2)
                    plan.append((L, m))
            for L, lmask in plan:
                if lmask is None:
                    msk = sub_sel
                    ly0, ly1, lx0, lx1 = 0, fy1 - fy0, 0, fx1 - fx0
                else:
                    msk = sub_sel & lmask
                    bx, by, bw, bh = cv2.boundingRect(msk.view(np.uint8))
                    if bw == 0:
                        continue
                    ly0, ly1, lx0, lx1 = by, by + bh, bx, bx + bw
                t = mips[L]
                th, tw = t.shape
                # texel (j, i) of this level ↦ O + (j + ½) E1/tw + (i + ½) E2/th ↦ ROI pixel
                Hm = Kc @ (G[i] * (1.0 / tw, 1.0 / th, 1.0))
                Hm[:, 2] += 0.5 * (Hm[:, 0] + Hm[:, 1])
                Hm[0] -= (x0 + fx0 + lx0) * Hm[2]
                Hm[1] -= (y0 + fy0 + ly0) * Hm[2]
                warped = cv2.warpPerspective(t, Hm, (int(lx1 - lx0), int(ly1 - ly0)), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                dst = layer[fy0 + ly0 : fy0 + ly1, fx0 + lx0 : fx0 + lx1]
                cv2.copyTo(warped, msk[ly0:ly1, lx0:lx1].view(np.uint8), dst)
        self._composite(img, invz, x0, x1, y0, y1, layer, layer_inv, alpha, zpass, s.ob.index)

    def _composite(self, img, invz, x0, x1, y0, y1, layer, layer_inv, alpha, zpass, index: int) -> None:
        """Write a solid's layer over the canvas: opaque inside, α-blended on its edge pixels;
        its 1/Z goes into the z-buffer where the pixel centre is inside (α ≥ ½)."""
        dst = img[y0:y1, x0:x1]
        zbuf = invz[y0:y1, x0:x1]
        # dst ← dst + α (layer − dst) where the solid is in front (α = 1 inside: a plain copy)
        d = dst.astype(_F32)
        blend = layer.astype(_F32)  # d + α (layer − d), in place
        blend -= d
        blend *= alpha
        blend += d
        blend = cv2.add(blend, 0.0, dtype=cv2.CV_8U)
        cv2.copyTo(blend, zpass.view(np.uint8), dst)
        zw = (zpass & (alpha >= 0.5)).view(np.uint8)
        cv2.copyTo(layer_inv, zw, zbuf)
        if self._ids is not None:
            cv2.copyTo(np.full(zw.shape, index + 2, _F32), zw, self._ids[y0:y1, x0:x1])

    def _draw_cylinder(self, s: _Solid, R, p, cam8, img, invz, uv8=None) -> None:
        ob = s.ob
        hull = self._hull(cam8, uv8)  # of the bounding square prism: bounds the silhouette
        if hull is None:
            return
        roi = self._roi(hull)
        if roi is None:
            return
        x0, x1, y0, y1 = roi
        near = self.options.near_m
        ub, vb = self._ub[:, x0:x1], self._vb[y0:y1]
        r = float(ob.radius)
        z_top, z_base = ob.z_top, ob.z_base
        on, oe, pD = p[0] - ob.centre[0], p[1] - ob.centre[1], p[2]
        C = on * on + oe * oe - r * r
        if C <= 0 and z_top <= pD <= z_base:
            return  # camera inside the solid
        f = self._f_mean
        dN = (_F32(R[0, 0]) * ub + _F32(R[0, 2])) + _F32(R[0, 1]) * vb
        dE = (_F32(R[1, 0]) * ub + _F32(R[1, 2])) + _F32(R[1, 1]) * vb
        dD = (_F32(R[2, 0]) * ub + _F32(R[2, 2])) + _F32(R[2, 1]) * vb
        cap_key = "top" if pD < z_top else ("bottom" if pD > z_base else None)
        # side: horizontal ray–circle; coverage from the ray's distance to the axis and the height
        # of the hit, in pixels ≈ metres · f / depth (exact sign: α ≥ ½ iff the centre ray hits)
        if C > 0:
            A = np.maximum(dN * dN + dE * dE, _F32(1e-12))
            Bh = _F32(on) * dN + _F32(oe) * dE
            tstar = -Bh / A
            perp2 = np.maximum(_F32(C + r * r) + Bh * tstar, _F32(0.0))  # squared ray–axis distance
            t_side = tstar - np.sqrt(np.maximum(_F32(r * r) - perp2, _F32(0.0)) / A)
            t_pos = np.maximum(t_side, _F32(near))
            scale = _F32(f) / t_pos
            z_side = _F32(pD) + t_side * dD
            a_side = np.minimum((_F32(r) - np.sqrt(perp2)) * scale, (z_side - _F32(z_top)) * scale)
            np.minimum(a_side, (_F32(z_base) - z_side) * scale, out=a_side)
            a_side += _F32(0.5)
            np.clip(a_side, 0.0, 1.0, out=a_side)
            a_side[t_side <= near] = 0.0
        else:
            a_side = np.zeros(dN.shape, _F32)
            t_side = z_side = None
        alpha, t_hit, use_cap = a_side, t_side, None
        if cap_key is not None:
            z_cap = z_top if cap_key == "top" else z_base
            with np.errstate(divide="ignore", invalid="ignore"):
                t_cap = _F32(z_cap - pD) / dD
            ok = t_cap > near  # false for NaN / rays away from the cap plane
            t_cap[~ok] = np.inf
            tc = np.where(ok, t_cap, _F32(0.0))
            cn = _F32(on) + tc * dN
            ce = _F32(oe) + tc * dE
            a_cap = (_F32(r) - np.sqrt(cn * cn + ce * ce)) * (_F32(f) / np.maximum(tc, _F32(near))) + _F32(0.5)
            np.clip(a_cap, 0.0, 1.0, out=a_cap)
            a_cap[~ok] = 0.0
            use_cap = a_cap > a_side
            alpha = np.maximum(a_side, a_cap)
            t_hit = t_cap if t_side is None else np.where(use_cap, t_cap, t_side)
        zbuf = invz[y0:y1, x0:x1]
        with np.errstate(divide="ignore"):
            inv = _F32(1.0) / np.maximum(t_hit, _F32(near))
        zpass = (alpha > 0) & (inv > zbuf)
        if not zpass.any():
            return
        layer = np.empty(inv.shape, np.uint8)
        side_m, top_m, bot_m = s.cyl
        covered = (zpass & (alpha >= 0.5)).view(np.uint8)
        zmean = cv2.mean(t_hit, mask=covered)[0] if covered.any() else cv2.mean(t_hit, mask=zpass.view(np.uint8))[0]
        lam = math.log2(max(zmean, 1e-6) / (f * s.cyl_texel)) + self.options.lod_bias
        side_sel = zpass if use_cap is None else (zpass & ~use_cap)
        bx, by, bw, bh = cv2.boundingRect(side_sel.view(np.uint8)) if t_side is not None else (0, 0, 0, 0)
        if bw > 0:
            L = min(max(round(lam), 0), len(side_m) - 1)
            t = side_m[L]
            th, tw = t.shape[0], t.shape[1] - 2
            b = (slice(by, by + bh), slice(bx, bx + bw))
            ts = t_side[b]
            theta = np.arctan2(_F32(oe) + ts * dE[b], _F32(on) + ts * dN[b])  # from north, clockwise
            mx = ((theta * _F32(1.0 / (2 * math.pi))) % _F32(1.0)) * _F32(tw) + _F32(0.5)  # +1 pad − ½
            my = (z_side[b] - _F32(z_top)) * _F32(th / (z_base - z_top)) - _F32(0.5)
            cv2.copyTo(cv2.remap(t, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), side_sel[b].view(np.uint8), layer[b])
        if use_cap is not None:
            cap_sel = zpass & use_cap
            if cap_sel.any():
                cap = top_m if cap_key == "top" else bot_m
                L = min(max(round(lam), 0), len(cap) - 1)
                t = cap[L]
                th, tw = t.shape
                mx = (ce + _F32(r)) * _F32(tw / (2 * r)) - _F32(0.5)
                my = (cn + _F32(r)) * _F32(th / (2 * r)) - _F32(0.5)
                cv2.copyTo(cv2.remap(t, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), cap_sel.view(np.uint8), layer)
        self._composite(img, invz, x0, x1, y0, y1, layer, inv, alpha, zpass, ob.index)
