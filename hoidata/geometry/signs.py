"""Inside/outside of query points for a triangle mesh, from a :class:`~hoidata.geometry.bvh.MeshBVH`.

- :func:`pseudonormal_outside`: the angle-weighted pseudonormal test (Baerentzen and Aanaes 2005) at
  each point's closest feature, as libigl's ``SIGNED_DISTANCE_TYPE_PSEUDONORMAL`` does it: the face
  normal inside a face, the mean of the adjacent faces' normals on an edge, the angle-weighted vertex
  normal at a corner; outside where (p - closest point) . normal >= 0. Exact for a closed mesh that
  does not pass through itself.
- :func:`winding_numbers`: the generalized winding number. For a closed mesh (every directed edge
  matched by its reverse, :func:`is_closed`) it is an integer away from the surface, the signed ray
  crossing count of :meth:`MeshBVH.crossings`; the few points where that test cannot decide, and
  every point of an open mesh, get libigl's winding number instead (:func:`hoidata.geometry.sdf.winding_inside`
  keeps the fast-approximation path for open meshes).

All positions share one frame and unit (metres in ``hoidata``); meshes are validated (float64, int64).
"""

from __future__ import annotations

import igl
import numpy as np

from hoidata.geometry.bvh import CORNER_A, CORNER_B, CORNER_C, EDGE_AB, EDGE_AC, EDGE_BC, MeshBVH

# (corner, corner) of each edge feature, and the corner of each corner feature
_EDGE_CORNERS = {EDGE_AB: (0, 1), EDGE_AC: (0, 2), EDGE_BC: (1, 2)}
_CORNERS = {CORNER_A: 0, CORNER_B: 1, CORNER_C: 2}
# the same as lookup tables indexed by feature code (-1: not that kind of feature)
_CORNER_OF = np.array([_CORNERS.get(k, -1) for k in range(7)])
_EDGE_FIRST = np.array([_EDGE_CORNERS.get(k, (-1, -1))[0] for k in range(7)])
_EDGE_SECOND = np.array([_EDGE_CORNERS.get(k, (-1, -1))[1] for k in range(7)])


def _unit(x: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, norm, out=np.zeros_like(x), where=norm > 0)


def closest_points(vertices: np.ndarray, faces: np.ndarray, face: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N, 3) points a + v (b - a) + w (c - a) of faces (N,) with barycentric weights (N, 2)."""
    a, b, c = (vertices[faces[face, k]] for k in range(3))
    return a + weights[:, :1] * (b - a) + weights[:, 1:] * (c - a)


def pseudonormal_outside(points, vertices, faces, face, weights, feature) -> np.ndarray:
    """(N,) bool: the pseudonormal test at each point's closest feature (from :meth:`MeshBVH.closest`)."""
    tri = vertices[faces]
    face_n = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))  # (F, 3)
    normal = face_n[face]
    at_edge = np.isin(feature, list(_EDGE_CORNERS))
    if at_edge.any():
        normal[at_edge] = _edge_normals(faces, face_n, face[at_edge], feature[at_edge])
    at_corner = np.isin(feature, list(_CORNERS))
    if at_corner.any():
        corner = _CORNER_OF[feature[at_corner]]
        normal[at_corner] = _vertex_normals(tri, faces, face_n, len(vertices))[faces[face[at_corner], corner]]
    offset = points - closest_points(vertices, faces, face, weights)
    return np.einsum("ij,ij->i", offset, normal) >= 0


def _vertex_normals(tri: np.ndarray, faces: np.ndarray, face_n: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V, 3) sums of the unit normals of the faces around each vertex, weighted by the corner angle."""
    out = np.zeros((n_vertices, 3))
    for k in range(3):
        e1, e2 = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
        angle = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2))
        np.add.at(out, faces[:, k], angle[:, None] * face_n)
    return out


def _edge_normals(faces, face_n, face, feature) -> np.ndarray:
    """(M, 3) sums of the unit normals of all faces that share the closest edge of each face (M,)."""
    lo, hi = np.minimum, np.maximum
    n_v = int(faces.max()) + 1
    keys = np.concatenate([lo(faces[:, i], faces[:, j]) * n_v + hi(faces[:, i], faces[:, j])
                           for i, j in ((0, 1), (0, 2), (1, 2))])
    normals = np.tile(face_n, (3, 1))
    unique, inverse = np.unique(keys, return_inverse=True)
    sums = np.zeros((len(unique), 3))
    np.add.at(sums, inverse, normals)
    a, b = faces[face, _EDGE_FIRST[feature]], faces[face, _EDGE_SECOND[feature]]
    return sums[np.searchsorted(unique, lo(a, b) * n_v + hi(a, b))]


def is_closed(faces: np.ndarray) -> bool:
    """Every directed edge (i, j) of the faces is matched by a reverse (j, i), as often: a 2-cycle
    (closed, consistently oriented; it may pass through itself), whose winding number is an integer."""
    heads = faces.reshape(-1)
    tails = np.roll(faces, -1, axis=1).reshape(-1)
    n = int(faces.max()) + 1
    return bool(np.array_equal(np.sort(heads * n + tails), np.sort(tails * n + heads)))


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, bvh: MeshBVH) -> np.ndarray:
    """(N,) generalized winding numbers of a closed mesh (:func:`is_closed`) at points off its surface."""
    count, undecided = bvh.crossings(points)
    winding = count.astype(np.float64)
    if undecided.any():
        winding[undecided] = igl.winding_number(vertices, faces, np.ascontiguousarray(points[undecided]))
    return winding

