"""Inside/outside of query points for a triangle mesh, from a :class:`~hoidata.geometry.bvh.MeshBVH`.

- :func:`pseudonormal_outside`: the angle-weighted pseudonormal test (Baerentzen and Aanaes 2005) at
  each point's closest feature, as libigl's ``SIGNED_DISTANCE_TYPE_PSEUDONORMAL`` does it: the face
  normal inside a face, the sum of the unit normals of the faces on an edge, the corner-angle-weighted
  sum around a vertex; outside where (p - closest point) . normal >= 0. Exact for a closed mesh that
  does not pass through itself. Only the normals at the points' own features are computed.
- :func:`winding_numbers`: the generalized winding number of a closed mesh (every directed edge
  matched by its reverse, :func:`is_closed`): an integer away from the surface, the signed ray
  crossing count of :meth:`MeshBVH.crossings`; the rare points where that test cannot decide get
  libigl's exact winding number.

All positions share one frame and unit (metres in ``hoidata``); meshes are validated (float64, int64).
"""

from __future__ import annotations

from collections import OrderedDict

import igl
import numba
import numpy as np

from hoidata.geometry.bvh import EDGE_AB, EDGE_AC, EDGE_BC, INTERIOR, MeshBVH, mesh_key

_ADJACENCY: OrderedDict = OrderedDict()
KEEP_ADJACENCY = 32  # face arrays whose edge and vertex incidence is kept (least recently used dropped first)


def adjacency(vertices: np.ndarray, faces: np.ndarray, key: tuple | None = None) -> tuple[np.ndarray, ...]:
    """Incidence of a face array, computed once per face array (``key``: its
    :func:`hoidata.geometry.bvh.mesh_key`, found here when None):

    - edge_of (F, 3): undirected edge index of each face's edges ab, ac, bc;
    - edge_ptr (E + 1,), edge_faces: the faces on edge e are edge_faces[edge_ptr[e]:edge_ptr[e + 1]];
    - vertex_ptr (V + 1,), vertex_faces, vertex_corner: the faces around vertex i and the corner
      (0, 1, 2) it is in each of them.
    """
    key = mesh_key(vertices, faces) if key is None else key
    if key not in _ADJACENCY:
        n_f, n_v = len(faces), len(vertices)
        pairs = [(0, 1), (0, 2), (1, 2)]  # slot order: ab, ac, bc
        lo = np.stack([np.minimum(faces[:, i], faces[:, j]) for i, j in pairs], axis=1)
        hi = np.stack([np.maximum(faces[:, i], faces[:, j]) for i, j in pairs], axis=1)
        unique, edge_of = np.unique((lo * n_v + hi).reshape(-1), return_inverse=True)
        edge_of = edge_of.reshape(n_f, 3)
        by_edge = np.argsort(edge_of.reshape(-1), kind="stable")
        edge_ptr = np.concatenate([[0], np.cumsum(np.bincount(edge_of.reshape(-1), minlength=len(unique)))])
        by_vertex = np.argsort(faces.reshape(-1), kind="stable")
        vertex_ptr = np.concatenate([[0], np.cumsum(np.bincount(faces.reshape(-1), minlength=n_v))])
        _ADJACENCY[key] = (edge_of, edge_ptr, by_edge // 3, vertex_ptr, by_vertex // 3, by_vertex % 3)
        while len(_ADJACENCY) > KEEP_ADJACENCY:
            _ADJACENCY.popitem(last=False)
    _ADJACENCY.move_to_end(key)
    return _ADJACENCY[key]


def pseudonormal_outside(points, vertices, faces, face, weights, feature, key: tuple | None = None) -> np.ndarray:
    """(N,) bool: the pseudonormal test at each point's closest feature (from :meth:`MeshBVH.closest`:
    faces (N,), barycentric weights (N, 2), feature codes (N,)); ``key``: the faces' mesh_key, if known."""
    out = np.empty(len(points), np.bool_)
    _pseudonormal_outside(points, vertices, faces, face, weights, feature, *adjacency(vertices, faces, key), out)
    return out


@numba.njit(cache=True, inline="always")
def _unit_normal(vertices, faces, f):
    """Unit normal (x, y, z) of face f, (0, 0, 0) for a face of zero area."""
    i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
    u0, u1, u2 = vertices[j, 0] - vertices[i, 0], vertices[j, 1] - vertices[i, 1], vertices[j, 2] - vertices[i, 2]
    v0, v1, v2 = vertices[k, 0] - vertices[i, 0], vertices[k, 1] - vertices[i, 1], vertices[k, 2] - vertices[i, 2]
    n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
    norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if norm > 0:
        return n0 / norm, n1 / norm, n2 / norm
    return 0.0, 0.0, 0.0


@numba.njit(cache=True, inline="always")
def _corner_angle(vertices, faces, g, corner):
    """Interior angle (radians) of face g at its corner 0, 1 or 2."""
    h, i, j = faces[g, corner], faces[g, (corner + 1) % 3], faces[g, (corner + 2) % 3]
    u0, u1, u2 = vertices[i, 0] - vertices[h, 0], vertices[i, 1] - vertices[h, 1], vertices[i, 2] - vertices[h, 2]
    v0, v1, v2 = vertices[j, 0] - vertices[h, 0], vertices[j, 1] - vertices[h, 1], vertices[j, 2] - vertices[h, 2]
    c0, c1, c2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
    return np.arctan2(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2), u0 * v0 + u1 * v1 + u2 * v2)


