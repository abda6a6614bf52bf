"""Mesh checks, repair and exact-vertex-count simplification for object models.

Everything here works on plain arrays: vertices ``(V, 3)`` float64 in metres and faces ``(F, 3)``
int64 vertex indices. The public functions take and return :class:`trimesh.Trimesh` objects so
callers can render or query them, but the math lives in small pure functions on arrays.

Why a repair step at all: textured OBJ files (every YCB ``textured_simple.obj``) duplicate vertices
along UV seams, so the loaded mesh is a set of open charts even when the physical surface is closed.
Signed distances need a closed, consistently wound surface, so we rebuild that from positions only.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import fast_simplification
import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

from hoidata.errors import DataError
from hoidata.geometry.surface import signed_volumes, split_longest_edges

# Vertices closer than 10 nm are the same point; OBJ seam duplicates are bit-identical anyway.
MERGE_DECIMALS = 8
# A hole is "small" and gets closed with a fan when its boundary has at most MAX_HOLE_EDGES edges
# and a perimeter of at most MAX_HOLE_PERIMETER times the bounding-box diagonal (about a 1 cm hole
# in a 15 cm object); anything bigger is a real opening and is reported, not papered over.
MAX_HOLE_EDGES = 64
MAX_HOLE_PERIMETER = 0.2


@dataclass
class MeshReport:
    """What :func:`check_mesh` found. ``volume`` (m^3) is the signed divergence-theorem volume and is
    only meaningful when ``watertight``; ``problems`` is empty for a mesh that is safe for SDFs."""

    n_vertices: int
    n_faces: int
    watertight: bool
    winding_consistent: bool
    volume: float
    n_components: int
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _half_edges(faces: np.ndarray) -> np.ndarray:
    """(3F, 2) directed edges; row 3*f + k is the edge from corner k to corner k+1 of face f."""
    return faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def _edge_groups(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every half-edge, the id of its undirected edge, and how many half-edges share that id."""
    und = np.sort(_half_edges(faces), axis=1)
    _, inverse, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    return inverse, counts[inverse]


def _vertex_components(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """(V,) component label of every vertex, vertices linked by face edges."""
    e = _half_edges(faces)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)[1]


def check_mesh(mesh: trimesh.Trimesh) -> MeshReport:
    """Describe a mesh's fitness for signed distances without changing it.

    Watertight means every edge is shared by exactly two faces; consistent winding means no
    directed edge occurs twice. Counts are taken on the mesh as given, so a raw textured OBJ
    reports its UV seams as boundary edges.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return MeshReport(len(vertices), 0, False, False, 0.0, 0, ["no faces"])
    problems = []
    _, counts = np.unique(np.sort(_half_edges(faces), axis=1), axis=0, return_counts=True)
    n_boundary, n_nonmanifold = int((counts == 1).sum()), int((counts > 2).sum())
    watertight = n_boundary == 0 and n_nonmanifold == 0
    _, dir_counts = np.unique(_half_edges(faces), axis=0, return_counts=True)
    winding = bool((dir_counts == 1).all())
    volume = float(signed_volumes(vertices, faces).sum())
    if n_boundary:
        problems.append(f"{n_boundary} boundary edges (not watertight)")
    if n_nonmanifold:
        problems.append(f"{n_nonmanifold} non-manifold edges (shared by more than two faces)")
    if not winding:
        problems.append("inconsistent winding (neighbouring faces disagree on orientation)")
    if watertight and volume <= 0:
        problems.append(f"non-positive volume {volume:.3e} m^3 (normals point inward)")
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    if repeated.any():
        problems.append(f"{int(repeated.sum())} degenerate faces (repeated vertex)")
    n_dup = len(faces) - len(np.unique(np.sort(faces, axis=1), axis=0))
    if n_dup:
        problems.append(f"{n_dup} duplicate faces")
    n_unused = len(vertices) - len(np.unique(faces))
    if n_unused:
        problems.append(f"{n_unused} unreferenced vertices")
    labels = _vertex_components(len(vertices), faces)
    n_components = len(np.unique(labels[faces[:, 0]]))
    return MeshReport(len(vertices), len(faces), watertight, winding, volume, n_components, problems)


def merge_by_position(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weld vertices that share a position (to MERGE_DECIMALS), dropping UV/normal seams."""
    key = np.round(vertices, MERGE_DECIMALS)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    # Keep the welded vertices in order of first appearance so the result is stable and readable.
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[first[order]], rank[inverse.ravel()][faces]


