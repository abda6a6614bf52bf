"""Reconstruction scores without sampling noise: surface integrals of the distance to the other surface, with
rigorous lower and upper bounds (docs/scoring.md, "The exact protocol and its bound").

For surfaces A (a prediction) and B (the ground truth) in cm, with f(x) = d(x, B)^2 the squared distance to the
triangles of B, the quantities are the limits of gSDF's sampled ones as the sample count grows:

- the mean squared distance ``(1/|A|) integral_A f dA``; Chamfer is the sum of both directions' means (cm^2);
- the fraction of A's area where d(x, B) < t; precision and recall are the two directions' fractions, and
  F = 2 P R / (P + R) (0 when both are 0).

Each triangle of A is cut into sub-triangles T (area a, vertices v_i, centroid c, r_i^2 = |v_i - c|^2, m = mean
r_i^2, R = max r_i). Two facts about f bound each one's share (proofs in the docs page):

- f is 1-Lipschitz in d: max(0, d(c) - R) <= d(x) <= d(c) + R on T;
- f - |x|^2 is concave (a minimum of affine functions of x), so g = f - |x - c|^2 is concave on T: g lies above
  the plane through its vertex values and below its value at c (Jensen), which gives
  ``a (mean f(v_i) - 3m/4) <= integral_T f <= a (f(c) + m/4)`` (the second moment of T about c is a m / 4), and
  ``min_x f >= min_i (f(v_i) - r_i^2)``; and d(x) <= |x - p| for any point p of B, whose maximum over T is at a
  vertex.

Sub-triangles are split in four (edge midpoints) where their share of the bounds' width is largest, until both
widths are under the tolerances or the query budget is spent (the bound is then wider, still rigorous, and says
so). Distances are exact point-to-triangle distances (:class:`hoidata.geometry.bvh.MeshBVH`) in float64; the
bounds hold up to float64 rounding (relative 1e-15).
"""

from __future__ import annotations

import numpy as np

from hoidata.geometry.bvh import MeshBVH

MAX_QUERIES = 4_000_000  # distance queries per direction of one part of one frame (about 1 GB of sub-triangles)
CHUNK = 100_000  # sub-triangles per block of the vertex-to-closest-point bound


class Target:
    """The other surface: its hierarchy and triangles (cm), for squared distances and closest points."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices, self.faces = vertices, faces
        self.bvh = MeshBVH(vertices, faces)
        self.queries = 0

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Squared distances (N,) and closest points (N, 3) of points (N, 3)."""
        self.queries += len(points)
        dist, face, w, _ = self.bvh.closest(np.ascontiguousarray(points, dtype=np.float64))
        tri = self.vertices[self.faces[face]]
        closest = tri[:, 0] + w[:, :1] * (tri[:, 1] - tri[:, 0]) + w[:, 1:] * (tri[:, 2] - tri[:, 0])
        return dist * dist, closest


