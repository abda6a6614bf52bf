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

A piece straddling a threshold has its area where d < t bounded by discs in its plane
(:mod:`hoisdf.scoring.recon_bounds`). Sub-triangles are split in four (edge midpoints) where their share of the
bounds' width is largest, until both widths are under the tolerances or the query budget is spent (the bound is
then wider, still rigorous, and says so). Distances are exact point-to-triangle distances
(:class:`hoidata.geometry.bvh.MeshBVH`) in float64, their rounding allowed for (:func:`rounding_limits`).
"""

from __future__ import annotations

import numpy as np

from hoidata.geometry.bvh import MeshBVH, morton_order
from hoisdf.scoring.recon_bounds import piece_bounds, plan_round, query, split_pieces

MAX_QUERIES = 4_000_000  # distance queries per direction of one part of one frame (about 1 GB of sub-triangles)


class Target:
    """The other surface: its hierarchy and triangles (cm), for squared distances and closest points."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices, self.faces = vertices, faces
        self.bvh = MeshBVH(vertices, faces, pose_shape=True)  # its tree a function of this mesh alone
        ref, lo, hi, blocks, first, count = self.bvh.wide()
        self.tree = (self.bvh.order, lo, hi, ref, blocks, first, count, self.bvh.tri)
        self.queries = 0

    def query(self, points: np.ndarray, hint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Squared distances (N,), closest points (N, 3) and faces (N,, the tree's leaf order) of points (N, 3);
        ``hint``: a face near each point (leaf order), else the points are visited along a Morton curve."""
        self.queries += len(points)
        points = np.ascontiguousarray(points, dtype=np.float64)
        if hint is not None:
            return query(points, hint, self.tree)
        visit = morton_order(points)
        d2, closest, face = query(points[visit], np.full(len(points), -1), self.tree)
        out = np.empty_like(d2), np.empty_like(closest), np.empty_like(face)
        for got, dst in zip((d2, closest, face), out):
            dst[visit] = got
        return out


def _areas(tri: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


FIELDS = ("tri", "fv", "pv", "hv", "area", "lo", "hi", "inside_lo", "inside_hi")
BOUNDS = ("area", "lo", "hi", "inside_lo", "inside_hi")  # zero for a piece no longer counted here


class Pieces:
    """Sub-triangles (``tri`` (n, 3, 3)) with their vertices' squared distances ``fv``, closest points ``pv`` and
    closest faces ``hv`` (the target tree's leaf order), and their bounds, computed once when they are made
    (:func:`hoisdf.scoring.recon_bounds.piece_bounds`): ``lo`` / ``hi`` of the integral of f, and per threshold
    ``inside_lo`` / ``inside_hi`` of its area where d < t. The first ``n`` rows of arrays with room to grow; a piece
    split or set aside stays in its row with its bounds zeroed (``live`` False) until :meth:`compact`."""

    def __init__(self, arrays: tuple):
        self.n = len(arrays[0])
        for name, a in zip(FIELDS, arrays):
            setattr(self, name, a)
        self.live = np.ones(self.n, bool)

    @classmethod
    def make(cls, tri: np.ndarray, fv: np.ndarray, pv: np.ndarray, hv: np.ndarray, target: Target, limits: tuple,
             discs: bool = True) -> Pieces:
        """``limits``: the squared thresholds taken in and out and f's slack (:func:`rounding_limits`)."""
        fc, pc, _ = target.query(tri.mean(1), np.ascontiguousarray(hv[:, 0]))
        return cls((tri, fv, pv, hv, *piece_bounds(tri, fv, pv, fc, pc, *limits, discs)))

    def view(self, name: str) -> np.ndarray:
        return getattr(self, name)[:self.n]

    def retire(self, idx: np.ndarray) -> None:
        """Stop counting the pieces ``idx`` here (their bounds were summed elsewhere, or their children hold them)."""
        for name in BOUNDS:
            getattr(self, name)[idx] = 0
        self.live[idx] = False

    def reserve(self, m: int) -> None:
        """Room for m more rows (the arrays at least doubled when they grow)."""
        if self.n + m > len(self.tri):
            room = max(self.n + m, 2 * len(self.tri))
            for name in (*FIELDS, "live"):
                old = getattr(self, name)
                new = np.zeros((room, *old.shape[1:]), old.dtype)
                new[:self.n] = old[:self.n]
                setattr(self, name, new)

    def compact(self) -> None:
        """Drop the rows no longer counted."""
        keep = np.flatnonzero(self.live[:self.n])
        for name in (*FIELDS, "live"):
            setattr(self, name, getattr(self, name)[keep])
        self.n = len(keep)

    def split(self, idx: np.ndarray, target: Target, limits: tuple, discs: bool = True) -> None:
        """Append the four children (edge midpoints) of the pieces ``idx``
        (:func:`hoisdf.scoring.recon_bounds.split_pieces`: seven distance queries each)."""
        self.reserve(4 * len(idx))
        target.queries += 7 * len(idx)
        split_pieces(*(getattr(self, name) for name in FIELDS), idx, self.n, target.tree, *limits, discs)
        self.live[self.n:self.n + 4 * len(idx)] = True
        self.n += 4 * len(idx)


ROUNDING = 64  # roundings of a coordinate's size allowed in a computed distance (each is some tens of operations)


def rounding_limits(a: np.ndarray, b: np.ndarray, thresholds: np.ndarray, tol_sq: float) -> tuple[tuple, bool]:
    """((squared thresholds (2, k) taken in and out by a computed distance's rounding, f's rounding), whether
    refining can still narrow the bounds) for surfaces with vertices ``a`` and ``b``: a distance computed from
    coordinates of size S is off by up to ROUNDING eps S, its square by ROUNDING eps S^2 (S = 1 m: 1e-12 cm and
    1e-10 cm^2). Coordinates no float64 can hold to the tolerances (a prediction scaled by 1e30) give bounds as
    wide as that rounding, honestly, and no refinement."""
    size = float(max(np.abs(a).max(), np.abs(b).max()))
    err = ROUNDING * np.finfo(np.float64).eps * size
    slack = err * size
    t2 = np.stack([np.maximum(thresholds - err, 0.0) ** 2 - slack, (thresholds + err) ** 2 + slack])
    return (t2, slack), bool(4 * slack < tol_sq and err < 1e-3 * thresholds.min())


RETIRE = 0.25  # a piece whose bound is this small a share of its area's part of the tolerances is set aside


def one_way(vertices: np.ndarray, faces: np.ndarray, target: Target, thresholds, tol_sq: float,
            tol_frac: float, max_queries: int = MAX_QUERIES, retire: float = RETIRE, discs: bool = True) -> dict:
    """Bounds of A's mean squared distance to B (cm^2) and of A's area fraction within each threshold (cm).

    Refines until the mean's bound is at most ``tol_sq`` wide and each fraction's at most ``tol_frac`` wide, or
    ``max_queries`` distance queries were made: each round splits the pieces that hold the larger half of the
    bounds' width. Each piece's bounds are computed once, when it is made. Pieces are set aside for good (their
    bounds summed) when they are settled: those whose width on the mean and on each fraction is at most ``retire``
    times their area's share of that tolerance (together at most ``retire`` times it, so the rest of the tolerance
    is left for the others), and those whose share of the width is negligible. Setting a piece aside only stops its
    refinement: the bounds stay rigorous whatever ``retire`` is (0: only negligible pieces). ``discs`` False bounds
    each fraction by whole pieces only (a piece straddling a threshold wholly undecided), as before the disc areas
    of :mod:`hoisdf.scoring.recon_bounds`.
    """
    thresholds = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
    start = target.queries
    fvert, pvert, hvert = target.query(vertices)
    limits, refinable = rounding_limits(vertices, target.vertices, thresholds, tol_sq)
    pieces = Pieces.make(vertices[faces], fvert[faces], pvert[faces], hvert[faces], target, limits, discs)
    total = float(pieces.area.sum())
    if not total > 0:
        raise ValueError("the surface has no area")
    done_lo = done_hi = 0.0
    done_in, done_maybe = np.zeros(len(thresholds)), np.zeros(len(thresholds))
    while True:
        budget = (max_queries - (target.queries - start)) // 7
        over, chosen, settled = plan_round(*(getattr(pieces, name) for name in BOUNDS), pieces.live, pieces.n, total,
                                           tol_sq, tol_frac, retire, (done_hi - done_lo) / total,
                                           (done_maybe - done_in) / total, budget)
        if not over or not refinable or target.queries - start >= max_queries:
            break
        done_lo += pieces.lo[settled].sum()
        done_hi += pieces.hi[settled].sum()
        done_in += pieces.inside_lo[settled].sum(0)
        done_maybe += pieces.inside_hi[settled].sum(0)
        pieces.split(chosen, target, limits, discs)
        pieces.retire(settled)
        pieces.retire(chosen)
        if 2 * int(pieces.live[:pieces.n].sum()) < pieces.n:
            pieces.compact()
    lo_sum, hi_sum = done_lo + pieces.view("lo").sum(), done_hi + pieces.view("hi").sum()
    f_lo = (done_in + pieces.view("inside_lo").sum(0)) / total
    f_hi = (done_maybe + pieces.view("inside_hi").sum(0)) / total
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
    d2, _, _ = Target(vertices, faces).query(c[None])
    return spread + float(d2[0])
