"""Compiled kernels of the local obstacle map (docs/derivations/obstacle_map.md, docs/derivations/compute.md).

Each step of the map as one loop over landmarks, used when :data:`companion.core.jit.ENABLED`: the
methods of :class:`companion.core.obstacle_map.ObstacleMap` and the functions of
:mod:`companion.core.obstacle_map_landmarks` dispatch here, and their numpy bodies are the reference
(tests/test_obstacle_map_kernel.py compares the two).  The kernels evaluate the reference's
expressions in the same order, so the decisions (entry, merge, found, seen through, retention,
support) are the reference's: the support test even repeats its float32 expansion
|q|² + |p|² − 2 q·p, rounded as BLAS rounds it.  Where the reference multiplies through BLAS or
LAPACK the numbers agree to rounding: the camera frame and the depth σ (a fixed order of summation
here), the fused covariance of a merge (Gauss–Jordan here, LAPACK there: relative differences
~ cond · 1e-16) and positive definiteness (the pivots of a Cholesky factorization here, the smallest
eigenvalue there: they can disagree only for a covariance singular to working precision).
"""

from __future__ import annotations

import math

import numpy as np

from companion.core import jit as _jit


@_jit.njit
def _consistent_for_entry_k(nis, converged, ratio, min_count):
    """:func:`consistent_for_entry_reference`: the same median of the converged finite NIS."""
    n = nis.size
    ok = np.ones(n, np.bool_)
    ref = np.empty(n)
    m = 0
    for i in range(n):
        if converged[i] and math.isfinite(nis[i]):
            ref[m] = nis[i]
            m += 1
    if ratio <= 0 or m < min_count:
        return ok
    lim = ratio * np.median(ref[:m])
    for i in range(n):
        ok[i] = nis[i] <= lim
    return ok


@_jit.njit
def _landmark_covariance_k(p, p_cam, range_sigma, bearing_sigma):
    """:func:`landmark_covariance_reference`: σ_r² u uᵀ + (r σ_b)² (I − u uᵀ) per landmark."""
    n = p.shape[0]
    P = np.empty((n, 3, 3))
    u = np.empty(3)
    for k in range(n):
        d0, d1, d2 = p[k, 0] - p_cam[0], p[k, 1] - p_cam[1], p[k, 2] - p_cam[2]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        rs = max(r, 1e-9)
        u[0], u[1], u[2] = d0 / rs, d1 / rs, d2 / rs
        s_r2 = range_sigma[k] * range_sigma[k]
        s_t = r * bearing_sigma
        s_t2 = s_t * s_t
        for i in range(3):
            for j in range(3):
                uu = u[i] * u[j]
                P[k, i, j] = s_r2 * uu + s_t2 * ((1.0 if i == j else 0.0) - uu)
    return P


@_jit.njit
def _points_on_current_rays_k(out_ids, out_p, out_range, track_ids, rays_cam, R_world_cam, p_world_cam):
    """:func:`points_on_current_rays_reference`: landmarks seen now at their range along the current ray."""
    p = out_p.copy()
    nt = track_ids.size
    if out_ids.size == 0 or nt == 0:
        return p
    pos = np.searchsorted(track_ids, out_ids)
    for k in range(out_ids.size):
        j = min(pos[k], nt - 1)
        if track_ids[j] != out_ids[k]:
            continue
        for i in range(3):
            d = rays_cam[j, 0] * R_world_cam[i, 0] + rays_cam[j, 1] * R_world_cam[i, 1] + rays_cam[j, 2] * R_world_cam[i, 2]
            p[k, i] = p_world_cam[i] + d * out_range[k]
    return p


