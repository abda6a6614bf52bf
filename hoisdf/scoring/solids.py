"""Solids bounded by triangle meshes, and the volume of a region of them to a guaranteed tolerance.

A mesh bounds the solid of points whose generalized winding number w (Jacobson, Kavan and Sorkine-Hornung 2013)
satisfies |w| > 1/2. For a closed mesh (every directed edge matched by its reverse) w is an integer that only
changes across the surface, so the solid is exact even where the mesh passes through itself (a posed MANO thumb
inside the palm: w = 2 there, still inside) or is wound inward (w = -1). Distances to the surface are exact
(:class:`hoidata.geometry.bvh.MeshBVH`), winding numbers come from signed ray crossing counts
(:func:`hoidata.geometry.signs.winding_numbers`); an open mesh gets libigl's fast winding number, exact near 1/2.

Volumes (:func:`region_volume`) come from an adaptive octree with exact bounds: if the distance from a cell's
centre to a mesh's surface exceeds the cell's half-diagonal, no surface passes through the cell, so w (hence
inside/outside) is the same at every point of it as at the centre. Cells decided for every mesh are wholly in or
out of the region. Of an undecided cell, the ball around its centre whose radius is that distance is still known
(in the region when the centre is, out otherwise); the rest of the cell is not. Undecided cells are split in 8
until what is not known adds up to at most the tolerance. The true volume lies between the known-in volume and
the volume not known to be out, so the error bound is rigorous for closed meshes (for an open one w also varies
continuously across its holes, and no bound is claimed). An undecided cell that only one mesh's surface crosses,
away from that surface's irregular parts, gets its exact volume instead (:mod:`hoisdf.scoring.cell_volume`):
then only cells along the curves where two surfaces meet stay undecided.

All positions share one frame and unit (metres here); volumes are in cubic units of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numpy as np

from hoidata.geometry.bvh import MeshBVH
from hoidata.geometry.sdf import AMBIGUOUS, WINDING_INSIDE, validate_mesh
from hoidata.geometry.signs import is_closed, winding_numbers
from hoisdf.scoring.cell_volume import column_integrals, crosses, face_parts, orientation

ROOT_CELLS = 16  # the first level splits the box's longest side into this many cubes
MAX_CELLS = 20_000_000  # cell-centre evaluations one volume may spend before it gives up (a few minutes)
SLACK = 1e-9  # relative margin on the half-diagonal: rounding never decides a cell the surface touches


class MeshSolid:
    """One mesh's solid: exact distance to its surface and winding number at query points.

    Args:
        vertices: (V, 3) float, metres. faces: (F, 3) int indices, wound outward (either way for closed meshes:
            only |w| is used).
    """

    def __init__(self, vertices, faces):
        self.vertices, self.faces = validate_mesh(vertices, faces)
        self.bvh = MeshBVH(self.vertices, self.faces, pose_shape=True)  # volumes sum in tree order: one tree a pose
        self.closed = is_closed(self.faces)
        self.lo, self.hi = self.vertices.min(0), self.vertices.max(0)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) exact unsigned distance of (N, 3) float64 points to the surface."""
        return self.bvh.closest(np.ascontiguousarray(points, dtype=np.float64))[0] if len(points) else np.zeros(0)

    def winding(self, points: np.ndarray) -> np.ndarray:
        """(N,) generalized winding number at (N, 3) points (an integer for a closed mesh, 0 outside its box)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        out = np.zeros(len(points))
        boxed = np.flatnonzero(np.all((points >= self.lo) & (points <= self.hi), axis=1))
        if len(boxed) == 0:
            return out
        query = np.ascontiguousarray(points[boxed])
        if self.closed:
            out[boxed] = winding_numbers(query, self.vertices, self.faces, self.bvh)
            return out
        w = igl.fast_winding_number(self.vertices, self.faces, query)
        unsure = np.flatnonzero(np.abs(np.abs(w) - WINDING_INSIDE) < AMBIGUOUS)
        if len(unsure):
            w[unsure] = igl.winding_number(self.vertices, self.faces, np.ascontiguousarray(query[unsure]))
        out[boxed] = w
        return out

    @staticmethod
    def _soup(tri: np.ndarray) -> MeshSolid | None:
        """A triangle soup (K, 3, 3) as a solid (for its distances), None when empty."""
        if len(tri) == 0:
            return None
        return MeshSolid(tri.reshape(-1, 3), np.arange(3 * len(tri), dtype=np.int64).reshape(-1, 3))

    def regular(self) -> tuple[float, MeshSolid | None]:
        """(s, irregular): the orientation s (+1 outward, -1 inward) and the parts of the surface that may border
        anything but w = 0 and w = s (:func:`hoisdf.scoring.cell_volume.face_parts`) as a triangle-soup solid,
        None when there are none. Computed once per closed solid."""
        if not hasattr(self, "_regular"):
            sign = orientation(self.vertices, self.faces)
            irregular, boundary = face_parts(self, sign)
            self._boundary = self._soup(boundary)
            self._regular = (sign, self._soup(irregular))
        return self._regular

    def boundary_distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) distance to the surface but its buried parts (:func:`~hoisdf.scoring.cell_volume.face_parts`): in a
        ball of that radius |w| > 1/2 is as at its centre (a segment from the centre crosses only buried faces,
        between values of |w| >= 1). Plain :meth:`distance` for an open mesh or one with no buried face."""
        if not self.closed:
            return self.distance(points)
        self.regular()
        return (self._boundary or self).distance(points)

    def cube_volumes(self, centres: np.ndarray, edge: float) -> tuple[np.ndarray, np.ndarray]:
        """(K,) s x the integral of w over each cube (its volume in the solid where only regular faces meet it),
        and (K,) bool: some face meets it (:func:`hoisdf.scoring.cell_volume.column_integrals`)."""
        out, touched = np.zeros(len(centres)), np.zeros(len(centres), bool)
        b = self.bvh
        column_integrals(np.ascontiguousarray(centres, dtype=np.float64), float(edge), b.boxes, b.left, b.start,
                         b.count, b.tri, out, touched)
        return self.regular()[0] * out, touched

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) exact distance, negative inside the solid (|w| > 1/2)."""
        dist = self.distance(points)
        return np.where(np.abs(self.winding(points)) > WINDING_INSIDE, -dist, dist)


@dataclass(frozen=True)
class VolumeEstimate:
    """A volume with rigorous bounds (closed meshes): ``lower <= true volume <= upper``.

    ``volume``: the cells wholly in the region plus the undecided cells whose centre is in it (the midpoint
    rule); it lies between the bounds, so ``|volume - true| <= upper - lower`` (the error bound). ``cells``: cell
    centres evaluated; ``guaranteed``: every mesh was closed, so the bounds hold (volumes in m^3 here)."""

    volume: float
    lower: float
    upper: float
    cells: int
    guaranteed: bool

    @property
    def error_bound(self) -> float:
        return self.upper - self.lower


@dataclass(frozen=True)
class Part:
    """One factor of a region: points where ``|w| > level`` for this solid (0.5: inside; 1.5: covered twice).

    For a level above 1, ``tangled`` is the solid's :func:`tangled_surface` (None: it has none): a ball that
    it does not enter is all as its centre, even where the rest of the surface passes through it."""

    solid: MeshSolid
    level: float = WINDING_INSIDE
    tangled: MeshSolid | None = None


def _grid(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Centres (K, 3) and edge of cubes covering the box, ROOT_CELLS along its longest side."""
    edge = float((hi - lo).max()) / ROOT_CELLS
    counts = np.maximum(1, np.ceil((hi - lo) / edge - 1e-9).astype(np.int64))
    start = (lo + hi) / 2 - (counts - 1) * edge / 2
    axes = np.meshgrid(*[start[k] + edge * np.arange(counts[k]) for k in range(3)], indexing="ij")
    return np.stack([a.reshape(-1) for a in axes], axis=1), edge


