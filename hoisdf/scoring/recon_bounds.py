"""The exact recon protocol's per-piece bounds (:mod:`hoisdf.scoring.recon_exact`), compiled: for each sub-triangle,
its area, the bounds of the integral of f = d(x, B)^2 over it, and the bounds of its area where d < t.

The area bounds are areas of discs in the piece's plane (docs/scoring.md, "The exact protocol and its bound"):
- inside: for a point p of B, d(x) <= |x - p|, so the piece's part within the ball |x - p| < t (a disc in its plane)
  is within the threshold; the largest such part over the closest points already found (of the centroid and the
  vertices) is a lower bound;
- outside: f lies above Q(x) = L(x) + |x - c|^2, with L the plane through the vertex values of the concave
  f - |x - c|^2, and Q < t^2 is a disc; d(x) >= d(c) - |x - c| excludes the disc |x - c| < d(c) - t. The smaller
  of the two areas left is an upper bound.
Both shrink like the cube of the piece's size along a threshold's contour (its share of the width like the square),
where counting a straddling piece as wholly undecided shrank only like its size.
"""

from __future__ import annotations

import numba
import numpy as np

from hoidata.geometry.bvh_wide import closest_wide

AREA_MARGIN = 1e-9  # a partial disc area is widened by this share of the piece's area: rounding of the disc's terms


@numba.njit(cache=True, inline="always")
def _edge_part(ax, ay, bx, by, r2):
    """Signed area of the disc |x| < sqrt(r2) intersected with the triangle (0, a, b)."""
    dx, dy = bx - ax, by - ay
    qa = dx * dx + dy * dy
    if qa == 0.0:
        return 0.0
    qb = ax * dx + ay * dy
    qc = ax * ax + ay * ay - r2
    disc = qb * qb - qa * qc
    t0, t1 = 1.0, 0.0
    if disc > 0.0:
        s = np.sqrt(disc)
        t0, t1 = max((-qb - s) / qa, 0.0), min((-qb + s) / qa, 1.0)
    if t0 >= t1:  # the segment misses the disc: a sector
        return 0.5 * r2 * np.arctan2(ax * by - ay * bx, ax * bx + ay * by)
    px, py = ax + t0 * dx, ay + t0 * dy
    qx, qy = ax + t1 * dx, ay + t1 * dy
    out = 0.5 * (px * qy - py * qx)  # the chord inside the disc: a triangle, with a sector on either side
    out += 0.5 * r2 * np.arctan2(ax * py - ay * px, ax * px + ay * py)
    out += 0.5 * r2 * np.arctan2(qx * by - qy * bx, qx * bx + qy * by)
    return out


@numba.njit(cache=True)
def disc_triangle_area(zx, zy, r2, w):
    """Area of the disc around (zx, zy) of squared radius r2 within the triangle w (3, 2) (plane coordinates)."""
    if r2 <= 0.0:
        return 0.0
    inside, box = 0, 0.0
    for j in range(3):
        dx, dy = w[j, 0] - zx, w[j, 1] - zy
        inside += dx * dx + dy * dy <= r2
    if inside == 3:  # the disc holds the triangle
        return 0.5 * abs((w[1, 0] - w[0, 0]) * (w[2, 1] - w[0, 1]) - (w[2, 0] - w[0, 0]) * (w[1, 1] - w[0, 1]))
    for e in range(2):  # the disc misses the triangle's bounding box
        z = zx if e == 0 else zy
        gap = max(min(w[0, e], w[1, e], w[2, e]) - z, z - max(w[0, e], w[1, e], w[2, e]), 0.0)
        box += gap * gap
    if box >= r2:
        return 0.0
    total = 0.0
    for j in range(3):
        k = (j + 1) % 3
        total += _edge_part(w[j, 0] - zx, w[j, 1] - zy, w[k, 0] - zx, w[k, 1] - zy, r2)
    return abs(total)


