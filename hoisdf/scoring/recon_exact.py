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

import numba
import numpy as np

from hoidata.geometry.bvh import MeshBVH

MAX_QUERIES = 4_000_000  # distance queries per direction of one part of one frame (about 1 GB of sub-triangles)


class Target:
    """The other surface: its hierarchy and triangles (cm), for squared distances and closest points."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices, self.faces = vertices, faces
        self.bvh = MeshBVH(vertices, faces, pose_shape=True)  # its tree a function of this mesh alone
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


@numba.njit(cache=True)
def piece_bounds(tri, fv, pv, fc, pc, t2):
    """Per sub-triangle (vertices ``tri``, vertex squared distances ``fv`` and closest points ``pv``, centroid
    squared distance ``fc`` and closest point ``pc``; squared thresholds ``t2``): area, lower and upper bound of the
    integral of f, and per threshold whether d < t surely / maybe holds on the whole piece (module docstring)."""
    n, k = tri.shape[0], t2.shape[0]
    area, lo, hi = np.empty(n), np.empty(n), np.empty(n)
    surely, maybe = np.empty((n, k), np.bool_), np.empty((n, k), np.bool_)
    for i in range(n):
        a = tri[i, 1] - tri[i, 0]
        b = tri[i, 2] - tri[i, 0]
        cx = a[1] * b[2] - a[2] * b[1]
        cy = a[2] * b[0] - a[0] * b[2]
        cz = a[0] * b[1] - a[1] * b[0]
        area[i] = 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)
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
        lo[i], hi[i] = min(low, high), high  # equal up to rounding where the piece is a point
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
        for t in range(k):
            surely[i, t] = sup2 < t2[t]
            maybe[i, t] = surely[i, t] or inf2 < t2[t]
    return area, lo, hi, surely, maybe


FIELDS = ("tri", "fv", "pv", "area", "lo", "hi", "surely", "maybe")


class Pieces:
    """Sub-triangles (``tri`` (n, 3, 3)) with their vertices' squared distances ``fv`` and closest points ``pv``, and
    their bounds, computed once when they are made: ``lo`` / ``hi`` of the integral of f, and per threshold whether
    the piece lies surely within it (``surely``) or maybe (``maybe``)."""

    def __init__(self, **arrays):
        for name in FIELDS:
            setattr(self, name, arrays[name])

    @classmethod
    def make(cls, tri: np.ndarray, fv: np.ndarray, pv: np.ndarray, target: Target, thresholds: np.ndarray) -> Pieces:
        fc, pc = target.query(tri.mean(1))
        area, lo, hi, surely, maybe = piece_bounds(tri, fv, pv, fc, pc, np.square(thresholds))
        return cls(tri=tri, fv=fv, pv=pv, area=area, lo=lo, hi=hi, surely=surely, maybe=maybe)

    def take(self, idx: np.ndarray) -> Pieces:
        return Pieces(**{name: getattr(self, name)[idx] for name in FIELDS})

    def join(self, other: Pieces) -> Pieces:
        return Pieces(**{name: np.concatenate([getattr(self, name), getattr(other, name)]) for name in FIELDS})

    def split(self, idx: np.ndarray, target: Target, thresholds: np.ndarray) -> Pieces:
        """The four children (edge midpoints) of the pieces ``idx``."""
        tri, fv, pv = self.tri[idx], self.fv[idx], self.pv[idx]
        mid = np.stack([(tri[:, 0] + tri[:, 1]) / 2, (tri[:, 1] + tri[:, 2]) / 2, (tri[:, 2] + tri[:, 0]) / 2], 1)
        fm, pm = target.query(mid.reshape(-1, 3))
        fm, pm = fm.reshape(-1, 3), pm.reshape(-1, 3, 3)
        # children: (v0, m01, m20), (m01, v1, m12), (m20, m12, v2), (m01, m12, m20)
        pts = np.concatenate([tri, mid], 1)
        fs, ps = np.concatenate([fv, fm], 1), np.concatenate([pv, pm], 1)
        kids = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])
        return Pieces.make(pts[:, kids].reshape(-1, 3, 3), fs[:, kids].reshape(-1, 3), ps[:, kids].reshape(-1, 3, 3),
                           target, thresholds)


RETIRE = 0.25  # a piece whose bound is this small a share of its area's part of the tolerances is set aside


def one_way(vertices: np.ndarray, faces: np.ndarray, target: Target, thresholds, tol_sq: float,
            tol_frac: float, max_queries: int = MAX_QUERIES, retire: float = RETIRE) -> dict:
    """Bounds of A's mean squared distance to B (cm^2) and of A's area fraction within each threshold (cm).

    Refines until the mean's bound is at most ``tol_sq`` wide and each fraction's at most ``tol_frac`` wide, or
    ``max_queries`` distance queries were made: each round splits the pieces that hold the larger half of the
    bounds' width. Each piece's bounds are computed once, when it is made. Pieces are set aside for good (their
    bounds summed) when they are settled: those that straddle no threshold and whose width is at most ``retire``
    times their area's share of ``tol_sq`` (together at most ``retire * tol_sq``, so the rest of the tolerance is
    left for the others), and those whose share of the width is negligible. Setting a piece aside only stops its
    refinement: the bounds stay rigorous whatever ``retire`` is (0: only negligible pieces).
    """
    thresholds = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
    start = target.queries
    fvert, pvert = target.query(vertices)
    pieces = Pieces.make(vertices[faces], fvert[faces], pvert[faces], target, thresholds)
    total = float(pieces.area.sum())
    if not total > 0:
        raise ValueError("the surface has no area")
    done_lo = done_hi = 0.0
    done_in, done_maybe = np.zeros(len(thresholds)), np.zeros(len(thresholds))
    while True:
        w_sq = (pieces.hi - pieces.lo) / total
        w_frac = (pieces.area[:, None] * (pieces.maybe & ~pieces.surely)) / total
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
        keep = np.zeros(len(score), bool)
        keep[rest] = score[rest] > 1e-6 * cum[-1] / max(len(score), 1)
        keep[rest] &= (w_sq[rest] > retire * tol_sq * pieces.area[rest] / total) | (w_frac[rest] > 0).any(1)
        settled = ~keep
        settled[chosen] = False
        done_lo += pieces.lo[settled].sum()
        done_hi += pieces.hi[settled].sum()
        done_in += (pieces.area[settled, None] * pieces.surely[settled]).sum(0)
        done_maybe += (pieces.area[settled, None] * pieces.maybe[settled]).sum(0)
        pieces = pieces.take(np.flatnonzero(keep)).join(pieces.split(chosen, target, thresholds))
    lo_sum, hi_sum = done_lo + pieces.lo.sum(), done_hi + pieces.hi.sum()
    f_lo = (done_in + (pieces.area[:, None] * pieces.surely).sum(0)) / total
    f_hi = (done_maybe + (pieces.area[:, None] * pieces.maybe).sum(0)) / total
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