def _children(centres: np.ndarray, edge: float) -> np.ndarray:
    """The 8 sub-cube centres of each cube (K, 3) of this edge -> (8 K, 3)."""
    offsets = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * edge / 4
    return (centres[:, None, :] + offsets[None]).reshape(-1, 3)


def _classify(part: Part, points: np.ndarray, radius: float, given: np.ndarray | None = None,
              given_member: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(member at the centre (K,) bool, radius (K,) of a ball around the centre that is all as the centre) for
    cells of this half-diagonal: the cell is decided when that radius exceeds the half-diagonal.

    ``given`` (K,) bool marks centres whose membership is already known (``given_member``): they lie in a ball
    that was all as its centre one level up, so the winding number (the costly ray casts) is not computed there.
    """
    dist = part.solid.boundary_distance(points) if part.level <= 1.0 else part.solid.distance(points)
    member = np.zeros(len(points), bool)
    ask = np.ones(len(points), bool) if given is None else ~given
    if given is not None:
        member[given] = given_member[given]
    if ask.any():
        member[ask] = np.abs(part.solid.winding(points[ask])) > part.level
    if part.level > 1.0 and not (dist > radius).all():
        # A ball that no tangled face enters meets only faces that cross no other face and have |w| <= 1 on both
        # sides: a segment from the centre to any point of the ball either crosses nothing (same w) or ends beside
        # such a face (|w| <= 1); and if |w| >= 2 at the centre, no such face can enter the ball at all. Either
        # way the whole ball is as its centre.
        far = np.inf if part.tangled is None else part.tangled.distance(points)
        dist = np.maximum(dist, far)
    return member, dist


def ball_in_cube(rho: np.ndarray, edge: float) -> np.ndarray:
    """A lower bound of the volume of a ball of radius ``rho`` (K,) and the cube of this edge around its centre:
    exact up to rho = edge / sqrt(2) (the ball less the 6 caps beyond the faces), that value beyond it."""
    a = edge / 2
    rho = np.minimum(rho, np.sqrt(2) * a)
    cap = np.maximum(rho - a, 0.0)
    return 4.0 / 3.0 * np.pi * rho ** 3 - 2.0 * np.pi * cap ** 2 * (2 * rho + a)


def _level(parts: list[Part], centres: np.ndarray, radius: float, hints=None):
    """Classify one level's cells: alive (not known to be out), known (wholly in), member (centre in), and the
    radii of the balls around the centres known to be in (rho_in) resp. out (rho_out); plus evaluations spent and
    each part's (member, radius) per cell (False / 0 where a part was not asked). ``hints``: per part, (known
    (K,) bool, member (K,) bool) centres whose membership is already known (see :func:`_classify`)."""
    n = len(centres)
    alive, known, member = np.ones(n, bool), np.ones(n, bool), np.ones(n, bool)
    rho_in, rho_out, cells = np.full(n, np.inf), np.zeros(n), 0
    per_member, per_rho = np.zeros((len(parts), n), bool), np.zeros((len(parts), n))
    for p, part in enumerate(parts):
        idx = np.flatnonzero(alive)
        if len(idx) == 0:
            break
        given, given_member = (None, None) if hints is None else (hints[p][0][idx], hints[p][1][idx])
        m, rho = _classify(part, centres[idx], radius, given, given_member)
        per_member[p, idx], per_rho[p, idx] = m, rho
        cells += len(idx)
        c = rho > radius
        alive[idx[c & ~m]] = False
        known[idx[~c]] = False
        member[idx[~m]] = False
        rho_in[idx[m]] = np.minimum(rho_in[idx[m]], rho[m])
        rho_out[idx[~m]] = np.maximum(rho_out[idx[~m]], rho[~m])
    return alive, known, member, rho_in, rho_out, cells, (per_member, per_rho)


def _child_hints(parts: list[Part], per_part, open_: np.ndarray, radius: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """For the children (:func:`_children` order) of the open cells: per part, which child centres lie in the
    parent's ball that is all as the parent's centre, and their membership. A child centre is a quarter of the
    parent's diagonal (less than half its ``radius``) from the parent's centre. Only for inside/outside parts
    (level <= 1), where the ball is exact for a closed mesh; a covered-twice part's ball also relies on
    :func:`tangled_surface`, which misses folds between faces sharing a vertex, so its centres are all asked."""
    per_member, per_rho = per_part
    return [(np.repeat(rho[open_] > radius / 2, 8) if part.level <= 1.0 else np.zeros(8 * int(open_.sum()), bool),
             np.repeat(m[open_], 8)) for part, m, rho in zip(parts, per_member, per_rho)]


def _resolve(parts: list[Part], centres: np.ndarray, edge: float, radius: float, open_: np.ndarray,
             per_part) -> tuple[np.ndarray, np.ndarray, int]:
    """Undecided cells whose volume is computed exactly: (resolved (K,) bool, volume (K,), evaluations).

    A cell qualifies when one inside/outside part of a closed mesh is undecided there, every other part holds
    it wholly (the cell is alive, so they are in), and no irregular face of that mesh comes within the cell's
    half-diagonal of its centre: then w takes only the values 0 and s in it, and the region's volume in the
    cell is s x the integral of w (:meth:`MeshSolid.cube_volumes`), or, where no face meets the cell, the cell
    or nothing as its centre."""
    per_member, per_rho = per_part
    undecided = per_rho <= radius
    resolved, volume, spent = np.zeros(len(centres), bool), np.zeros(len(centres)), 0
    for p, part in enumerate(parts):
        if part.level > 1.0 or not part.solid.closed:
            continue
        idx = np.flatnonzero(open_ & undecided[p] & (undecided.sum(0) == 1))
        if len(idx) == 0:
            continue
        irregular = part.solid.regular()[1]
        if irregular is not None:
            idx = idx[irregular.distance(centres[idx]) > radius]
        vol, touched = part.solid.cube_volumes(centres[idx], edge)
        spent += len(idx)
        vol = np.where(touched, vol, np.where(per_member[p, idx], edge ** 3, 0.0))
        ok = (vol >= -1e-8 * edge ** 3) & (vol <= (1 + 1e-8) * edge ** 3)  # rounding only; else refine
        resolved[idx[ok]], volume[idx[ok]] = True, np.clip(vol[ok], 0.0, edge ** 3)
    return resolved, volume, spent


def region_volume(parts: list[Part], lo, hi, tolerance: float, rel_tolerance: float = 0.0,
                  max_cells: int = MAX_CELLS, strict: bool = True,
                  exact_cells: bool = True) -> VolumeEstimate:
    """Volume of the intersection of the parts' regions within the box [lo, hi], to within
    max(``tolerance``, ``rel_tolerance`` x the volume).

    Args:
        parts: the factors (a point is in the region when it is in every part).
        lo: (3,) lowest corner of a box holding the region (e.g. the overlap of the meshes' bounding boxes).
        hi: (3,) its highest corner.
        tolerance: the largest acceptable error bound, cubic units (> 0).
        rel_tolerance: also acceptable: this fraction of the volume (0: off). It is checked against the
            certain part of the volume (a lower bound), so it holds relative to the true volume.
        exact_cells: compute the volume of cells crossed by one regular surface exactly (:func:`_resolve`),
            so only cells along the curves where surfaces meet (or near irregular faces) stay undecided: the
            bound then shrinks with the square of the cell edge instead of the edge. False: the ball bound only.
        max_cells: evaluation budget; a tolerance that needs more raises ValueError instead of running on, or
            with ``strict`` False returns what it has: rigorous bounds, wider than asked.

    Returns:
        :class:`VolumeEstimate` with ``error_bound <= max(tolerance, rel_tolerance * lower)``.
    """
    if not tolerance > 0:
        raise ValueError(f"tolerance must be positive, got {tolerance}")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    guaranteed = all(p.solid.closed for p in parts)
    if np.any(hi <= lo):
        return VolumeEstimate(0.0, 0.0, 0.0, 0, guaranteed)
    centres, edge = _grid(lo, hi)
    decided, cells, hints, slack = 0.0, 0, None, 0.0
    while True:
        radius, cell = edge * np.sqrt(3) / 2 * (1 + SLACK), edge ** 3
        alive, known, member, rho_in, rho_out, spent, per_part = _level(parts, centres, radius, hints)
        cells += spent
        decided += float((alive & known).sum()) * cell
        open_ = alive & ~known
        if exact_cells and open_.any():
            resolved, volume, spent = _resolve(parts, centres, edge, radius, open_, per_part)
            cells += spent
            decided += float(volume[resolved].sum())
            slack += 1e-8 * cell * float(resolved.sum())  # far above the rounding of the column sums
            open_ &= ~resolved
        # An undecided cell is still known around its centre: a ball of rho_in in the region when the centre is,
        # one of rho_out outside it otherwise (rho < the half-diagonal here, so 1 - 52 % of the cell, or less).
        inside, outside = open_ & member, open_ & ~member
        sure_in = float(ball_in_cube(rho_in[inside], edge).sum())
        sure_out = float(ball_in_cube(rho_out[outside], edge).sum())
        lower = decided + sure_in - slack
        upper = decided + float(open_.sum()) * cell - sure_out + slack
        estimate = decided + float(inside.sum()) * cell  # the midpoint rule on the undecided cells
        if upper - lower <= max(tolerance, rel_tolerance * lower):
            return VolumeEstimate(estimate, lower, upper, cells, guaranteed)
        if cells + 8 * int(open_.sum()) * len(parts) > max_cells:
            if not strict:
                return VolumeEstimate(estimate, lower, upper, cells, guaranteed)
            raise ValueError(f"tolerance {tolerance:.3g} needs more than {max_cells} cell evaluations "
                             f"(bounds still {upper - lower:.3g} apart); ask for a larger tolerance")
        hints = _child_hints(parts, per_part, open_, radius)
        centres, edge = _children(centres[open_], edge), edge / 2


# ---------------------------------------------------------------- where a closed mesh passes through itself

def self_crossing_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) bool: faces that cross another face sharing no vertex with them (see
    :func:`hoisdf.scoring.cell_volume.crossing_parts`; a fold between neighbouring faces goes unnoticed)."""
    vertices, faces = validate_mesh(vertices, faces)
    return crosses(MeshSolid(vertices, faces), vertices[faces], np.arange(len(faces)))


def _tangled(solid: MeshSolid, tri: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """(K,) bool: triangles (parts of faces ``parent``) that cross another face or have a winding number in front of
    them other than 0 or -1 (so that |w| may exceed 1 on one of their sides)."""
    v, f = solid.vertices, solid.faces
    normal = np.cross(v[f[parent, 1]] - v[f[parent, 0]], v[f[parent, 2]] - v[f[parent, 0]])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    step = 1e-7 * float(np.linalg.norm(solid.hi - solid.lo))  # off the face, far below any feature size
    front = tri.mean(1) + step * np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    return crosses(solid, tri, parent) | ~np.isin(np.rint(solid.winding(front)), (-1.0, 0.0))


def tangled_surface(solid: MeshSolid, levels: int = 3) -> tuple[np.ndarray, np.ndarray] | None:
    """The parts of a closed mesh's surface that may border a region of |w| >= 2, as a triangle soup
    (vertices (3 K, 3), faces (K, 3)), or None when there are none.

    Every other face (or part of one) crosses no face and separates w = 0 from w = 1 (or -1 from 0 where wound
    inward). Tangled faces are split in 4 at their edge midpoints ``levels`` times, keeping the parts that are
    still tangled: what remains hugs the self-intersection curves and the faces inside the rest of the solid.
    """
    f = solid.faces
    parent = np.flatnonzero(_tangled(solid, solid.vertices[f], np.arange(len(f))))
    tri = solid.vertices[f[parent]]
    for _ in range(levels):
        if len(tri) == 0:
            break
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tri = np.stack([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))], 1).reshape(-1, 3, 3)
        parent = np.repeat(parent, 4)
        keep = _tangled(solid, tri, parent)
        tri, parent = tri[keep], parent[keep]
    if len(tri) == 0:
        return None
    return tri.reshape(-1, 3), np.arange(3 * len(tri), dtype=np.int64).reshape(-1, 3)