@numba.njit(cache=True)
def piece_bounds(tri, fv, pv, fc, pc, t2, slack, discs=True):
    """Per sub-triangle (vertices ``tri``, vertex squared distances ``fv`` and closest points ``pv``, centroid
    squared distance ``fc`` and closest point ``pc``): area, lower and upper bound of the integral of f, and per
    threshold lower and upper bounds of its area where d < t (module docstring and :mod:`hoisdf.scoring.recon_exact`).
    The computed distances' rounding is allowed for: ``t2`` (2, k) holds each threshold's square taken in by it (for
    the lower area bound) and out (for the upper), and the integral's bounds are widened by ``slack`` per unit area
    (f's rounding)."""
    n, k = tri.shape[0], t2.shape[1]
    area, lo, hi = np.empty(n), np.empty(n), np.empty(n)
    inside_lo, inside_hi = np.zeros((n, k)), np.zeros((n, k))
    w = np.empty((3, 2))
    for i in range(n):
        a = tri[i, 1] - tri[i, 0]
        b = tri[i, 2] - tri[i, 0]
        cx = a[1] * b[2] - a[2] * b[1]
        cy = a[2] * b[0] - a[0] * b[2]
        cz = a[0] * b[1] - a[1] * b[0]
        norm = np.sqrt(cx * cx + cy * cy + cz * cz)
        area[i] = 0.5 * norm
        c = (tri[i, 0] + tri[i, 1] + tri[i, 2]) / 3.0
        m, r2max, fmean, inf2 = 0.0, 0.0, 0.0, np.inf
        for j in range(3):
            r2 = 0.0
            for e in range(3):
                r2 += (tri[i, j, e] - c[e]) ** 2
            m += r2 / 3.0
            r2max = max(r2max, r2)
            fmean += fv[i, j] / 3.0
            inf2 = min(inf2, fv[i, j] - r2)
        dc = np.sqrt(fc[i])
        near = max(dc - np.sqrt(r2max), 0.0) ** 2
        low = area[i] * max(fmean - 0.75 * m, near)
        high = area[i] * min(fc[i] + 0.25 * m, (dc + np.sqrt(r2max)) ** 2)
        lo[i], hi[i] = min(low, high) - area[i] * slack, high + area[i] * slack  # low > high only by rounding
        inf2 = max(inf2, near)
        # sup d over the piece: <= max over its vertices of the distance to any closest point already known
        sup2 = np.inf
        for q in range(4):
            p = pc[i] if q == 0 else pv[i, q - 1]
            worst = 0.0
            for j in range(3):
                d2 = 0.0
                for e in range(3):
                    d2 += (tri[i, j, e] - p[e]) ** 2
                worst = max(worst, d2)
            sup2 = min(sup2, worst)
        undecided = False
        for t in range(k):
            inside_lo[i, t] = area[i] if sup2 < t2[0, t] else 0.0
            inside_hi[i, t] = area[i] if (sup2 < t2[0, t] or inf2 < t2[1, t]) else 0.0
            undecided |= inside_lo[i, t] < inside_hi[i, t]
        if not (discs and undecided and norm > 0.0):
            continue
        # the piece's plane: c the origin, e1 along the first edge, e2 = n x e1
        la = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
        e1 = a / la
        nv = np.array([cx, cy, cz]) / norm
        e2 = np.array([nv[1] * e1[2] - nv[2] * e1[1], nv[2] * e1[0] - nv[0] * e1[2], nv[0] * e1[1] - nv[1] * e1[0]])
        g = np.empty(3)
        for j in range(3):
            r = tri[i, j] - c
            w[j, 0], w[j, 1] = r[0] * e1[0] + r[1] * e1[1] + r[2] * e1[2], r[0] * e2[0] + r[1] * e2[1] + r[2] * e2[2]
            g[j] = fv[i, j] - (r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        x1, y1, x2, y2 = w[1, 0] - w[0, 0], w[1, 1] - w[0, 1], w[2, 0] - w[0, 0], w[2, 1] - w[0, 1]
        det = x1 * y2 - x2 * y1
        alpha = ((g[1] - g[0]) * y2 - (g[2] - g[0]) * y1) / det
        beta = (x1 * (g[2] - g[0]) - x2 * (g[1] - g[0])) / det
        gamma = g[0] - alpha * w[0, 0] - beta * w[0, 1]  # L at c
        kappa = gamma - 0.25 * (alpha * alpha + beta * beta)  # Q = |x - z|^2 + kappa, z = -(alpha, beta) / 2
        margin = AREA_MARGIN * area[i]
        for t in range(k):
            if not inside_lo[i, t] < inside_hi[i, t]:
                continue
            upper = disc_triangle_area(-0.5 * alpha, -0.5 * beta, t2[1, t] - kappa, w)
            if dc * dc > t2[1, t]:
                gap = dc - np.sqrt(t2[1, t])
                upper = min(upper, area[i] - disc_triangle_area(0.0, 0.0, gap * gap, w))
            lower = 0.0
            for q in range(4):
                p = pc[i] if q == 0 else pv[i, q - 1]
                r = p - c
                h = r[0] * nv[0] + r[1] * nv[1] + r[2] * nv[2]
                px, py = r[0] * e1[0] + r[1] * e1[1] + r[2] * e1[2], r[0] * e2[0] + r[1] * e2[1] + r[2] * e2[2]
                lower = max(lower, disc_triangle_area(px, py, t2[0, t] - h * h, w))
            inside_hi[i, t] = min(area[i], max(upper + margin, 0.0))
            inside_lo[i, t] = min(max(lower - margin, 0.0), inside_hi[i, t])
    return area, lo, hi, inside_lo, inside_hi


@numba.njit(cache=True)
def query(points, hint, tree):
    """Squared distances (N,), closest points (N, 3) and faces (N,) in leaf order of points (N, 3) to the target
    whose wide tree is ``tree`` = (order, lo, hi, ref, blocks, first, count, tri); ``hint`` (N,): a face near each
    point (leaf order; -1: the previous point's). The squares of :meth:`hoidata.geometry.bvh.MeshBVH.closest`'s
    distances, the closest points a + v (b - a) + w (c - a) from its weights."""
    order, lo, hi, ref, blocks, first, count, tri = tree
    n = len(points)
    dist, face, weights, feature = np.empty(n), np.empty(n, np.int64), np.empty((n, 2)), np.empty(n, np.int8)
    closest_wide(points, np.arange(n), hint, order, lo, hi, ref, blocks, first, count, tri, dist, face, weights,
                 feature)
    d2, closest = np.empty(n), np.empty((n, 3))
    for i in range(n):
        k, v, w = face[i], weights[i, 0], weights[i, 1]
        d2[i] = dist[i] * dist[i]
        for e in range(3):
            closest[i, e] = tri[k, e] + v * (tri[k, 3 + e] - tri[k, e]) + w * (tri[k, 6 + e] - tri[k, e])
    return d2, closest, face


KIDS = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])  # (v0, m01, m20), (m01, v1, m12), (m20, m12, v2), mids
EDGES = np.array([[0, 1], [1, 2], [2, 0]])  # the midpoints m01, m12, m20