@_jit.njit
def _entry_checks_k(p, P):
    """The checks of :meth:`ObstacleMap.observe`: finite, symmetric (1e-9 relative) and positive definite (the pivots of
    the Cholesky factorization of (P + Pᵀ)/2 are positive ⇔ its eigenvalues are)."""
    m = p.shape[0]
    ok = np.zeros(m, np.bool_)
    n_bad = 0
    n_not_pd = 0
    A = np.empty((3, 3))
    for k in range(m):
        finite = True
        for i in range(3):
            finite = finite and math.isfinite(p[k, i])
            for j in range(3):
                finite = finite and math.isfinite(P[k, i, j])
        if not finite:
            n_bad += 1
            continue
        sym = True
        for i in range(3):
            for j in range(3):
                sym = sym and abs(P[k, i, j] - P[k, j, i]) <= 1e-9 * (1.0 + abs(P[k, i, j]))
                A[i, j] = 0.5 * (P[k, i, j] + P[k, j, i])
        d0 = A[0, 0]
        pd = d0 > 0
        if pd:
            l10, l20 = A[1, 0] / d0, A[2, 0] / d0
            d1 = A[1, 1] - l10 * A[1, 0]
            pd = d1 > 0
            if pd:
                l21 = (A[2, 1] - l20 * A[1, 0]) / d1
                d2 = A[2, 2] - l20 * A[2, 0] - l21 * l21 * d1
                pd = d2 > 0
        if sym and pd:
            ok[k] = True
        else:
            n_not_pd += 1
    return ok, n_bad, n_not_pd


@_jit.njit
def _inv3(A):
    """Inverse of a 3×3 matrix by Gauss–Jordan elimination with partial pivoting (as LAPACK's LU)."""
    M = A.copy()
    X = np.eye(3)
    for c in range(3):
        piv = c
        for r in range(c + 1, 3):
            if abs(M[r, c]) > abs(M[piv, c]):
                piv = r
        if piv != c:
            for j in range(3):
                M[c, j], M[piv, j] = M[piv, j], M[c, j]
                X[c, j], X[piv, j] = X[piv, j], X[c, j]
        for r in range(3):
            if r == c:
                continue
            f = M[r, c] / M[c, c]
            for j in range(3):
                M[r, j] -= f * M[c, j]
                X[r, j] -= f * X[c, j]
    for r in range(3):
        for j in range(3):
            X[r, j] /= M[r, r]
    return X


@_jit.njit
def _drift_pos_k(dt, drift_mps, drift_max):
    """σ of the position drift after ``dt`` s since a point was last observed (§ Drift;
    :meth:`ObstacleMap._drift`)."""
    return min(drift_mps * dt, drift_max)