def drop_bad_faces(faces: np.ndarray) -> np.ndarray:
    """Remove faces with a repeated vertex and duplicates of the same vertex triple.

    A triple that occurs exactly twice with opposite orientation is an internal double wall (two
    closed parts glued face to face); dropping both copies joins the parts into one closed body.
    """
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[ok]
    _, first, inverse, counts = np.unique(
        np.sort(faces, axis=1), axis=0, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    keep = np.zeros(len(faces), dtype=bool)
    keep[first] = True
    order = np.argsort(inverse, kind="stable")
    pairs = order[counts[inverse[order]] == 2].reshape(-1, 2)  # the two copies of each doubled triple
    f0, f1 = faces[pairs[:, 0]], faces[pairs[:, 1]]
    same = np.any([(np.roll(f0, k, axis=1) == f1).all(axis=1) for k in range(3)], axis=0)
    keep[pairs[~same].ravel()] = False
    return faces[keep]


def drop_unreferenced(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove vertices no face uses, keeping the order of the rest."""
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return vertices[used], remap[faces]


def fix_winding(faces: np.ndarray) -> np.ndarray:
    """Flip faces so that neighbours across every two-face edge traverse it in opposite directions.

    Breadth-first over the face graph from one seed face per component (a virtual root links the
    seeds, so a single traversal covers all components); a face's flip state is its parent's,
    toggled when the two faces run their shared edge the same way. Non-manifold edges are ignored.
    """
    n = len(faces)
    group, count = _edge_groups(faces)
    halves = np.flatnonzero(count == 2)
    pairs = halves[np.argsort(group[halves], kind="stable")].reshape(-1, 2)
    directed = _half_edges(faces)
    fa, fb = pairs[:, 0] // 3, pairs[:, 1] // 3
    same = directed[pairs[:, 0], 0] == directed[pairs[:, 1], 0]
    if not same.any():
        return faces
    # weight 1: consistent neighbours, 2: one must flip; the virtual root n links with weight 1.
    ordered = np.stack([np.minimum(fa, fb), np.maximum(fa, fb)], 1)
    pair_key, first = np.unique(ordered, axis=0, return_index=True)
    weight = np.where(same[first], 2.0, 1.0)
    seeds = np.unique(_face_components(n, pair_key), return_index=True)[1]
    rows = np.concatenate([pair_key[:, 0], np.full(len(seeds), n)])
    cols = np.concatenate([pair_key[:, 1], seeds])
    w = np.concatenate([weight, np.ones(len(seeds))])
    graph = coo_matrix((w, (rows, cols)), shape=(n + 1, n + 1)).tocsr()
    graph = (graph + graph.T).tocsr()
    order, pred = breadth_first_order(graph, n, directed=False, return_predecessors=True)
    nodes = order[1:]
    toggles = np.asarray(graph[nodes, pred[nodes]]).ravel() == 2.0
    flip = np.zeros(n + 1, dtype=bool)
    parent = pred.tolist()
    for node, toggle in zip(nodes.tolist(), toggles.tolist()):
        flip[node] = flip[parent[node]] ^ toggle
    out = faces.copy()
    out[flip[:n]] = out[flip[:n]][:, ::-1]
    return out


def _face_components(n_faces: int, pairs: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n_faces, n_faces))
    return connected_components(graph, directed=False)[1]


def orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip every connected component whose signed volume is negative, so normals point outward.

    Assumes components are separate solids; a hollow shell modelled as two nested components
    would get its inner wall flipped the wrong way (no YCB model is built like that).
    """
    labels = _vertex_components(len(vertices), faces)[faces[:, 0]]
    volume = np.bincount(labels, weights=signed_volumes(vertices, faces))
    flip = volume[labels] < 0
    out = faces.copy()
    out[flip] = out[flip][:, ::-1]
    return out


def fill_small_holes(vertices: np.ndarray, faces: np.ndarray, max_edges: int = MAX_HOLE_EDGES,
                     max_perimeter: float = MAX_HOLE_PERIMETER):
    """Close boundary loops of at most ``max_edges`` edges and a perimeter of at most
    ``max_perimeter`` times the bounding-box diagonal with a fan around the loop centroid.

    Loops through a vertex with several boundary edges are ambiguous and left open. New faces are
    wound against the boundary so they agree with the faces they close. Returns (vertices, faces).
    """
    _, count = _edge_groups(faces)
    border = _half_edges(faces)[count == 1]
    nxt: dict[int, int] = {}
    ambiguous = set()
    for u, v in border.tolist():
        if v in nxt:  # two boundary edges end here: a pinch vertex, loops through it are ambiguous
            ambiguous.add(v)
        nxt[v] = u  # the filling face runs the boundary edge backwards
    limit = max_perimeter * np.linalg.norm(vertices.max(0) - vertices.min(0))
    new_vertices, new_faces, seen = [], [], set()
    for start in sorted(nxt):
        loop, cur = [start], nxt[start]
        while cur != start and cur in nxt and cur not in seen and len(loop) <= max_edges:
            loop.append(cur)
            cur = nxt[cur]
        seen.update(loop)
        if cur != start or len(loop) > max_edges or ambiguous.intersection(loop) or len(loop) < 3:
            continue
        if np.linalg.norm(vertices[loop] - vertices[np.roll(loop, -1)], axis=1).sum() > limit:
            continue
        if len(loop) == 3:
            new_faces.append(loop)
            continue
        centre = len(vertices) + len(new_vertices)
        new_vertices.append(vertices[loop].mean(axis=0))
        new_faces.extend([loop[i], loop[(i + 1) % len(loop)], centre] for i in range(len(loop)))
    if not new_faces:
        return vertices, faces
    vertices = np.vstack([vertices, np.reshape(new_vertices, (-1, 3))])
    return vertices, np.vstack([faces, np.asarray(new_faces, dtype=np.int64)])


def repair_mesh(mesh: trimesh.Trimesh, path=None) -> tuple[trimesh.Trimesh, MeshReport]:
    """Geometry-only copy of ``mesh`` suitable for signed distances, and its :class:`MeshReport`.

    Steps: weld by position (removes UV seams), drop degenerate/duplicate faces and unused
    vertices, make winding consistent, fill small holes, orient each body to positive volume.
    A result that is still not watertight is returned as is, with the report (and a warning
    naming ``path``) saying so; SDF code then falls back to the generalized winding number.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise DataError(path, "faces", "mesh has no triangle faces")
    vertices, faces = merge_by_position(vertices, faces)
    faces = drop_bad_faces(faces)
    if len(faces) == 0:
        raise DataError(path, "faces", "every face is degenerate after welding vertices")
    vertices, faces = drop_unreferenced(vertices, faces)
    faces = fix_winding(faces)
    vertices, faces = fill_small_holes(vertices, faces)
    faces = orient_outward(vertices, fix_winding(faces))
    repaired = trimesh.Trimesh(vertices, faces, process=False)
    report = check_mesh(repaired)
    if report.problems:
        where = "mesh" if path is None else str(path)
        warnings.warn(f"{where}: after repair: {'; '.join(report.problems)}", stacklevel=2)
    return repaired, report


def decimate(vertices: np.ndarray, faces: np.ndarray, max_vertices: int, aim: int):
    """Quadric decimation (fast_simplification) to at most ``max_vertices``, aiming at ``aim``.

    fast_simplification targets a face count; a closed genus-0 mesh has F = 2V - 4, so we ask for
    2 * aim faces and lower the request by the overshoot until the vertex count fits. Open
    boundaries are kept in place (they would otherwise shrink by millimetres) unless the boundary
    alone has too many vertices to reach the target.
    """
    for preserve_border in (True, False):
        target = 2 * aim
        for _ in range(10):
            target = max(4, min(target, len(faces) - 1))
            v, f = fast_simplification.simplify(vertices, faces, target_count=target,
                                                preserve_border=preserve_border)
            f = drop_bad_faces(np.asarray(f, dtype=np.int64))
            v, f = drop_unreferenced(np.asarray(v, dtype=np.float64), f)
            if len(v) <= max_vertices:
                return v, f
            target -= 2 * (len(v) - aim)
    raise RuntimeError(f"decimation did not reach {max_vertices} vertices (got {len(v)})")


def simplify_mesh(mesh: trimesh.Trimesh, n_vertices: int = 1000) -> trimesh.Trimesh:
    """Evaluation mesh with exactly ``n_vertices`` vertices (geometry only, outward normals).

    The repaired (welded) geometry is decimated with quadric error metrics to about 2% fewer
    vertices than asked, then the longest edges are split at their midpoints until the count is
    exact. A mesh already at or below the target is only refined, so its surface is unchanged.
    """
    if n_vertices < 4:
        raise ValueError(f"n_vertices must be at least 4, got {n_vertices}")
    base, _ = repair_mesh(mesh)
    vertices, faces = np.asarray(base.vertices), np.asarray(base.faces)
    if len(vertices) > n_vertices:
        vertices, faces = decimate(vertices, faces, n_vertices, n_vertices - max(1, n_vertices // 50))
    vertices, faces = split_longest_edges(vertices, faces, n_vertices - len(vertices))
    return trimesh.Trimesh(vertices, faces, process=False)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points uniformly distributed by area on the triangles, reproducible from ``seed``."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    t = tri[idx]
    # sqrt trick: (1 - sqrt r1, sqrt r1 (1 - r2), sqrt r1 r2) is uniform on a triangle.
    return (1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2]


def _distance_to_mesh(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """(N,) unsigned distance (m) from points to the mesh surface; libigl if present, else trimesh."""
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    try:
        import igl  # optional dependency (hoisdf[sdf]); much faster than trimesh.proximity
    except ImportError:
        return trimesh.proximity.closest_point(trimesh.Trimesh(vertices, faces, process=False), points)[1]
    return np.sqrt(igl.point_mesh_squared_distance(np.ascontiguousarray(points), vertices, faces)[0])


def surface_error(simplified: trimesh.Trimesh, original: trimesh.Trimesh,
                  n_samples: int = 20000, seed: int = 0) -> dict:
    """Symmetric point-to-surface distance between two meshes, in metres: ``{"max": .., "mean": ..}``.

    ``n_samples`` area-uniform samples plus all vertices of each mesh are measured against the
    other surface; both directions are pooled for the max and the mean.
    """
    dists = []
    for k, (src, dst) in enumerate([(simplified, original), (original, simplified)]):
        used = np.asarray(src.vertices)[np.unique(src.faces)]  # stray unreferenced vertices are not surface
        pts = np.vstack([sample_surface(src.vertices, src.faces, n_samples, seed + k), used])
        dists.append(_distance_to_mesh(pts, dst))
    d = np.concatenate(dists)
    return {"max": float(d.max()), "mean": float(d.mean())}