@numba.njit(cache=True)
def split_pieces(tri, fv, pv, hv, area, lo, hi, inside_lo, inside_hi, idx, n, tree, t2, slack, discs):
    """Write the four children (edge midpoints) of the pieces ``idx`` into rows n to n + 4 len(idx) of the pieces'
    arrays: corners, the corners' squared distances, closest points and faces (leaf order), and their
    :func:`piece_bounds` (``t2``, ``slack``: its thresholds and rounding; ``discs`` False: the fractions' bounds by
    whole pieces only, as before the disc areas).
    Each midpoint's query starts from the face of its edge's first corner, each centroid's from its first corner's."""
    m = len(idx)
    mid = np.empty((3 * m, 3))
    mid_hint = np.empty(3 * m, np.int64)
    for s in range(m):
        i = idx[s]
        for q in range(3):
            a, b = EDGES[q, 0], EDGES[q, 1]
            for e in range(3):
                mid[3 * s + q, e] = (tri[i, a, e] + tri[i, b, e]) / 2
            mid_hint[3 * s + q] = hv[i, a]
    fm, pm, hm = query(mid, mid_hint, tree)
    for s in range(m):
        i = idx[s]
        for c in range(4):
            r = n + 4 * s + c
            for j in range(3):
                src = KIDS[c, j]
                if src < 3:
                    tri[r, j], fv[r, j], pv[r, j], hv[r, j] = tri[i, src], fv[i, src], pv[i, src], hv[i, src]
                else:
                    q = 3 * s + src - 3
                    tri[r, j], fv[r, j], pv[r, j], hv[r, j] = mid[q], fm[q], pm[q], hm[q]
    end = n + 4 * m
    cen = np.empty((4 * m, 3))
    for r in range(4 * m):
        for e in range(3):
            cen[r, e] = (tri[n + r, 0, e] + tri[n + r, 1, e] + tri[n + r, 2, e]) / 3
    fc, pc, _ = query(cen, hv[n:end, 0].copy(), tree)
    b = piece_bounds(tri[n:end], fv[n:end], pv[n:end], fc, pc, t2, slack, discs)
    area[n:end], lo[n:end], hi[n:end], inside_lo[n:end], inside_hi[n:end] = b