def _areas(tri: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


class _Pieces:
    """Sub-triangles with their vertex and centroid distances."""

    def __init__(self, tri, fv, pv, target: Target):
        self.tri, self.fv, self.pv = tri, fv, pv
        self.area = _areas(tri)
        self.c = tri.mean(1)
        self.fc, self.pc = target.query(self.c)

    def bounds(self, thresholds: np.ndarray):
        """Per piece: integral lower/upper bounds of f, and (n, k) 'surely inside' / 'maybe inside' per threshold."""
        r2 = np.square(self.tri - self.c[:, None]).sum(2)
        m, big_r = r2.mean(1), np.sqrt(r2.max(1))
        dc = np.sqrt(self.fc)
        lo = self.area * np.maximum(self.fv.mean(1) - 0.75 * m, np.square(np.maximum(dc - big_r, 0.0)))
        hi = self.area * np.minimum(self.fc + 0.25 * m, np.square(dc + big_r))
        lo = np.minimum(lo, hi)  # equal up to rounding where T is a point
        # sup d over T: <= max over the vertices of the distance to any closest point already known
        sup2 = np.empty(len(self.tri))
        for s in range(0, len(self.tri), CHUNK):  # in chunks: the (n, 3, 4, 3) differences are large
            known = np.concatenate([self.pc[s:s + CHUNK, None], self.pv[s:s + CHUNK]], 1)  # (n, 4, 3)
            sup2[s:s + CHUNK] = np.square(self.tri[s:s + CHUNK, :, None] - known[:, None]).sum(3).max(1).min(1)
        inf2 = np.maximum((self.fv - r2).min(1), np.square(np.maximum(dc - big_r, 0.0)))
        t2 = np.square(thresholds)[None]
        surely = sup2[:, None] < t2
        return lo, hi, surely, surely | (inf2[:, None] < t2)

    def split(self, idx: np.ndarray, target: Target) -> _Pieces:
        tri, fv, pv = self.tri[idx], self.fv[idx], self.pv[idx]
        mid = np.stack([(tri[:, 0] + tri[:, 1]) / 2, (tri[:, 1] + tri[:, 2]) / 2, (tri[:, 2] + tri[:, 0]) / 2], 1)
        fm, pm = target.query(mid.reshape(-1, 3))
        fm, pm = fm.reshape(-1, 3), pm.reshape(-1, 3, 3)
        # children: (v0, m01, m20), (m01, v1, m12), (m20, m12, v2), (m01, m12, m20)
        pts = np.concatenate([tri, mid], 1)
        fs, ps = np.concatenate([fv, fm], 1), np.concatenate([pv, pm], 1)
        kids = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])
        new_tri = pts[:, kids].reshape(-1, 3, 3)
        new_f = fs[:, kids].reshape(-1, 3)
        new_p = ps[:, kids].reshape(-1, 3, 3)
        return _Pieces(new_tri, new_f, new_p, target)


def _concat(a: _Pieces, b: _Pieces) -> _Pieces:
    out = object.__new__(_Pieces)
    for name in ("tri", "fv", "pv", "area", "c", "fc", "pc"):
        setattr(out, name, np.concatenate([getattr(a, name), getattr(b, name)]))
    return out


def _take(p: _Pieces, idx: np.ndarray) -> _Pieces:
    out = object.__new__(_Pieces)
    for name in ("tri", "fv", "pv", "area", "c", "fc", "pc"):
        setattr(out, name, getattr(p, name)[idx])
    return out