@_jit.njit
def _merge_pairs_k(p, P, cand, map_p, map_P, map_t, rem, t, gate_k2, drift_mps, drift_max):
    """The pairs of :meth:`ObstacleMap._merge`: each new landmark ``cand`` nearest a remembered row
    ``rem`` within gate_k² (var_new + var_rem) (var = tr P / 3, the remembered one grown by σ_drift² =
    min(drift_mps · age, drift_max)²); one new landmark per remembered point (the first), pairs in
    ascending row.  Each pair's new point: the information-form fusion with P_rem + σ_drift² I when the
    two agree (dᵀ S⁻¹ d ≤ gate_k², S the sum of the two covariances), else the new estimate (``fused``
    False: two estimates that disagree are not averaged)."""
    nc, nr = cand.size, rem.size
    var_rem = np.empty(nr)
    s2 = np.zeros(map_p.shape[0])  # σ_drift² of each remembered row, for the gate and the fusion
    for r in range(nr):
        q = rem[r]
        s = _drift_pos_k(max(t - map_t[q], 0.0), drift_mps, drift_max)
        s2[q] = s * s
        var_rem[r] = (map_P[q, 0, 0] + map_P[q, 1, 1] + map_P[q, 2, 2]) / 3.0 + s2[q]
    taken = np.full(map_p.shape[0], -1, np.int64)  # remembered row -> first new landmark that landed on it
    for c in range(nc):
        i = cand[c]
        var_new = (P[i, 0, 0] + P[i, 1, 1] + P[i, 2, 2]) / 3.0
        best, best_d2 = -1, np.inf
        for r in range(nr):
            q = rem[r]
            dx, dy, dz = p[i, 0] - map_p[q, 0], p[i, 1] - map_p[q, 1], p[i, 2] - map_p[q, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 <= gate_k2 * (var_new + var_rem[r]) and d2 < best_d2:
                best, best_d2 = q, d2
        if best >= 0 and taken[best] < 0:
            taken[best] = i
    rj = np.flatnonzero(taken >= 0)
    ci = taken[rj]
    n = rj.size
    p_f = np.empty((n, 3))
    P_f = np.empty((n, 3, 3))
    fused = np.zeros(n, np.bool_)
    for k in range(n):
        P_old = map_P[rj[k]].copy()
        for a in range(3):
            P_old[a, a] += s2[rj[k]]
        d = np.empty(3)
        for a in range(3):
            d[a] = p[ci[k], a] - map_p[rj[k], a]
        Si = _inv3(P_old + P[ci[k]])
        m2 = 0.0
        for a in range(3):
            for b in range(3):
                m2 += d[a] * Si[a, b] * d[b]
        if m2 > gate_k2:  # they disagree: the new estimate supersedes the old one
            for a in range(3):
                p_f[k, a] = p[ci[k], a]
                for b in range(3):
                    P_f[k, a, b] = P[ci[k], a, b]
            continue
        fused[k] = True
        I_old = _inv3(P_old)
        I_new = _inv3(P[ci[k]])
        Pk = _inv3(I_old + I_new)
        for a in range(3):
            for b in range(3):
                P_f[k, a, b] = 0.5 * (Pk[a, b] + Pk[b, a])
        info = np.empty(3)
        for a in range(3):
            info[a] = (I_old[a, 0] * map_p[rj[k], 0] + I_old[a, 1] * map_p[rj[k], 1] + I_old[a, 2] * map_p[rj[k], 2]) + (
                I_new[a, 0] * p[ci[k], 0] + I_new[a, 1] * p[ci[k], 1] + I_new[a, 2] * p[ci[k], 2])
        for a in range(3):
            p_f[k, a] = P_f[k, a, 0] * info[0] + P_f[k, a, 1] * info[1] + P_f[k, a, 2] * info[2]
    return ci, rj, p_f, P_f, fused


@_jit.njit
def _prune_k(o, u, p, t_seen, pv, t, min_score, radius, max_age):
    """:meth:`ObstacleMap.prune`: kept points and the counts dropped by score, radius and age (before the cap)."""
    n = o.size
    keep = np.ones(n, np.bool_)
    n_score = n_far = n_old = 0
    for i in range(n):
        oi = float(o[i])
        score = (oi - 0.5 * float(u[i])) / (1.0 + oi)
        if score < min_score:
            n_score += 1
            keep[i] = False
            continue
        d0, d1, d2 = p[i, 0] - pv[0], p[i, 1] - pv[1], p[i, 2] - pv[2]
        if math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > radius:
            n_far += 1
            keep[i] = False
        elif t - t_seen[i] > max_age:
            n_old += 1
            keep[i] = False
    return keep, n_score, n_far, n_old


@_jit.njit
def _support_k(p, rows, pv, radius_m, rel, r_seen, seen_ratio, stop_at=0):
    """:meth:`ObstacleMap.support`: map points within the support radius of each row, by the
    reference's own float32 expansion E = |q|² + |p|² − 2 q·p, rounded as numpy rounds it: |q|² summed
    in order, q·p as BLAS's sgemm accumulates it on FMA hardware (x86-64 with FMA, ARMv8), a fused
    multiply–add chain q2·p2 + (q1·p1 + q0·p0), each step rounded once to float32 (products of
    float32 are exact in float64; a double rounding could differ only on an exact float32 tie).

    Only the points within a slab along the axis of largest spread are tested: E is within
    9 u (|q|² + |p|²) of the exact squared distance of the float32 points (u = 2⁻²⁴: two or three
    roundings in each of |q|², |p|², q·p, their sum and difference), so a point farther along that
    axis than √(r² + 16 u (|q|² + max |p|²)) cannot pass; the counts are those of testing every pair.
    ``r_seen`` (N,), ``seen_ratio``: the relative radius scales with the larger of the distance d from
    ``pv`` and min(r_seen, seen_ratio · d), each point's range when last entered (0: d alone).
    ``stop_at`` > 0: a count stops there (enough to decide ``count >= stop_at``)."""
    n = p.shape[0]
    X, Y, Z = np.empty(n), np.empty(n), np.empty(n)  # float32 coordinates, held exactly in float64
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    pp_max = 0.0
    for j in range(n):
        X[j], Y[j], Z[j] = np.float32(p[j, 0]), np.float32(p[j, 1]), np.float32(p[j, 2])
        lo[0], hi[0] = min(lo[0], X[j]), max(hi[0], X[j])
        lo[1], hi[1] = min(lo[1], Y[j]), max(hi[1], Y[j])
        lo[2], hi[2] = min(lo[2], Z[j]), max(hi[2], Z[j])
        pp_max = max(pp_max, X[j] * X[j] + Y[j] * Y[j] + Z[j] * Z[j])
    axis = 0
    for a in range(1, 3):
        if hi[a] - lo[a] > hi[axis] - lo[axis]:
            axis = a
    key = X if axis == 0 else (Y if axis == 1 else Z)
    order = np.argsort(key)
    Xs, Ys, Zs, ks = X[order], Y[order], Z[order], key[order]
    at = np.empty(n, np.int64)  # position of each point in the sorted order
    for j in range(n):
        at[order[j]] = j
    pp = np.empty(n, np.float32)
    for j in range(n):
        x, y, z = np.float32(Xs[j]), np.float32(Ys[j]), np.float32(Zs[j])
        pp[j] = x * x + y * y + z * z
    two = np.float32(2.0)
    u = 2.0**-24
    count = np.zeros(rows.size, np.int64)
    for k in range(rows.size):
        i = rows[k]
        radius = radius_m
        if rel > 0:
            d0, d1, d2 = p[i, 0] - pv[0], p[i, 1] - pv[1], p[i, 2] - pv[2]
            d = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            radius = max(radius, rel * max(d, min(r_seen[i], seen_ratio * d)))
        lim = np.float32(radius * radius)
        q0, q1, q2 = X[i], Y[i], Z[i]
        f0, f1, f2 = np.float32(q0), np.float32(q1), np.float32(q2)
        qq = f0 * f0 + f1 * f1 + f2 * f2
        w = math.sqrt(float(lim) + 16.0 * u * (float(qq) + pp_max))
        j0 = np.searchsorted(ks, key[i] - w)
        j1 = np.searchsorted(ks, key[i] + w, side="right")
        c = 0
        a = at[i]  # the point itself (inside its slab): visit outwards from it, nearest along the axis first
        right, left = a, a - 1
        while right < j1 or left >= j0:
            if right < j1 and (left < j0 or right - a <= a - left):
                j = right
                right += 1
            else:
                j = left
                left -= 1
            dot = np.float32(q0 * Xs[j])
            dot = np.float32(q1 * Ys[j] + dot)
            dot = np.float32(q2 * Zs[j] + dot)
            if ((qq + pp[j]) - two * dot) <= lim:
                c += 1
                if c == stop_at:
                    break
        count[k] = c
    return count


@_jit.njit
def _column_support_k(p, rows, radius_m, half_height_m, stop_at=0):
    """:meth:`ObstacleMap.support`'s column count: 1 + the map points within ``radius_m``
    horizontally (dx² + dy² ≤ r², float64) and ``half_height_m`` vertically of each row, the
    same expressions as the numpy reference.  Only the points within ``radius_m`` in north are
    visited (sorted once).  ``stop_at`` > 0: a count stops there."""
    order = np.argsort(p[:, 0])
    xs = p[order, 0].copy()
    r2 = radius_m * radius_m
    count = np.ones(rows.size, np.int64)
    for k in range(rows.size):
        i = rows[k]
        j0 = np.searchsorted(xs, p[i, 0] - radius_m)
        j1 = np.searchsorted(xs, p[i, 0] + radius_m, side="right")
        c = 1
        for q in range(j0, j1):
            j = order[q]
            if j == i:
                continue
            dx = p[j, 0] - p[i, 0]
            dy = p[j, 1] - p[i, 1]
            if dx * dx + dy * dy <= r2 and abs(p[j, 2] - p[i, 2]) <= half_height_m:
                c += 1
                if c == stop_at:
                    break
        count[k] = c
    return count


@_jit.njit
def _sorted_order(a):
    """Indices sorting ``a`` (the identity when it is already non-decreasing, as the pipeline's keys are)."""
    for i in range(1, a.size):
        if a[i] < a[i - 1]:
            return np.argsort(a)
    return np.arange(a.size)


@_jit.njit
def _first_rows(map_keys, queries):
    """(len(queries),) the first row holding each query key, −1 if none: the rows
    :meth:`ObstacleMap._rows` finds (its stable order makes the first of equal keys win), found by
    one pass over the map with a binary search in the (sorted) queries."""
    m = queries.size
    rows = np.full(m, -1, np.int64)
    if m == 0:
        return rows
    order = _sorted_order(queries)
    sq = queries[order]
    for r in range(map_keys.size):
        key = map_keys[r]
        j = np.searchsorted(sq, key)
        while j < m and sq[j] == key:
            if rows[order[j]] < 0:
                rows[order[j]] = r
            j += 1
    return rows


@_jit.njit
def _contains(sorted_keys, key):
    j = np.searchsorted(sorted_keys, key)
    return j < sorted_keys.size and sorted_keys[j] == key


@_jit.njit
def _rows_of_k(map_keys, keys):
    """Rows (ascending, each once) holding any of ``keys`` (:meth:`ObstacleMap.forget`)."""
    hit = np.zeros(map_keys.size, np.bool_)
    for r in _first_rows(map_keys, keys):
        if r >= 0:
            hit[r] = True
    return np.flatnonzero(hit)


@_jit.njit
def _observe_k(map_keys, map_p, map_P, map_t, map_o, map_u, keys_in, p_in, P_in, live_keys, live_is_keys, t, gate_k2,
               drift_mps, drift_max):
    """:meth:`ObstacleMap.observe` (docs/derivations/obstacle_map.md): refuse bad landmarks, mark the
    live rows, refresh the held ones, merge new ones into remembered points (fused), append the rest.
    Rows are updated in place (as the reference does); returns the map's arrays (new ones when points
    were appended), the refusal counts, the number merged and how many of those were superseded."""
    ok, n_bad, n_not_pd = _entry_checks_k(p_in, P_in)
    sel = np.flatnonzero(ok)
    keys = keys_in[sel]
    p = p_in[sel]
    P = P_in[sel]
    if live_is_keys:
        live_keys = keys
    n, m = map_keys.size, keys.size
    live = np.zeros(n, np.bool_)
    for r in _first_rows(map_keys, live_keys):
        if r >= 0:
            live[r] = True
    sl = live_keys[_sorted_order(live_keys)]
    held = _first_rows(map_keys, keys)
    key_live = np.zeros(m, np.bool_)
    new = np.ones(m, np.bool_)
    for k in range(m):
        key_live[k] = _contains(sl, keys[k])  # np.isin(keys, live_keys)
        r = held[k]
        if r >= 0:
            new[k] = False
            for a in range(3):
                map_p[r, a] = p[k, a]
                for b in range(3):
                    map_P[r, a, b] = P[k, a, b]
            map_t[r] = t
    n_merged = 0
    n_superseded = 0
    rem = np.flatnonzero(~live)
    cand = np.flatnonzero(new)
    if rem.size and cand.size:
        ci, rj, p_f, P_f, fused = _merge_pairs_k(p, P, cand, map_p, map_P, map_t, rem, t, gate_k2, drift_mps, drift_max)
        for k in range(ci.size):
            r, c = rj[k], ci[k]
            map_keys[r] = keys[c]
            for a in range(3):
                map_p[r, a] = p_f[k, a]
                for b in range(3):
                    map_P[r, a, b] = P_f[k, a, b]
            map_t[r] = t
            live[r] = key_live[c]
            map_o[r] += 1
            new[c] = False
        n_merged = ci.size
        n_superseded = ci.size - int(np.count_nonzero(fused))
    add = np.flatnonzero(new)
    if add.size == 0:
        return map_keys, map_p, map_P, map_t, map_o, map_u, live, n_bad, n_not_pd, n_merged, n_superseded
    N = n + add.size
    out_keys = np.empty(N, np.int64)
    out_p = np.empty((N, 3))
    out_P = np.empty((N, 3, 3))
    out_t = np.empty(N)
    out_o = np.zeros(N, np.int64)
    out_u = np.zeros(N, np.int64)
    out_live = np.empty(N, np.bool_)
    for i in range(n):
        out_keys[i], out_t[i], out_o[i], out_u[i], out_live[i] = map_keys[i], map_t[i], map_o[i], map_u[i], live[i]
        for a in range(3):
            out_p[i, a] = map_p[i, a]
            for b in range(3):
                out_P[i, a, b] = map_P[i, a, b]
    for q in range(add.size):
        k, i = add[q], n + q
        out_keys[i], out_t[i], out_live[i] = keys[k], t, key_live[k]
        for a in range(3):
            out_p[i, a] = p[k, a]
            for b in range(3):
                out_P[i, a, b] = P[k, a, b]
    return out_keys, out_p, out_P, out_t, out_o, out_u, out_live, n_bad, n_not_pd, n_merged, n_superseded


@_jit.njit
def _check_view_k(map_keys, p, P, t_seen, o, u, live, R, p_world_cam, fx, fy, cx, cy, width, height, luv, live_depth, live_sigma,
                  live_keys, has_live_keys, t, margin, radius2, gate_k, drift_mps, drift_max):
    """:meth:`ObstacleMap.check_view`: remembered points predicted in view (pinhole, inside the margin)
    are found again (a live pixel within the radius whose depth agrees within gate_k σ: o += 1, age
    restarts, or absorbed by that live point's own row) or seen through (not found, a live point
    beyond: u += 1).  Updates o, u, t_seen in place; returns (predicted, found, missed, absorbed rows)."""
    rem = np.flatnonzero(~live)
    nr, nl = rem.size, luv.shape[0]
    rows = np.empty(nr, np.int64)
    uq = np.empty(nr)
    vq = np.empty(nr)
    z = np.empty(nr)
    k = 0
    for q in range(nr):
        i = rem[q]
        d0, d1, d2 = p[i, 0] - p_world_cam[0], p[i, 1] - p_world_cam[1], p[i, 2] - p_world_cam[2]
        zc = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
        if not zc > 0.1:
            continue
        xc = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
        yc = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
        uu, vv = fx * xc / zc + cx, fy * yc / zc + cy
        if uu >= margin and uu <= width - 1 - margin and vv >= margin and vv <= height - 1 - margin:
            rows[k], uq[k], vq[k], z[k] = i, uu, vv, zc
            k += 1
    none = np.zeros(0, np.int64)
    if k == 0 or nl == 0:
        return k, 0, 0, none
    found = np.zeros(k, np.bool_)
    best = np.full(k, -1, np.int64)
    n_missed = 0
    for q in range(k):
        i = rows[q]
        s_pos = _drift_pos_k(t - t_seen[i], drift_mps, drift_max)
        s_map2 = 0.0
        for a in range(3):
            s_map2 += R[a, 2] * (P[i, a, 0] * R[0, 2] + P[i, a, 1] * R[1, 2] + P[i, a, 2] * R[2, 2])
        s_map2 += s_pos * s_pos
        best_d2 = np.inf
        beyond = False
        for l in range(nl):
            du, dv = uq[q] - luv[l, 0], vq[q] - luv[l, 1]
            d2 = du * du + dv * dv
            if not d2 <= radius2:
                continue
            dz = live_depth[l] - z[q]
            gate = gate_k * math.sqrt(s_map2 + live_sigma[l] * live_sigma[l])
            if abs(dz) <= gate:
                found[q] = True
                if d2 < best_d2:
                    best_d2, best[q] = d2, l
            elif dz > gate:
                beyond = True
        if beyond and not found[q]:
            u[i] += 1
            n_missed += 1
    n_found = 0
    for q in range(k):
        n_found += found[q]
    absorbed = np.zeros(map_keys.size, np.bool_)
    into = np.full(k, -1, np.int64)  # the live point's own row that absorbs a found point
    if n_found and has_live_keys:
        fq = np.flatnonzero(found)
        target = _first_rows(map_keys, live_keys[best[fq]])
        gain = np.zeros(k, np.int64)
        for f in range(fq.size):  # o of the absorbed points read before any is added (np.add.at)
            q = fq[f]
            into[q] = target[f]
            gain[q] = o[rows[q]] + 1
        for q in range(k):
            if into[q] >= 0:
                o[into[q]] += gain[q]
                absorbed[rows[q]] = True
    for q in range(k):
        if found[q] and into[q] < 0:
            o[rows[q]] += 1
            t_seen[rows[q]] = t
    return k, n_found, n_missed, np.flatnonzero(absorbed)


@_jit.njit
def _remembered_k(p, P, t_seen, live, pv, t, min_support, radius_m, rel, r_seen, seen_ratio, drift_mps, drift_max, heading_rad_s,
                  column_radius_m=0.0, column_half_height_m=0.0):
    """:meth:`ObstacleMap.remembered`: the rows not live with ``min_support`` map points around them,
    σ_r = √(uᵀPu + σ_drift²), σ_t = √((tr P − uᵀPu)/2 + σ_drift² + (r_h σ_ψ)²) and the time since seen."""
    rows = np.flatnonzero(~live)
    if min_support > 1 and rows.size:
        sup = _support_k(p, rows, pv, radius_m, rel, r_seen, seen_ratio, min_support)
        if column_radius_m > 0:  # only the rows the sphere left short need the column's count
            short = np.flatnonzero(sup < min_support)
            if short.size:
                col = _column_support_k(p, rows[short], column_radius_m, column_half_height_m, min_support)
                sup[short] = np.maximum(sup[short], col)
        rows = rows[sup >= min_support]
    n = rows.size
    s_r = np.empty(n)
    s_t = np.empty(n)
    dt = np.empty(n)
    for k in range(n):
        i = rows[k]
        d0, d1, d2 = p[i, 0] - pv[0], p[i, 1] - pv[1], p[i, 2] - pv[2]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        rs = max(r, 1e-9)
        u0, u1, u2 = d0 / rs, d1 / rs, d2 / rs
        uPu = (u0 * (P[i, 0, 0] * u0 + P[i, 0, 1] * u1 + P[i, 0, 2] * u2) + u1 * (P[i, 1, 0] * u0 + P[i, 1, 1] * u1 + P[i, 1, 2] * u2)
               + u2 * (P[i, 2, 0] * u0 + P[i, 2, 1] * u1 + P[i, 2, 2] * u2))
        dt[k] = max(t - t_seen[i], 0.0)
        s_pos = _drift_pos_k(dt[k], drift_mps, drift_max)
        s_head = heading_rad_s * dt[k]
        r_h = np.hypot(d0, d1)
        s_r[k] = math.sqrt(max(uPu, 0.0) + s_pos * s_pos)
        tr = P[i, 0, 0] + P[i, 1, 1] + P[i, 2, 2]
        s_t[k] = math.sqrt(max(tr - uPu, 0.0) / 2.0 + s_pos * s_pos + (r_h * s_head) * (r_h * s_head))
    return rows, s_r, s_t, dt


@_jit.njit
def _map_entries_k(ids, key_base, converged, valid, range_sigma, range_m, p_world, mean_nis, has_nis, max_rel_sigma, ratio,
                   p_world_cam, bearing_sigma):
    """:func:`map_entries_reference`: keys, the mask that may enter, the keys to forget and the entries' covariances."""
    n = ids.size
    keys = np.empty(n, np.int64)
    good = np.empty(n, np.bool_)
    for i in range(n):
        keys[i] = ids[i] + key_base
        good[i] = converged[i] and valid[i] and range_sigma[i] <= max_rel_sigma * range_m[i]
    forget = np.zeros(0, np.int64)
    if ratio > 0 and has_nis:
        ok = _consistent_for_entry_k(mean_nis, converged & valid, ratio, 10)
        bad = good & ~ok
        forget = keys[bad]
        good &= ~bad
    sel = np.flatnonzero(good)
    P = _landmark_covariance_k(p_world[sel], p_world_cam, range_sigma[sel], bearing_sigma)
    return keys, good, forget, P


@_jit.njit
def _live_view_k(ids, track_ids, track_uv, keys, good, p_world, range_sigma, range_m, R, p_world_cam, fx, fy, cx, cy, pinhole):
    """:func:`live_view_reference`: the track rows of the live landmarks with a point in the map, their
    pinhole pixels (when ``pinhole``: the camera has no distortion; else the caller undistorts the
    rows), depth along the optical axis, its σ and their keys."""
    n, nt = ids.size, track_ids.size
    rows = np.empty(n, np.int64)
    src = np.empty(n, np.int64)
    m = 0
    if n and nt:
        pos = np.searchsorted(track_ids, ids)
        for k in range(n):
            j = min(pos[k], nt - 1)
            if track_ids[j] == ids[k] and good[k]:
                rows[m], src[m] = j, k
                m += 1
    rows = rows[:m]
    uv = np.empty((m, 2))
    depth = np.empty(m)
    sig = np.empty(m)
    lkeys = np.empty(m, np.int64)
    for q in range(m):
        k, j = src[q], rows[q]
        depth[q] = (p_world[k, 0] - p_world_cam[0]) * R[0, 2] + (p_world[k, 1] - p_world_cam[1]) * R[1, 2] + (
            p_world[k, 2] - p_world_cam[2]) * R[2, 2]
        sig[q] = range_sigma[k] * abs(depth[q]) / max(range_m[k], 1e-9)
        lkeys[q] = keys[k]
        if pinhole:  # CameraModel.undistort_to_pinhole without distortion: K (K⁻¹ uv)
            uv[q, 0] = fx * ((track_uv[j, 0] - cx) / fx) + cx
            uv[q, 1] = fy * ((track_uv[j, 1] - cy) / fy) + cy
    return rows, uv, depth, sig, lkeys


@_jit.register_warmup
def _warm_up() -> None:
    """Compile the map kernels on a tiny map: enter, merge, re-observe, absorb, prune, remember, forget.

    The calls of :class:`companion.core.obstacle_map.ObstacleMap` and
    :mod:`companion.core.obstacle_map_landmarks` on ``MapConfig(min_support=2, support_radius_rel=0.1)``,
    with the argument types they pass (the configuration's floats and ints as literals)."""
    R_wc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # camera looking north
    p_wc = np.zeros(3)
    p = np.array([[10.0, 0.0, 0.0], [10.0, 0.3, 0.0], [10.0, -0.3, 0.1]])
    ok = _consistent_for_entry_k(np.array([1.0, 1.0, 2.0]), np.ones(3, bool), 10.0, 1)
    P = _landmark_covariance_k(p[ok], p_wc, np.full(3, 0.2), 0.002)
    gate_k2 = 3.0**2
    m = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))
    *m, _, _, _, _ = _observe_k(*m, np.array([1, 2, 3]), p, P, np.zeros(0, np.int64), True, 0.0, gate_k2, 0.02, 1.5)  # keys … live
    keys, good, _, _ = _map_entries_k(np.array([1, 2]), 0, np.ones(2, bool), np.ones(2, bool), np.full(2, 0.2), np.full(2, 10.0),
                                      p[:2], np.ones(2), True, 0.15, 5.0, p_wc, 0.002)
    _live_view_k(np.array([1, 2]), np.array([2]), np.array([[160.0, 120.0]]), keys, good, p[:2], np.full(2, 0.2), np.full(2, 10.0),
                 R_wc, p_wc, 277.0, 277.0, 159.5, 119.5, True)
    *m, _, _, _, _ = _observe_k(*m[:6], np.array([4, 5]), p[:2] + 0.01, P[:2], np.array([4, 5]), False, 0.1, gate_k2, 0.02, 1.5)
    *_, absorbed = _check_view_k(*m, R_wc, p_wc, 300.0, 300.0, 160.0, 120.0, 320.0, 240.0, np.array([[160.0, 120.0]]),
                                 np.array([10.0]), np.array([0.2]), np.array([4]), True, 0.1, 4.0, 6.0**2, 3.0, 0.02, 1.5)
    keep = np.ones(len(m[0]), bool)
    keep[absorbed] = False
    keys, p_m, P_m, t_seen, o, u, live = (a[keep] for a in m)
    keep, *_ = _prune_k(o, u, p_m, t_seen, p_wc, 0.1, -0.75, 60.0, 20.0)
    keys, p_m, P_m, t_seen, live = (a[keep] for a in (keys, p_m, P_m, t_seen, live))
    _remembered_k(p_m, P_m, t_seen, live, p_wc, 0.2, 2, 0.6, 0.1, np.zeros(len(p_m)), 0.0, 0.02, 1.5, math.radians(0.05), 0.3, 1.2)
    _rows_of_k(keys, np.array([5]))
    _points_on_current_rays_k(np.array([1, 4]), p[:2], np.array([10.0, 10.0]), np.array([4]), np.array([[0.0, 0.0, 1.0]]), R_wc, p_wc)
