"""World geometry: obstacles as solids, vectorized ray casting, clearances and horizontal ranges.

Frames (docs/derivations/frames.md): world = local NED (x north, y east, z down), metres.  Every obstacle is an
upright solid between ``z_top`` and ``z_base`` (NED, ``z_top < z_base``):

* boxes, walls and targets are *oriented boxes*: centre, yaw ψ of their first local axis
  ``a = (cos ψ, sin ψ, 0)``, second axis ``b = (−sin ψ, cos ψ, 0)``, third axis down, and half
  extents along (a, b, down).  A target is a box of zero thickness along ``a`` (its facing);
* cylinders: vertical axis through ``centre_ne``, radius ``r``.

This module is the independent reference the renderer is tested against: it intersects rays
with the solids analytically (slab test, ray–circle quadratic), without any rasterization.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from companion.errors import ConfigError, InputError

from .config import BoxConfig, CylinderConfig, TargetConfig, WallConfig, WorldConfig, load_world_config

#: ``RayHits.index`` of a ray that hits nothing (sky) within range.
SKY = -1
#: ``RayHits.index`` of a ray that hits the ground plane first.
GROUND = -2

_KIND_CODE = {"box": 1, "wall": 2, "cylinder": 3, "target": 4, "ground": 5}


@dataclass(frozen=True, eq=False)
class Obstacle:
    """One solid of the world.  ``label`` names it in errors: ``'tower' (box[1])``."""

    index: int  # position in World.obstacles
    kind: str  # "box" | "wall" | "cylinder" | "target"
    kind_index: int  # position in its TOML array ([[box]] number kind_index)
    name: str
    config: BoxConfig | CylinderConfig | WallConfig | TargetConfig
    centre: np.ndarray  # (3,) NED centre of the solid (vertical middle)
    yaw: float  # rad, direction of the first local axis (boxes/walls/targets)
    half: np.ndarray  # (3,) half extents along (a, b, down); cylinders: (r, r, half height)
    texture_seed: int

    @property
    def label(self) -> str:
        tag = f"{self.kind}[{self.kind_index}]"
        return f"{self.name!r} ({tag})" if self.name != tag else tag

    @property
    def is_cylinder(self) -> bool:
        return self.kind == "cylinder"

    @property
    def radius(self) -> float:
        return float(self.half[0])

    @property
    def z_top(self) -> float:
        return float(self.centre[2] - self.half[2])

    @property
    def z_base(self) -> float:
        return float(self.centre[2] + self.half[2])

    @property
    def axes(self) -> np.ndarray:
        """(3, 3) rows = local axes a, b, down in world NED."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])

    def faces(self) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Planar faces of a box/wall/target as ``(key, O, E1, E2, n_out)`` in world NED.

        ``O`` is the face's top-left corner as seen from outside, ``E1`` spans it left → right
        (texture columns), ``E2`` top → bottom (texture rows), ``n_out`` is the outward unit normal.
        A target has a single face ``"front"`` (normal = its facing); it is drawn from both sides.
        """
        if self.is_cylinder:
            raise ValueError("a cylinder has no planar faces")
        A, B, D = self.axes
        ha, hb, hd = self.half
        c = self.centre
        if self.kind == "target":
            return [("front", c + hb * B - hd * D, -2 * hb * B, 2 * hd * D, A)]
        return [
            ("a+", c + ha * A + hb * B - hd * D, -2 * hb * B, 2 * hd * D, A),
            ("a-", c - ha * A - hb * B - hd * D, 2 * hb * B, 2 * hd * D, -A),
            ("b+", c - ha * A + hb * B - hd * D, 2 * ha * A, 2 * hd * D, B),
            ("b-", c + ha * A - hb * B - hd * D, -2 * ha * A, 2 * hd * D, -B),
            ("top", c - ha * A - hb * B - hd * D, 2 * ha * A, 2 * hb * B, -D),
            ("bottom", c - ha * A - hb * B + hd * D, 2 * ha * A, 2 * hb * B, D),
        ]

    def corners(self) -> np.ndarray:
        """(8, 3) world corners of the oriented box (its bounding box for a cylinder).

        Order: index bits (i_a, i_b, i_d) → sign −/+ along a, b, down: corner k = (k>>2 & 1, k>>1 & 1, k & 1).
        """
        signs = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], float) * 2 - 1
        if self.is_cylinder:
            axes = np.eye(3)
        else:
            axes = self.axes
        return self.centre + (signs * self.half) @ axes


@dataclass(frozen=True)
class RayHits:
    """Result of :meth:`World.raycast`: ``distance`` along each ray in units of its direction
    vector (``inf`` where nothing is hit) and ``index``: obstacle index, :data:`GROUND` or :data:`SKY`."""

    distance: np.ndarray
    index: np.ndarray


def _texture_seed(world_seed: int, kind: str, i: int, own: int | None) -> int:
    if own is not None:
        return int(own)
    return int(np.random.SeedSequence([world_seed, _KIND_CODE[kind], i]).generate_state(1)[0])


class World:
    """A loaded world: ground plane, obstacles and the geometry queries used for truth.

    Build it with :func:`load_world` (a TOML file) or ``World(WorldConfig(...))``.
    """

    def __init__(self, config: WorldConfig, source: str = "") -> None:
        self.config = config
        self.source = source or config.name or "<world>"
        g = config.ground
        self.ground = g
        self.ground_z: float | None = g.z_ned if g.enabled else None
        base_default = g.altitude_m
        obs: list[Obstacle] = []

        def add(kind, k, cfg, centre_ne, base_alt, height, yaw, half_ab):
            base = base_default if base_alt is None else base_alt
            z_base = -float(base)
            z_top = z_base - float(height)
            centre = np.array([centre_ne[0], centre_ne[1], 0.5 * (z_top + z_base)], float)
            half = np.array([half_ab[0], half_ab[1], 0.5 * float(height)], float)
            name = cfg.name or f"{kind}[{k}]"
            seed = _texture_seed(config.seed, kind, k, cfg.seed)
            obs.append(Obstacle(len(obs), kind, k, name, cfg, centre, float(yaw), half, seed))

        for k, b in enumerate(config.box):
            add("box", k, b, b.centre_ne_m, b.base_altitude_m, b.height_m, math.radians(b.yaw_deg), (0.5 * b.size_m[0], 0.5 * b.size_m[1]))
        for k, w in enumerate(config.wall):
            dn, de = w.end_ne_m[0] - w.start_ne_m[0], w.end_ne_m[1] - w.start_ne_m[1]
            mid = (0.5 * (w.start_ne_m[0] + w.end_ne_m[0]), 0.5 * (w.start_ne_m[1] + w.end_ne_m[1]))
            add("wall", k, w, mid, w.base_altitude_m, w.height_m, math.atan2(de, dn), (0.5 * math.hypot(dn, de), 0.5 * w.thickness_m))
        for k, c in enumerate(config.cylinder):
            add("cylinder", k, c, c.centre_ne_m, c.base_altitude_m, c.height_m, 0.0, (c.radius_m, c.radius_m))
        for k, t in enumerate(config.target):
            p = t.position_ned_m
            centre = np.array(p, float)
            half = np.array([0.0, 0.5 * t.size_m, 0.5 * t.size_m])
            name = t.name or f"target[{k}]"
            seed = _texture_seed(config.seed, "target", k, t.seed)
            obs.append(Obstacle(len(obs), "target", k, name, t, centre, math.radians(t.facing_deg), half, seed))
        self.obstacles: tuple[Obstacle, ...] = tuple(obs)
        self._by_name = {o.name: o for o in obs}

        box_like = [o for o in obs if not o.is_cylinder]
        cyl = [o for o in obs if o.is_cylinder]
        self._box_idx = np.array([o.index for o in box_like], int)
        self._box_centre = np.array([o.centre for o in box_like], float).reshape(-1, 3)
        self._box_cs = np.array([[math.cos(o.yaw), math.sin(o.yaw)] for o in box_like], float).reshape(-1, 2)
        self._box_half = np.array([o.half for o in box_like], float).reshape(-1, 3)
        self._cyl_idx = np.array([o.index for o in cyl], int)
        self._cyl_centre = np.array([o.centre for o in cyl], float).reshape(-1, 3)
        self._cyl_r = np.array([o.radius for o in cyl], float)
        self._cyl_hz = np.array([o.half[2] for o in cyl], float)
        self._z_top = np.array([o.z_top for o in obs], float)
        self._z_base = np.array([o.z_base for o in obs], float)
        # the same numbers as Python floats, for clearance() (one point per physics step)
        self._box_rows = [(int(i), *c, *cs, *h) for i, c, cs, h in
                          zip(self._box_idx.tolist(), self._box_centre.tolist(), self._box_cs.tolist(), self._box_half.tolist())]
        self._cyl_rows = [(int(i), c[2], r, hz) for i, c, r, hz in
                          zip(self._cyl_idx.tolist(), self._cyl_centre.tolist(), self._cyl_r.tolist(), self._cyl_hz.tolist())]
        self._texture_cache = None

    # ------------------------------------------------------------------------------ lookup
    def __repr__(self) -> str:
        return f"World({self.source!r}, {len(self.obstacles)} obstacles, ground={'on' if self.ground_z is not None else 'off'})"

    @property
    def targets(self) -> tuple[Obstacle, ...]:
        return tuple(o for o in self.obstacles if o.kind == "target")

    def obstacle(self, name: str) -> Obstacle:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"{self.source}: no obstacle named {name!r}; known: {', '.join(sorted(self._by_name))}") from None

    # ------------------------------------------------------------------------------ ray casting
    def raycast(self, origins: np.ndarray, dirs: np.ndarray, max_range: float = np.inf, *, ground: bool = True) -> RayHits:
        """First hit of each ray ``origins + t·dirs`` (t > 0) with the ground and the obstacles.

        ``origins`` (N, 3) or (3,), ``dirs`` (N, 3) in world NED; ``dirs`` need not be unit
        vectors: ``distance`` is in units of t (pass camera rays with unit optical-axis component
        and ``distance`` is the depth along the optical axis).  A ray starting inside a solid hits
        it at t = 0.  Hits with t > ``max_range`` count as misses.
        """
        d = np.asarray(dirs, float).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(origins, float), d.shape)
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
            raise InputError("raycast: origins or dirs contain NaN or inf")
        n = len(d)
        best = np.full(n, np.inf)
        idx = np.full(n, SKY, int)
        if ground and self.ground_z is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (self.ground_z - o[:, 2]) / d[:, 2]
            ok = (d[:, 2] > 0) & (o[:, 2] < self.ground_z) & (t >= 0)
            best = np.where(ok, t, best)
            idx = np.where(ok, GROUND, idx)
        if len(self._box_idx):
            t = _ray_boxes(o, d, self._box_centre, self._box_cs, self._box_half)  # (N, Mb)
            j = np.argmin(t, axis=1)
            tj = t[np.arange(n), j]
            upd = tj < best
            best = np.where(upd, tj, best)
            idx = np.where(upd, self._box_idx[j], idx)
        if len(self._cyl_idx):
            t = _ray_cylinders(o, d, self._cyl_centre, self._cyl_r, self._cyl_hz)
            j = np.argmin(t, axis=1)
            tj = t[np.arange(n), j]
            upd = tj < best
            best = np.where(upd, tj, best)
            idx = np.where(upd, self._cyl_idx[j], idx)
        miss = best > max_range
        best[miss] = np.inf
        idx[miss] = SKY
        return RayHits(best, idx)

    # ------------------------------------------------------------------------------ clearance
    def signed_distances(self, p_ned: np.ndarray) -> np.ndarray:
        """(M,) Euclidean distance from the point to each obstacle's surface, negative inside."""
        p = np.asarray(p_ned, float).reshape(3)
        sd = np.empty(len(self.obstacles))
        if len(self._box_idx):
            rel = p - self._box_centre
            c, s = self._box_cs[:, 0], self._box_cs[:, 1]
            loc = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], 1)
            sd[self._box_idx] = _sdf(np.abs(loc) - self._box_half)
        if len(self._cyl_idx):
            rel = p - self._cyl_centre
            q = np.stack([np.hypot(rel[:, 0], rel[:, 1]) - self._cyl_r, np.abs(rel[:, 2]) - self._cyl_hz], 1)
            sd[self._cyl_idx] = _sdf(q)
        return sd

    def clearance(self, p_ned: np.ndarray) -> tuple[float, Obstacle | None]:
        """Distance from ``p_ned`` to the nearest obstacle surface (negative inside it) and that obstacle.

        :meth:`signed_distances` and its first minimum, computed on Python floats with the same
        operations in the same order (numpy's norm of a row sums left to right; hypot stays
        numpy's), so the numbers are bit for bit the same at a fraction of the cost — the
        simulator asks once per physics step (tests/test_flightsim_world.py compares the two)."""
        if not self.obstacles:
            return math.inf, None
        p0, p1, p2 = np.asarray(p_ned, float).reshape(3).tolist()
        sd = [0.0] * len(self.obstacles)
        for i, c0, c1, c2, co, si, h0, h1, h2 in self._box_rows:
            r0, r1 = p0 - c0, p1 - c1
            q0 = abs(co * r0 + si * r1) - h0
            q1 = abs(-si * r0 + co * r1) - h1
            q2 = abs(p2 - c2) - h2
            o0, o1, o2 = max(q0, 0.0), max(q1, 0.0), max(q2, 0.0)
            sd[i] = math.sqrt(o0 * o0 + o1 * o1 + o2 * o2) + min(max(q0, q1, q2), 0.0)
        if self._cyl_rows:
            radial = np.hypot(p0 - self._cyl_centre[:, 0], p1 - self._cyl_centre[:, 1]).tolist()  # numpy's hypot
            for (i, c2, r, hz), h in zip(self._cyl_rows, radial):
                q0 = h - r
                q1 = abs(p2 - c2) - hz
                o0, o1 = max(q0, 0.0), max(q1, 0.0)
                sd[i] = math.sqrt(o0 * o0 + o1 * o1) + min(max(q0, q1), 0.0)
        k = min(range(len(sd)), key=sd.__getitem__)  # the first minimum, as np.argmin
        return sd[k], self.obstacles[k]

    def check_start_clear(self, p_ned, min_clearance_m: float = 1.0, what: str = "start position") -> None:
        """Raise :class:`ConfigError` naming the obstacle if ``p_ned`` is inside one or nearer than
        ``min_clearance_m`` to it, or if it is below the ground plane (more than 0.5 m: a vehicle
        standing on its gear is fine)."""
        p = np.asarray(p_ned, float).reshape(3)
        if not np.all(np.isfinite(p)):
            raise ConfigError(f"{what} {tuple(p)} is not finite")
        ptxt = "(" + ", ".join(f"{x:.2f}" for x in p) + ")"
        if self.ground_z is not None and p[2] > self.ground_z + 0.5:
            raise ConfigError(f"{self.source}: {what} {ptxt} is {p[2] - self.ground_z:.2f} m below the ground plane (z = {self.ground_z:.2f})")
        sd = self.signed_distances(p) if self.obstacles else np.zeros(0)
        for k in np.argsort(sd):
            if sd[k] <= 0:
                raise ConfigError(f"{self.source}: {what} {ptxt} is inside obstacle {self.obstacles[k].label}")
            if sd[k] < min_clearance_m:
                raise ConfigError(
                    f"{self.source}: {what} {ptxt} is only {sd[k]:.2f} m from obstacle {self.obstacles[k].label}; "
                    f"at least {min_clearance_m:.2f} m needed"
                )
            break

    # ------------------------------------------------------------------------------ horizontal
    def in_band(self, z_ned: float, band_half_height_m: float | None) -> np.ndarray:
        """(M,) obstacles whose vertical extent overlaps [z − band, z + band] (all if band is None)."""
        if band_half_height_m is None:
            return np.ones(len(self.obstacles), bool)
        return (self._z_top <= z_ned + band_half_height_m) & (self._z_base >= z_ned - band_half_height_m)

    def horizontal_distances(self, p_ned, bearings_rad, band_half_height_m: float | None = None) -> np.ndarray:
        """(B, M) horizontal distance from ``p_ned`` to each obstacle along each world bearing.

        Bearings are clockwise from north (NED: direction (cos b, sin b)).  The obstacles' footprints
        are cast against horizontal rays from the point (its height ignored); ``inf`` where a ray
        misses, 0 if the point is inside the footprint.  With ``band_half_height_m`` only obstacles
        overlapping that vertical band around the point count (others are ``inf``).
        """
        p = np.asarray(p_ned, float).reshape(3)
        b = np.atleast_1d(np.asarray(bearings_rad, float))
        out = np.full((len(b), len(self.obstacles)), np.inf)
        if not self.obstacles:
            return out
        d = np.stack([np.cos(b), np.sin(b), np.zeros_like(b)], 1)
        o = np.broadcast_to(np.array([p[0], p[1], 0.0]), d.shape)
        if len(self._box_idx):
            c = self._box_centre.copy()
            c[:, 2] = 0.0
            h = self._box_half.copy()
            h[:, 2] = 1.0
            out[:, self._box_idx] = _ray_boxes(o, d, c, self._box_cs, h)
        if len(self._cyl_idx):
            c = self._cyl_centre.copy()
            c[:, 2] = 0.0
            out[:, self._cyl_idx] = _ray_cylinders(o, d, c, self._cyl_r, np.ones(len(self._cyl_r)))
        out[:, ~self.in_band(p[2], band_half_height_m)] = np.inf
        return out

    def closest_horizontal(self, p_ned, band_half_height_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(M,) horizontal distance from the point to each footprint and the bearing (rad, from
        north, clockwise) of the footprint's closest point; ``inf``/NaN for obstacles out of the band."""
        p = np.asarray(p_ned, float).reshape(3)
        m = len(self.obstacles)
        dist = np.full(m, np.inf)
        bear = np.full(m, np.nan)
        if len(self._box_idx):
            rel = p[:2] - self._box_centre[:, :2]
            c, s = self._box_cs[:, 0], self._box_cs[:, 1]
            la, lb = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
            qa = np.clip(la, -self._box_half[:, 0], self._box_half[:, 0])
            qb = np.clip(lb, -self._box_half[:, 1], self._box_half[:, 1])
            cn = self._box_centre[:, 0] + c * qa - s * qb  # closest point, world NE
            ce = self._box_centre[:, 1] + s * qa + c * qb
            dist[self._box_idx] = np.hypot(cn - p[0], ce - p[1])
            bear[self._box_idx] = np.arctan2(ce - p[1], cn - p[0])
        if len(self._cyl_idx):
            dn, de = self._cyl_centre[:, 0] - p[0], self._cyl_centre[:, 1] - p[1]
            dist[self._cyl_idx] = np.maximum(np.hypot(dn, de) - self._cyl_r, 0.0)
            bear[self._cyl_idx] = np.arctan2(de, dn)
        out = ~self.in_band(p[2], band_half_height_m)
        dist[out] = np.inf
        bear[out] = np.nan
        return dist, bear

    # ------------------------------------------------------------------------------ textures
    def textures(self):
        """Procedural textures of this world (built once, then cached in memory and on disk; see :mod:`.textures`)."""
        if self._texture_cache is None:
            from .textures import cached_world_textures

            self._texture_cache = cached_world_textures(self)
        return self._texture_cache


def _sdf(q: np.ndarray) -> np.ndarray:
    """Signed distance from per-axis excess ``q = |local| − half`` (rows)."""
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(np.max(q, axis=1), 0.0)
    return outside + inside


def _ray_boxes(o: np.ndarray, d: np.ndarray, centre: np.ndarray, cs: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(N, M) entry distance of N rays into M oriented upright boxes (slab test); inf on a miss."""
    rel = o[:, None, :] - centre[None, :, :]  # (N, M, 3)
    c, s = cs[None, :, 0], cs[None, :, 1]
    lo = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)
    ld = np.stack([c * d[:, None, 0] + s * d[:, None, 1], -s * d[:, None, 0] + c * d[:, None, 1], np.broadcast_to(d[:, None, 2], (len(d), len(centre)))], -1)
    h = half[None, :, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-h - lo) / ld
        t2 = (h - lo) / ld
    par = ld == 0.0
    inside_slab = np.abs(lo) <= h
    tmin = np.where(par, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    tmax = np.where(par, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    t_enter = np.max(tmin, axis=-1)
    t_exit = np.min(tmax, axis=-1)
    hit = (t_enter <= t_exit) & (t_exit >= 0)
    return np.where(hit, np.maximum(t_enter, 0.0), np.inf)


def _ray_cylinders(o: np.ndarray, d: np.ndarray, centre: np.ndarray, r: np.ndarray, hz: np.ndarray) -> np.ndarray:
    """(N, M) entry distance of N rays into M vertical cylinders (centre = middle of the axis)."""
    on = o[:, None, 0] - centre[None, :, 0]
    oe = o[:, None, 1] - centre[None, :, 1]
    od = o[:, None, 2] - centre[None, :, 2]
    dn, de, dd = d[:, None, 0], d[:, None, 1], d[:, None, 2]
    a = dn * dn + de * de
    bh = on * dn + oe * de
    cc = on * on + oe * oe - r[None, :] ** 2
    disc = bh * bh - a * cc
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        r1 = (-bh - sq) / a
        r2 = (-bh + sq) / a
        z1 = (-hz[None, :] - od) / dd
        z2 = (hz[None, :] - od) / dd
    vert = a == 0.0  # ray parallel to the axis: inside the circle for all t, or never
    r1 = np.where(vert, np.where(cc <= 0, -np.inf, np.inf), np.where(disc >= 0, r1, np.inf))
    r2 = np.where(vert, np.where(cc <= 0, np.inf, -np.inf), np.where(disc >= 0, r2, -np.inf))
    flat = dd == 0.0
    in_z = np.abs(od) <= hz[None, :]
    zmin = np.where(flat, np.where(in_z, -np.inf, np.inf), np.minimum(z1, z2))
    zmax = np.where(flat, np.where(in_z, np.inf, -np.inf), np.maximum(z1, z2))
    t_enter = np.maximum(r1, zmin)
    t_exit = np.minimum(r2, zmax)
    hit = (t_enter <= t_exit) & (t_exit >= 0)
    return np.where(hit, np.maximum(t_enter, 0.0), np.inf)


def load_world(path: str | os.PathLike) -> World:
    """Load and validate a world TOML (``configs/worlds/*.toml``)."""
    return World(load_world_config(path), source=str(path))
