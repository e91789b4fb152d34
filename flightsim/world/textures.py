"""Seeded procedural textures, rich in corners, with box-filtered mip pyramids.

Every texture is a deterministic function of its seed (``numpy.random.default_rng``):

* ``blocks`` — a multi-scale mosaic: two irregular grids of random grey cells (cell sizes drawn at
  random, so nothing repeats at a fixed period) under a layer of painted rectangles whose sizes
  spread log-uniformly from half a metre to half the face.  T-junctions and crossings give Harris
  corners at every viewing distance, and no two patches look alike, so NCC has one clear peak;
* ``facade`` — a building face: low-contrast ``blocks`` plaster with floors of windows whose size,
  spacing and position are jittered and whose glass, blinds, frames and mullions get their own
  random greys (window rows are regular as on real buildings, but no two windows match);
* ``fields`` — the ground tile: fields and plots (large rectangles), finer mosaic inside them,
  tracks and bushes; it wraps seamlessly (the ground is an infinite repetition of this tile,
  so its period is ``tile_px × texel_m``, 205 m by default);
* ``checker`` — a target's checker with random dark and light greys;
* ``plain`` — a uniform grey, only when a world asks for a texture-less face.

Feature sizes are in metres (converted with the texel size), so a texture looks the same at any
resolution.  Mip level k halves level k−1 with a 2×2 box filter (``cv2.INTER_AREA``).

Building a world's textures takes seconds (the ground tile most); every flight of a campaign uses
the same world, so :func:`cached_world_textures` keeps them on disk, keyed by the world's
configuration and this module's source (``$FLIGHTSIM_TEXTURE_CACHE``, default
``$XDG_CACHE_HOME/monorange/textures`` or ``~/.cache/monorange/textures``; ``off`` disables it).
A cached world is exactly the one :func:`build_world_textures` would build.
"""

from __future__ import annotations

import hashlib
import math
import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .config import MAX_TEXTURE_PX

#: Grey levels used by textures stay within this range (headroom for exposure changes).
GREY_MIN, GREY_MAX = 12.0, 243.0
#: Pixels per checker cell of a target texture at level 0.
CHECKER_CELL_PX = 32