@numba.njit(cache=True)
def _pseudonormal_outside(points, vertices, faces, face, weights, feature, edge_of, edge_ptr, edge_faces,
                          vertex_ptr, vertex_faces, vertex_corner, out):
    for i in range(len(points)):
        f, kind = face[i], feature[i]
        n0, n1, n2 = 0.0, 0.0, 0.0
        if kind == INTERIOR:
            n0, n1, n2 = _unit_normal(vertices, faces, f)
        elif kind == EDGE_AB or kind == EDGE_AC or kind == EDGE_BC:
            e = edge_of[f, 0 if kind == EDGE_AB else (1 if kind == EDGE_AC else 2)]
            for k in range(edge_ptr[e], edge_ptr[e + 1]):
                m0, m1, m2 = _unit_normal(vertices, faces, edge_faces[k])
                n0, n1, n2 = n0 + m0, n1 + m1, n2 + m2
        else:  # a corner: CORNER_A = 0, CORNER_B = 1, CORNER_C = 3
            vertex = faces[f, 0 if kind == 0 else (1 if kind == 1 else 2)]
            for k in range(vertex_ptr[vertex], vertex_ptr[vertex + 1]):
                g = vertex_faces[k]
                angle = _corner_angle(vertices, faces, g, vertex_corner[k])
                m0, m1, m2 = _unit_normal(vertices, faces, g)
                n0, n1, n2 = n0 + angle * m0, n1 + angle * m1, n2 + angle * m2
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        v, w = weights[i, 0], weights[i, 1]
        dot = 0.0
        for d, n_d in ((0, n0), (1, n1), (2, n2)):
            closest = vertices[a, d] + v * (vertices[b, d] - vertices[a, d]) + w * (vertices[c, d] - vertices[a, d])
            dot += (points[i, d] - closest) * n_d
        out[i] = dot >= 0


def is_closed(faces: np.ndarray) -> bool:
    """Every directed edge (i, j) of the faces is matched by a reverse (j, i), as often: a 2-cycle
    (closed, consistently oriented; it may pass through itself), whose winding number is an integer."""
    heads = faces.reshape(-1)
    tails = np.roll(faces, -1, axis=1).reshape(-1)
    n = int(faces.max()) + 1
    return bool(np.array_equal(np.sort(heads * n + tails), np.sort(tails * n + heads)))


_CLOSED: OrderedDict = OrderedDict()


def is_closed_kept(faces: np.ndarray, key: tuple) -> bool:
    """:func:`is_closed` of a face array whose :func:`hoidata.geometry.bvh.mesh_key` is ``key``, found once per key."""
    if key not in _CLOSED:
        _CLOSED[key] = is_closed(faces)
        while len(_CLOSED) > KEEP_ADJACENCY:
            _CLOSED.popitem(last=False)
    _CLOSED.move_to_end(key)
    return _CLOSED[key]


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, bvh: MeshBVH,
                    dist: np.ndarray | None = None, visit: np.ndarray | None = None) -> np.ndarray:
    """(N,) generalized winding numbers of a closed mesh (:func:`is_closed`) at points off its surface.

    With the points' unsigned distances to the mesh ``dist`` (N,) and an order ``visit`` (N,) of them, only some
    points cast a ray: the winding number of a closed mesh is constant off its surface, so a point shares its
    predecessor's (in ``visit``) when the segment between them lies in the union of the two balls of radius ``dist``
    around them, which holds no point of the surface (:func:`_shared_winding`). The same numbers, fewer rays."""
    if dist is None or visit is None:
        source = np.arange(len(points))
    else:
        source = _shared_winding(points, np.asarray(dist, dtype=np.float64), np.asarray(visit, dtype=np.int64))
    cast = np.flatnonzero(source == np.arange(len(points)))
    rays = np.ascontiguousarray(points[cast])
    count, undecided = bvh.crossings(rays)
    winding = np.empty(len(points))
    winding[cast] = count
    if undecided.any():
        winding[cast[undecided]] = igl.winding_number(vertices, faces, np.ascontiguousarray(rays[undecided]))
    return winding[source]


SHARE_WINDOW = 32  # predecessors tried
SHARE_MARGIN = 1e-9  # relative: the segment must be this much shorter than the two radii (rounding of all three)
SHARE_ROUNDING = 1e-12  # and shorter by this share of the coordinates' size (a distance's absolute rounding)


@numba.njit(cache=True)
def _shared_winding(points, dist, visit):
    """(N,) int64: for each point, the point whose winding number it has, itself where it must cast a ray. Walking
    ``visit``, a point p whose predecessor q satisfies |p - q| (1 + SHARE_MARGIN) + rounding < dist[p] + dist[q]
    takes q's source: the segment pq then lies in the union of the two open balls around p and q whose radii are
    their distances to the surface (a point of it within dist[p] of p is in p's ball, any other within dist[q] of
    q), a connected set that holds no point of the surface, so the winding number is the same at both ends."""
    source = np.arange(len(points))
    for t in range(1, len(visit)):
        i = visit[t]
        for back in range(1, min(t, SHARE_WINDOW) + 1):
            j = visit[t - back]
            d0, d1, d2 = points[i, 0] - points[j, 0], points[i, 1] - points[j, 1], points[i, 2] - points[j, 2]
            size = max(abs(points[i, 0]), abs(points[i, 1]), abs(points[i, 2]), abs(points[j, 0]), abs(points[j, 1]),
                       abs(points[j, 2]))
            gap = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) * (1.0 + SHARE_MARGIN) + SHARE_ROUNDING * size
            if gap < dist[i] + dist[j]:
                source[i] = source[j]
                break
    return source