def one_way(vertices: np.ndarray, faces: np.ndarray, target: Target, thresholds, tol_sq: float,
            tol_frac: float, max_queries: int = MAX_QUERIES) -> dict:
    """Bounds of A's mean squared distance to B (cm^2) and of A's area fraction within each threshold (cm).

    Refines until the mean's bound is at most ``tol_sq`` wide and each fraction's at most ``tol_frac`` wide, or
    ``max_queries`` distance queries were made. Pieces that are settled (bounded closely enough) are retired so
    the work goes where the width is.
    """
    thresholds = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
    start = target.queries
    fvert, pvert = target.query(vertices)
    tri = vertices[faces]
    pieces = _Pieces(tri, fvert[faces], pvert[faces], target)
    total = float(pieces.area.sum())
    if not total > 0:
        raise ValueError("the surface has no area")
    done_lo = done_hi = 0.0
    done_in, done_maybe = np.zeros(len(thresholds)), np.zeros(len(thresholds))
    while True:
        lo, hi, surely, maybe = pieces.bounds(thresholds)
        w_sq = (hi - lo) / total
        w_frac = (pieces.area[:, None] * (maybe & ~surely)) / total
        width_sq = w_sq.sum() + (done_hi - done_lo) / total
        width_frac = w_frac.sum(0) + (done_maybe - done_in) / total
        over = (width_sq > tol_sq) or bool((width_frac > tol_frac).any())
        if not over or target.queries - start >= max_queries:
            break
        score = w_sq / tol_sq + (w_frac / tol_frac).max(1)
        order = np.argsort(-score)
        cum = np.cumsum(score[order])
        n = max(1, int(np.searchsorted(cum, 0.5 * cum[-1])) + 1)
        n = min(n, max(1, (max_queries - (target.queries - start)) // 7))
        chosen, rest = order[:n], order[n:]
        # retire the pieces that are not chosen and whose share is already negligible
        keep = np.zeros(len(score), bool)
        keep[rest] = score[rest] > 1e-6 * cum[-1] / max(len(score), 1)
        settled = ~keep
        settled[chosen] = False
        done_lo += lo[settled].sum()
        done_hi += hi[settled].sum()
        done_in += (pieces.area[settled, None] * surely[settled]).sum(0)
        done_maybe += (pieces.area[settled, None] * maybe[settled]).sum(0)
        children = pieces.split(chosen, target)
        pieces = _concat(_take(pieces, np.flatnonzero(keep)), children)
    lo_sum = done_lo + lo.sum()
    hi_sum = done_hi + hi.sum()
    f_lo = (done_in + (pieces.area[:, None] * surely).sum(0)) / total
    f_hi = (done_maybe + (pieces.area[:, None] * maybe).sum(0)) / total
    return {"sq": (lo_sum / total, hi_sum / total), "frac": (np.clip(f_lo, 0, 1), np.clip(f_hi, 0, 1)),
            "area_cm2": total, "queries": target.queries - start, "converged": not over}


def fscore(p: float, r: float) -> float:
    """2 P R / (P + R), 0 when both are 0 (increasing in each)."""
    return 0.0 if p + r <= 0 else 2.0 * p * r / (p + r)


def pair_scores(pred: tuple[np.ndarray, np.ndarray], gt: tuple[np.ndarray, np.ndarray], thresholds,
                names, tol_chamfer: float, tol_f: float, max_queries: int = MAX_QUERIES) -> dict:
    """Exact Chamfer (cm^2) and F-scores at ``thresholds`` (cm) of two meshes in cm, each as (value, +- bound).

    ``tol_chamfer`` and ``tol_f`` are the half-widths aimed at; the bound reported is the one reached."""
    (vp, fp), (vg, fg) = pred, gt
    to_gt, to_pred = Target(vg, fg), Target(vp, fp)
    # each direction's width <= tol_chamfer makes the sum's half-width <= tol_chamfer; the F-score's slopes in
    # P and R are at most 2, so fraction widths of tol_f / 2 keep its half-width <= tol_f
    a = one_way(vp, fp, to_gt, thresholds, tol_chamfer, tol_f / 2, max_queries)  # precision side
    b = one_way(vg, fg, to_pred, thresholds, tol_chamfer, tol_f / 2, max_queries)  # recall side
    lo, hi = a["sq"][0] + b["sq"][0], a["sq"][1] + b["sq"][1]
    out = {"chamfer": ((lo + hi) / 2, (hi - lo) / 2)}
    for k, name in enumerate(names):
        f_lo = fscore(a["frac"][0][k], b["frac"][0][k])
        f_hi = fscore(a["frac"][1][k], b["frac"][1][k])
        out[name] = ((f_lo + f_hi) / 2, (f_hi - f_lo) / 2)
    out["queries"] = a["queries"] + b["queries"]
    out["converged"] = a["converged"] and b["converged"]
    return out


def centroid_penalty(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The Chamfer (cm^2) of a prediction collapsed to one point at the ground truth's area centroid c: the
    mean of |x - c|^2 over the surface (closed form per triangle) plus d(c, surface)^2. The penalty of a frame
    whose prediction is missing, unreadable or empty."""
    tri = vertices[faces]
    area = _areas(tri)
    cen = tri.mean(1)
    c = (area[:, None] * cen).sum(0) / area.sum()
    m = np.square(tri - cen[:, None]).sum(2).mean(1)
    spread = float((area * (np.square(cen - c).sum(1) + m / 4)).sum() / area.sum())
    d2, _ = Target(vertices, faces).query(c[None])
    return spread + float(d2[0])