BUCKETS = 4  # score classes per octave when choosing the pieces to split


@numba.njit(cache=True)
def plan_round(area, lo, hi, inside_lo, inside_hi, live, n, total, tol_sq, tol_frac, retire, done_sq, done_frac,
               budget):
    """One refinement round of :func:`hoisdf.scoring.recon_exact.one_way` over the first n pieces: (over, chosen,
    settled), over True while the mean's width (``done_sq`` of pieces set aside included) or a fraction's
    (``done_frac``) is above its tolerance; chosen, the pieces of the highest scores (scaled widths) that hold half
    of the score or more, taken by classes of a quarter octave (at most ``budget``, highest classes first); settled,
    the others whose width on the mean and each fraction is at most ``retire`` times their area's share of that
    tolerance, or whose share of the width is negligible."""
    k = inside_lo.shape[1]
    score = np.zeros(n)
    width_sq, width_frac = done_sq, done_frac.copy()
    alive = 0
    for i in range(n):
        w_sq = (hi[i] - lo[i]) / total
        width_sq += w_sq
        s = 0.0
        for t in range(k):
            w = (inside_hi[i, t] - inside_lo[i, t]) / total
            width_frac[t] += w
            s = max(s, w / tol_frac)
        score[i] = w_sq / tol_sq + s
        alive += live[i]
    over = width_sq > tol_sq
    for t in range(k):
        over |= width_frac[t] > tol_frac
    empty = np.zeros(0, np.int64)
    if not over:
        return over, empty, empty
    top = score.max()
    mass = score.sum()
    span = 64 * BUCKETS  # classes below top / 2**64 are never chosen
    klass = np.full(n, -1, np.int64)  # 0: within a quarter octave of the top score
    mass_of = np.zeros(span)
    for i in range(n):
        if score[i] > 0:
            c = int(np.floor(BUCKETS * np.log2(top / score[i])))
            if c < span:
                klass[i] = c
                mass_of[c] += score[i]
    last, cum = 0, 0.0
    while last < span - 1 and cum + mass_of[last] < 0.5 * mass:
        cum += mass_of[last]
        last += 1
    chosen = np.empty(n, np.int64)
    m = 0
    for c in range(last + 1):  # class by class, within a class in row order
        for i in range(n):
            if klass[i] == c and m < max(budget, 1):
                chosen[m] = i
                m += 1
    picked = np.zeros(n, np.bool_)
    picked[chosen[:m]] = True
    negligible = 1e-6 * mass / max(alive, 1)
    settled = np.empty(n, np.int64)
    count = 0
    for i in range(n):
        if picked[i] or not live[i]:
            continue
        share = retire * area[i] / total
        small = (hi[i] - lo[i]) / total <= share * tol_sq
        for t in range(k):
            small &= (inside_hi[i, t] - inside_lo[i, t]) / total <= share * tol_frac
        if score[i] <= negligible or small:
            settled[count] = i
            count += 1
    return over, chosen[:m].copy(), settled[:count].copy()