def build_mips(tex: np.ndarray) -> list[np.ndarray]:
    """Box-filtered mip pyramid down to 1×1 (level 0 = ``tex``), all uint8 and C-contiguous."""
    levels = [np.ascontiguousarray(tex, dtype=np.uint8)]
    while levels[-1].shape[0] > 1 or levels[-1].shape[1] > 1:
        h, w = levels[-1].shape
        levels.append(cv2.resize(levels[-1], (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA))
    return levels


def texel_for(extent_m: tuple[float, ...], texel_m: float) -> float:
    """Texel size giving at most :data:`MAX_TEXTURE_PX` texels along the longest extent."""
    return max(texel_m, max(extent_m) / MAX_TEXTURE_PX)


def _dims(extent_m: float, texel_m: float) -> int:
    return max(2, int(math.ceil(extent_m / texel_m - 1e-9)))


def _irregular_grid(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    """(h, w) float32 of random values on a grid whose rows and columns have random widths
    (mean ``cell`` texels); periodic in both directions (a cell straddles the seam)."""
    out = []
    for n in (h, w):
        k = max(1, int(round(n / max(cell, 1.0))))
        bounds = np.sort(rng.choice(n, size=min(k, n), replace=False)) if k > 1 else np.array([0])
        idx = (np.searchsorted(bounds, np.arange(n), side="right") - 1) % len(bounds)
        out.append((idx, len(bounds)))
    (ri, nr), (ci, nc) = out
    vals = rng.random((nr, nc), dtype=np.float32)
    return vals[ri][:, ci]


def _rect(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, value: float, wrap: bool) -> None:
    """Fill [x0, x1) × [y0, y1) (clipped, or wrapped around the edges when ``wrap``)."""
    h, w = img.shape
    if not wrap:
        img[max(y0, 0) : max(min(y1, h), 0), max(x0, 0) : max(min(x1, w), 0)] = value
        return
    for oy in (-h, 0, h):
        for ox in (-w, 0, w):
            ya, yb, xa, xb = y0 + oy, y1 + oy, x0 + ox, x1 + ox
            if yb <= 0 or ya >= h or xb <= 0 or xa >= w:
                continue
            img[max(ya, 0) : min(yb, h), max(xa, 0) : min(xb, w)] = value


def _paint_rects(rng, img, texel_m, min_m, max_m, coverage, wrap, value_fn, max_count=6000, aspect=3.0) -> None:
    h, w = img.shape
    max_m = max(max_m, min_m * 1.01)
    area_m2 = h * w * texel_m * texel_m
    lo, hi = math.log(min_m), math.log(max_m)
    # mean area of a log-uniform size: E[s^2] = (max^2 - min^2) / (2 (ln max - ln min))
    mean_area = (max_m**2 - min_m**2) / (2.0 * (hi - lo))
    n = int(min(max_count, max(4, coverage * area_m2 / mean_area)))
    size = np.exp(rng.uniform(lo, hi, n)) / texel_m
    ar = np.exp(rng.uniform(-math.log(aspect), math.log(aspect), n))
    sw = np.maximum(1, np.round(size * np.sqrt(ar))).astype(int)
    sh = np.maximum(1, np.round(size / np.sqrt(ar))).astype(int)
    x0 = rng.integers(-sw + 1 if not wrap else 0, w, n) if n else np.zeros(0, int)
    y0 = rng.integers(-sh + 1 if not wrap else 0, h, n) if n else np.zeros(0, int)
    vals = value_fn(n)
    order = np.argsort(-size)  # big ones first, small ones on top
    for k in order:
        _rect(img, int(x0[k]), int(y0[k]), int(x0[k] + sw[k]), int(y0[k] + sh[k]), float(vals[k]), wrap)


def _moments(x: np.ndarray) -> tuple[float, float]:
    """Mean and standard deviation of ``x`` that do not depend on where the array sits in memory.

    numpy's float sums are pairwise with SIMD blocks whose split follows the data's alignment, so
    the same values at another address can differ in the last bit, and a texture built from
    them would change with whatever the process allocated before (a seed would not fix the
    world).  Here the values are quantized to 2⁻¹⁶ of their largest magnitude and summed as
    integers, which is exact in any order; the moments are good to ~1e-5 relative, which only
    scales the grey levels.
    """
    v = np.asarray(x, np.float64).ravel()
    if v.size == 0:
        return 0.0, 0.0
    m = float(np.max(np.abs(v)))
    if not m > 0:
        return 0.0, 0.0
    q = np.rint(v * (65536.0 / m)).astype(np.int64)  # |q| ≤ 2¹⁶: q² sums stay far below 2⁶³
    n = v.size
    s1, s2 = int(q.sum()), int((q * q).sum())
    mean_q = s1 / n
    var_q = max(s2 / n - mean_q * mean_q, 0.0)
    scale = m / 65536.0
    return mean_q * scale, math.sqrt(var_q) * scale


def _to_grey(x: np.ndarray, mean: float, contrast: float, std: float = 48.0) -> np.ndarray:
    mu, s = _moments(x)
    y = mean + contrast * std * (x - mu) / (s if s > 1e-6 else 1.0)
    return np.clip(np.rint(y), GREY_MIN, GREY_MAX).astype(np.uint8)


def blocks_texture(rng, h: int, w: int, texel_m: float, *, mean: float = 128.0, contrast: float = 1.0, wrap: bool = False) -> np.ndarray:
    """Multi-scale random mosaic (see module doc), uint8 (h, w)."""
    fine = _irregular_grid(rng, h, w, max(2.0, 0.3 / texel_m))
    mid = _irregular_grid(rng, h, w, max(3.0, 1.2 / texel_m))
    paint = _irregular_grid(rng, h, w, max(4.0, 5.0 / texel_m))
    ext = min(h, w) * texel_m
    _paint_rects(rng, paint, texel_m, 0.5, max(1.0, 0.5 * ext), 1.2, wrap, lambda n: rng.random(n))
    x = 0.55 * paint + 0.28 * mid + 0.17 * fine
    return _to_grey(x, mean, contrast)


def facade_texture(rng, h: int, w: int, texel_m: float, *, contrast: float = 1.0) -> np.ndarray:
    """Building face with jittered floors of windows over a plaster mosaic, uint8 (h, w)."""
    plaster_mean = rng.uniform(95.0, 175.0)
    img = blocks_texture(rng, h, w, texel_m, mean=plaster_mean, contrast=0.45 * contrast).astype(np.float32)
    floor_h = rng.uniform(2.9, 3.8)
    bay_w = rng.uniform(2.3, 4.2)
    win_w = bay_w * rng.uniform(0.35, 0.65)
    win_h = floor_h * rng.uniform(0.38, 0.6)
    H_m, W_m = h * texel_m, w * texel_m
    n_floors = int(H_m // floor_h)
    n_bays = int(W_m // bay_w)
    if n_floors < 1 or n_bays < 1:
        mu, sd = _moments(img)
        return _to_grey(img, mu, 1.0, std=sd + 1e-3)
    x_margin = 0.5 * (W_m - n_bays * bay_w)
    t = lambda m: int(round(m / texel_m))  # noqa: E731 - metres to texels
    c = contrast
    for j in range(n_floors):
        top = j * floor_h + 0.5 * (floor_h - win_h) + rng.uniform(-0.08, 0.08)
        for i in range(n_bays):
            if rng.random() < 0.07:
                continue  # a blind spot: a missing window
            left = x_margin + i * bay_w + 0.5 * (bay_w - win_w) + rng.uniform(-0.12, 0.12)
            ww = win_w * rng.uniform(0.92, 1.08)
            wh = win_h * rng.uniform(0.95, 1.05)
            x0, y0, x1, y1 = t(left), t(top), t(left + ww), t(top + wh)
            frame = float(np.clip(plaster_mean + c * rng.choice([-1, 1]) * rng.uniform(30, 70), GREY_MIN, GREY_MAX))
            glass = rng.uniform(25, 95) if rng.random() < 0.75 else rng.uniform(150, 230)
            f = max(1, t(0.08))
            _rect(img, x0 - f, y0 - f, x1 + f, y1 + f, frame, False)
            _rect(img, x0, y0, x1, y1, plaster_mean + c * (glass - plaster_mean), False)
            if rng.random() < 0.3:  # blind pulled part-way down
                _rect(img, x0, y0, x1, y0 + t(wh * rng.uniform(0.2, 0.7)), plaster_mean + c * (rng.uniform(120, 220) - plaster_mean), False)
            if rng.random() < 0.4:  # mullion
                xm = t(left + ww * rng.uniform(0.4, 0.6))
                _rect(img, xm - max(1, f // 2), y0, xm + max(1, f // 2) + 1, y1, frame, False)
    return np.clip(np.rint(img), GREY_MIN, GREY_MAX).astype(np.uint8)


def fields_texture(rng, n: int, texel_m: float, *, mean: float = 110.0, contrast: float = 1.0) -> np.ndarray:
    """Seamless ground tile (n × n): fields, plots, mosaic, tracks and bushes."""
    fine = _irregular_grid(rng, n, n, max(2.0, 0.4 / texel_m))
    mid = _irregular_grid(rng, n, n, max(3.0, 2.0 / texel_m))
    fields = _irregular_grid(rng, n, n, max(4.0, 25.0 / texel_m))
    ext = n * texel_m
    _paint_rects(rng, fields, texel_m, 2.0, max(4.0, 0.25 * ext), 1.0, True, lambda k: rng.random(k), aspect=4.0)
    x = 0.55 * fields + 0.27 * mid + 0.18 * fine
    # tracks: long thin light strips; bushes: small dark squares in clumps
    for _ in range(max(1, int(ext / 60))):
        wdt = max(1, int(round(rng.uniform(1.5, 4.0) / texel_m)))
        pos = int(rng.integers(0, n))
        v = rng.uniform(0.8, 1.1)
        if rng.random() < 0.5:
            _rect(x, 0, pos, n, pos + wdt, v, True)
        else:
            _rect(x, pos, 0, pos + wdt, n, v, True)
    n_bush = int(min(3000, (ext / 9.0) ** 2))
    for _ in range(n_bush):
        s = max(1, int(round(rng.uniform(0.8, 4.0) / texel_m)))
        s2 = max(1, int(round(s * rng.uniform(0.6, 1.6))))
        cx, cy = int(rng.integers(0, n)), int(rng.integers(0, n))
        _rect(x, cx, cy, cx + s, cy + s2, rng.uniform(-0.1, 0.45), True)
    return _to_grey(x, mean, contrast, std=42.0)


def checker_texture(rng, cells: int) -> np.ndarray:
    """``cells`` × ``cells`` checker of random dark/light greys, :data:`CHECKER_CELL_PX` per cell."""
    dark = rng.uniform(15, 75, (cells, cells))
    light = rng.uniform(175, 240, (cells, cells))
    ii, jj = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    vals = np.where((ii + jj) % 2 == 0, dark, light).astype(np.float32)
    return np.rint(np.kron(vals, np.ones((CHECKER_CELL_PX, CHECKER_CELL_PX), np.float32))).astype(np.uint8)


def plain_texture(grey: float) -> np.ndarray:
    return np.full((2, 2), int(round(grey)), np.uint8)


@dataclass
class WorldTextures:
    """Mip pyramids of every surface. ``faces[(obstacle_index, key)]``; keys are the box face keys
    of :meth:`Obstacle.faces`, or ``"side"``, ``"top"``, ``"bottom"`` for cylinders.  Every level of
    a cylinder side texture carries one extra column on each side (a copy of the opposite edge), so
    sampling across the seam at north wraps around the circumference without wrapping vertically."""

    ground: list[np.ndarray] | None
    ground_texel_m: float
    faces: dict[tuple[int, str], list[np.ndarray]] = field(default_factory=dict)
    #: render-time cache: ground levels repeated for fast warping (filled by the renderer)
    _tiled: list | None = None


def _face_texture(rng, obstacle, h: int, w: int, texel: float, key: str, wrap: bool = False) -> np.ndarray:
    cfg = obstacle.config
    if cfg.texture == "plain":
        return plain_texture(cfg.grey)
    if cfg.texture == "facade" and key in ("a+", "a-", "b+", "b-"):
        return facade_texture(rng, h, w, texel, contrast=cfg.contrast)
    return blocks_texture(rng, h, w, texel, mean=rng.uniform(90, 165), contrast=cfg.contrast, wrap=wrap)


def build_world_textures(world) -> WorldTextures:
    """Generate every texture of ``world`` from its seeds (deterministic)."""
    g = world.ground
    ground = None
    if world.ground_z is not None:
        gseed = g.seed if g.seed is not None else int(np.random.SeedSequence([world.config.seed, 5, 0]).generate_state(1)[0])
        rng = np.random.default_rng(gseed)
        if g.texture == "plain":
            tile = np.full((g.tile_px, g.tile_px), int(round(g.mean_grey)), np.uint8)
        elif g.texture == "blocks":
            tile = blocks_texture(rng, g.tile_px, g.tile_px, g.texel_m, mean=g.mean_grey, contrast=g.contrast, wrap=True)
        else:
            tile = fields_texture(rng, g.tile_px, g.texel_m, mean=g.mean_grey, contrast=g.contrast)
        ground = build_mips(tile)
    out = WorldTextures(ground, g.texel_m)
    base_texel = world.config.texel_m
    for ob in world.obstacles:
        rng = np.random.default_rng(ob.texture_seed)
        if ob.kind == "target":
            out.faces[(ob.index, "front")] = build_mips(checker_texture(rng, ob.config.cells))
            continue
        if ob.is_cylinder:
            r, height = ob.radius, 2 * ob.half[2]
            circ = 2 * math.pi * r
            texel = texel_for((circ, height, 2 * r), base_texel)
            w, h = _dims(circ, texel), _dims(height, texel)
            side = _face_texture(rng, ob, h, w, texel, "side", wrap=True)
            out.faces[(ob.index, "side")] = [np.ascontiguousarray(np.concatenate([m[:, -1:], m, m[:, :1]], 1)) for m in build_mips(side)]
            n = _dims(2 * r, texel)
            for key in ("top", "bottom"):
                out.faces[(ob.index, key)] = build_mips(_face_texture(rng, ob, n, n, texel, key))
            continue
        for key, _o, e1, e2, _n in ob.faces():
            l1, l2 = float(np.linalg.norm(e1)), float(np.linalg.norm(e2))
            texel = texel_for((l1, l2), base_texel)
            out.faces[(ob.index, key)] = build_mips(_face_texture(rng, ob, _dims(l2, texel), _dims(l1, texel), texel, key))
    return out


#: environment variable naming the texture cache directory ("off": no disk cache)
CACHE_ENV = "FLIGHTSIM_TEXTURE_CACHE"


def texture_cache_dir() -> Path | None:
    """Where world textures are cached (None: disabled)."""
    v = os.environ.get(CACHE_ENV, "").strip()
    if v.lower() == "off":
        return None
    if v:
        return Path(v)
    base = os.environ.get("XDG_CACHE_HOME", "").strip() or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "monorange" / "textures"


def texture_cache_key(world) -> str:
    """Digest of everything the textures depend on: the world configuration and this module's code."""
    h = hashlib.sha256()
    h.update(repr(world.config).encode())
    h.update(str(MAX_TEXTURE_PX).encode())
    h.update(Path(__file__).read_bytes())
    return h.hexdigest()[:32]


def _flatten(tex: WorldTextures) -> dict[str, np.ndarray]:
    arrays = {}
    for k, lv in enumerate(tex.ground or []):
        arrays[f"ground/{k}"] = lv
    for (index, key), levels in tex.faces.items():
        for k, lv in enumerate(levels):
            arrays[f"face/{index}/{key}/{k}"] = lv
    return arrays


def _unflatten(arrays, ground_texel_m: float) -> WorldTextures:
    ground: dict[int, np.ndarray] = {}
    faces: dict[tuple[int, str], dict[int, np.ndarray]] = {}
    for name in arrays.files:
        parts = name.split("/")
        if parts[0] == "ground":
            ground[int(parts[1])] = arrays[name]
        else:
            faces.setdefault((int(parts[1]), parts[2]), {})[int(parts[3])] = arrays[name]
    out = WorldTextures([ground[k] for k in sorted(ground)] or None, ground_texel_m)
    out.faces = {fk: [lv[k] for k in sorted(lv)] for fk, lv in faces.items()}
    return out


def cached_world_textures(world) -> WorldTextures:
    """:func:`build_world_textures`, read from the disk cache when this world was built before (and
    written there otherwise; atomically, so parallel flights never read half a file).  A cache that
    cannot be read or written is ignored: the textures are built."""
    d = texture_cache_dir()
    if d is None:
        return build_world_textures(world)
    path = d / f"{texture_cache_key(world)}.npz"
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as arrays:
                return _unflatten(arrays, world.ground.texel_m)
        except Exception:  # a damaged file: rebuild and replace it
            pass
    tex = build_world_textures(world)
    try:
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".{path.stem}.{uuid.uuid4().hex}.npz"
        np.savez(tmp, **_flatten(tex))
        os.replace(tmp, path)
    except OSError:
        pass
    return tex
