"""A bounding-volume hierarchy over one triangle mesh: exact closest faces and signed ray crossings.

Compiled with numba, single-threaded (a build worker is one core), float64 throughout:

- :meth:`MeshBVH.closest` gives each query point's exact distance to the mesh, a face that attains
  it and the closest point's barycentric weights and feature (face interior, edge or corner, which a
  pseudonormal sign needs). The point-triangle distance is Ericson's Voronoi-region routine
  (*Real-Time Collision Detection*, 5.1.5) in the operation order of the brute-force reference
  :func:`hoidata.geometry.sdf.closest_point_on_triangles`; the traversal skips a box only when its
  distance exceeds the best one found, so the minimum is over all faces. On ties the lowest face
  index wins (the reference's rule). Both queries run on the tree's wide view
  (:mod:`hoidata.geometry.bvh_wide`: 8 children per node, 8-face leaf blocks, distances in vector lanes),
  which gives the same bits as the binary walk.
- :meth:`MeshBVH.crossings` gives each point's signed count of crossings of the mesh by the ray from
  the point along one of :data:`RAYS` (+1 where the ray passes a face from its back to its front): for a
  closed, consistently oriented mesh this is the winding number. The ray/triangle test is the
  watertight one of Woop, Benthin and Wald (JCGT 2013): an edge's edge function is computed from its
  two transformed vertices alone and flips sign exactly between the two faces that share it, so a ray
  through a face's edge is counted by exactly one of them. Where that cannot decide (an edge function
  exactly zero: the ray meets an edge or a corner; a zero determinant: it runs in a face's plane; the
  point lies on the face it meets), the point is marked undecided, for a closed-form winding number.

Boxes are padded by 1e-9 of the mesh's extent: culling only gets more conservative.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numba
import numpy as np

from hoidata.geometry.bvh_wide import closest_wide, crossings_wide, gather, widen

LEAF_SIZE = 4
# Below this depth the surface-area split is replaced by the median one, so no tree gets deeper than
# MEDIAN_DEPTH + log2(F) (under 80 for any face count that fits in memory): the query stacks hold 128.
MEDIAN_DEPTH = 40
PAD = 1e-9  # box padding, relative to the mesh's bounding-box diagonal
# The rays of MeshBVH.crossings: each point casts the one that leaves the mesh's box soonest, mostly
# along +x, -x, +y, -y, +z or -z, tilted off every axis and diagonal (unit vectors).
_TILT = (0.1234567, -0.0765432)
RAYS = np.array([[s * (1.0 if d == k else _TILT[(d - k) % 3 - 1]) for d in range(3)]
                 for k in range(3) for s in (1.0, -1.0)])
RAYS = RAYS / np.linalg.norm(RAYS, axis=1, keepdims=True)

NO_HINT = np.zeros(0, np.int64)  # MeshBVH.closest without hints

# Feature codes of MeshBVH.closest: the part of face (a, b, c) the closest point lies on.
CORNER_A, CORNER_B, EDGE_AB, CORNER_C, EDGE_AC, EDGE_BC, INTERIOR = range(7)


class MeshBVH:
    """The hierarchy of one mesh: vertices (V, 3) float64 and faces (F >= 1, 3) int64 in [0, V),
    already validated (:func:`hoidata.geometry.sdf.validate_mesh`). Same units and frame as the queries.

    The tree's shape (which faces share a leaf, how leaves nest) is built once per face array, by the
    surface-area heuristic, and kept (:func:`topology`): a new pose of the same mesh (the next
    frame's hand, the object in another pose) only refits the boxes around its vertices. The shape
    decides what is visited first and what is skipped: distances, crossing counts and anything else chosen or
    counted never depend on it, but a float sum over the faces met, in visiting order (a cube's column integral,
    :mod:`hoisdf.scoring.cell_volume`), can differ in its last bits with the pose that built the shape, and so
    with what a process happened to see first. ``pose_shape=True`` builds the shape from these vertices (kept by
    their content too), so that such sums are a function of this mesh alone, in any process.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, pose_shape: bool = False):
        self.key = mesh_key(vertices, faces)  # what the per-face-array caches (tree shape, adjacency) are keyed by
        shape_key = self.key + (vertex_digest(vertices),) if pose_shape else self.key
        self.order, self.left, self.start, self.count = topology(vertices, faces, shape_key)
        self.boxes = np.empty((len(self.left), 6))  # (lo xyz, hi xyz) per node
        self.tri = np.empty((len(faces), 9))  # corners a, b, c of each face, in leaf order
        pad = PAD * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        _refit(vertices, faces, pad, self.order, self.left, self.start, self.count, self.boxes, self.tri)
        self._wide = None  # the closest-face query's wide view (bvh_wide.gather), made on its first call

    def closest(self, points: np.ndarray, visit: np.ndarray | None = None, hint: np.ndarray | None = None,
                leaf_faces: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For validated points (N, 3) float64: distance (N,) float64, face (N,) int64, barycentric
        weights (N, 2) of the closest point q = a + v (b - a) + w (c - a), and its feature (N,) int8.
        ``visit``: the order to query them in (:func:`morton_order` of the points when None; a caller querying the
        same points on several meshes passes it once); ``hint`` (N,): a face near each point, in leaf order (as
        ``leaf_faces=True`` returns them: ``self.order`` maps them to face indices), -1 for none. Neither changes the
        results, only the work."""
        n = len(points)
        dist, face, weights, feature = np.empty(n), np.empty(n, np.int64), np.empty((n, 2)), np.empty(n, np.int8)
        ref, lo, hi, blocks, first, count = self.wide()
        closest_wide(points, morton_order(points) if visit is None else visit, NO_HINT if hint is None else hint,
                     self.order, lo, hi, ref, blocks, first, count, self.tri, dist, face, weights, feature)
        return dist, face if leaf_faces else self.order[face], weights, feature

    def crossings(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed crossing count (N,) int64 along a ray from each point (the one of :data:`RAYS` that
        leaves the mesh's box soonest), and undecided (N,) bool."""
        n = len(points)
        count, undecided = np.zeros(n, np.int64), np.zeros(n, np.bool_)
        ref, lo, hi, blocks, _, block_count = self.wide()
        crossings_wide(points, RAYS, self.boxes[0], lo, hi, ref, blocks, block_count, count, undecided)
        return count, undecided

    def wide(self) -> tuple[np.ndarray, ...]:
        """(ref, lo, hi, blocks, first, count): the tree's wide view for this pose (:mod:`hoidata.geometry.bvh_wide`),
        made on first use."""
        if self._wide is None:
            nodes, ref, leaf_of = wide_view(self.left, self.count)
            self._wide = ref, *gather(nodes, leaf_of, self.boxes, self.tri, self.start, self.count)
        return self._wide


_TOPOLOGIES: OrderedDict = OrderedDict()
KEEP_TOPOLOGIES = 32  # face arrays whose tree shape is kept (least recently used dropped first)


def mesh_key(vertices: np.ndarray, faces: np.ndarray) -> tuple[int, bytes]:
    """What a cache of per-face-array data is keyed by: the vertex count and a digest of the faces."""
    return len(vertices), hashlib.blake2b(np.ascontiguousarray(faces).tobytes(), digest_size=16).digest()


def vertex_digest(vertices: np.ndarray) -> bytes:
    """A digest of the vertices' float64 values: with :func:`mesh_key`, what a tree shape built from this pose is
    kept by."""
    return hashlib.blake2b(np.ascontiguousarray(vertices, np.float64).tobytes(), digest_size=16).digest()


def topology(vertices: np.ndarray, faces: np.ndarray, key: tuple | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(order, left, start, count) of the tree over these faces: built from ``vertices`` the first
    time a face array (by content, with the vertex count: ``key``, :func:`mesh_key` when None) is seen, then reused."""
    key = mesh_key(vertices, faces) if key is None else key
    if key in _TOPOLOGIES:
        _TOPOLOGIES.move_to_end(key)
        return _TOPOLOGIES[key]
    n = len(faces)
    order = np.arange(n, dtype=np.int64)  # leaf order -> face index
    left = np.empty(2 * n, np.int64)  # first child (the second is left + 1), -1 for a leaf
    start, count = np.empty(2 * n, np.int64), np.empty(2 * n, np.int64)  # a node's range of `order`
    used = _build(vertices, faces, order, left, start, count)
    _TOPOLOGIES[key] = (order, left[:used].copy(), start[:used].copy(), count[:used].copy())
    while len(_TOPOLOGIES) > KEEP_TOPOLOGIES:
        _TOPOLOGIES.popitem(last=False)
    return _TOPOLOGIES[key]


_WIDE: OrderedDict = OrderedDict()


def wide_view(left: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`hoidata.geometry.bvh_wide.widen` of a kept tree shape (by the identity of its arrays), kept beside it."""
    key = (id(left), id(count))
    if key not in _WIDE or _WIDE[key][0] is not left:
        _WIDE[key] = (left, count, *widen(left, count))
        while len(_WIDE) > KEEP_TOPOLOGIES:
            _WIDE.popitem(last=False)
    _WIDE.move_to_end(key)
    return _WIDE[key][2:]


@numba.njit(cache=True)
def _face_boxes(vertices, faces):
    """Centroids, box minima and box maxima of the faces, (F, 3) each."""
    n = len(faces)
    cen, lo, hi = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    for f in range(n):
        for d in range(3):
            a, b, c = vertices[faces[f, 0], d], vertices[faces[f, 1], d], vertices[faces[f, 2], d]
            cen[f, d] = (a + b + c) / 3.0
            lo[f, d], hi[f, d] = min(a, b, c), max(a, b, c)
    return cen, lo, hi


@numba.njit(cache=True, inline="always")
def _half_area(lo, hi):
    ex, ey, ez = hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]
    return ex * ey + ey * ez + ex * ez


@numba.njit(cache=True)
def _build(vertices, faces, order, left_of, start_of, count_of):
    """Top-down, surface-area heuristic: each node's faces are sorted by centroid along each axis and
    split where (left box area) * (left count) + (right box area) * (right count) is smallest;
    at most LEAF_SIZE faces per leaf. Returns the number of nodes (children after their parent)."""
    cen, lo, hi = _face_boxes(vertices, faces)
    n = len(faces)
    stack = np.empty((128, 4), np.int64)  # (node, start, count, depth)
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = 0, 0, n, 0
    top, n_nodes = 1, 1
    key, prefix = np.empty(n), np.empty(n)
    box_lo, box_hi = np.empty(3), np.empty(3)
    while top:
        top -= 1
        node, start, count, depth = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        start_of[node], count_of[node] = start, count
        if count <= LEAF_SIZE:
            left_of[node] = -1
            continue
        best_cost, best_axis, best_split = np.inf, 0, count // 2
        if depth >= MEDIAN_DEPTH:  # the median on the widest centroid axis: balanced from here on
            for d in range(3):
                box_lo[d], box_hi[d] = np.inf, -np.inf
                for k in range(start, start + count):
                    box_lo[d], box_hi[d] = min(box_lo[d], cen[order[k], d]), max(box_hi[d], cen[order[k], d])
            best_axis = np.argmax(box_hi - box_lo)
        for axis in range(3 if depth < MEDIAN_DEPTH else 0):
            for k in range(count):
                key[k] = cen[order[start + k], axis]
            sorted_faces = order[start:start + count][np.argsort(key[:count], kind="mergesort")]
            box_lo[:], box_hi[:] = np.inf, -np.inf
            for k in range(count):  # prefix[k]: area of the box of the first k + 1 faces
                f = sorted_faces[k]
                for d in range(3):
                    box_lo[d], box_hi[d] = min(box_lo[d], lo[f, d]), max(box_hi[d], hi[f, d])
                prefix[k] = _half_area(box_lo, box_hi)
            box_lo[:], box_hi[:] = np.inf, -np.inf
            for k in range(count - 1, 0, -1):  # split before face k: [0, k) and [k, count)
                f = sorted_faces[k]
                for d in range(3):
                    box_lo[d], box_hi[d] = min(box_lo[d], lo[f, d]), max(box_hi[d], hi[f, d])
                cost = prefix[k - 1] * k + _half_area(box_lo, box_hi) * (count - k)
                if cost < best_cost:
                    best_cost, best_axis, best_split = cost, axis, k
        for k in range(count):
            key[k] = cen[order[start + k], best_axis]
        order[start:start + count] = order[start:start + count][np.argsort(key[:count], kind="mergesort")]
        left_of[node] = n_nodes
        stack[top, 0], stack[top, 1], stack[top, 2] = n_nodes + 1, start + best_split, count - best_split
        stack[top + 1, 0], stack[top + 1, 1], stack[top + 1, 2] = n_nodes, start, best_split
        stack[top, 3], stack[top + 1, 3] = depth + 1, depth + 1
        top += 2
        n_nodes += 2
    return n_nodes


@numba.njit(cache=True)
def _refit(vertices, faces, pad, order, left_of, start_of, count_of, boxes, tri):
    """Corners in leaf order and every node's box (padded by ``pad``) for these vertex positions."""
    _, lo, hi = _face_boxes(vertices, faces)
    for k in range(len(order)):
        for corner in range(3):
            for d in range(3):
                tri[k, 3 * corner + d] = vertices[faces[order[k], corner], d]
    for node in range(len(left_of) - 1, -1, -1):  # children come after their parent
        left = left_of[node]
        for d in range(3):
            if left < 0:
                box_lo, box_hi = np.inf, -np.inf
                for k in range(start_of[node], start_of[node] + count_of[node]):
                    box_lo, box_hi = min(box_lo, lo[order[k], d]), max(box_hi, hi[order[k], d])
                boxes[node, d], boxes[node, 3 + d] = box_lo - pad, box_hi + pad
            else:
                boxes[node, d] = min(boxes[left, d], boxes[left + 1, d])
                boxes[node, 3 + d] = max(boxes[left, 3 + d], boxes[left + 1, 3 + d])


def morton_order(points: np.ndarray) -> np.ndarray:
    """(N,) int64: the points' order along a Z-order curve over their bounding box (:func:`_morton_order`), the
    visiting order of :meth:`MeshBVH.closest` that makes each query start near its predecessor's answer."""
    return _morton_order(points)


@numba.njit(cache=True)
def _morton_order(points):
    """Visiting order of the points along a Z-order curve over their bounding box: each query then
    starts from its predecessor's face, usually a near one, so the first bound is already tight.
    (Any order gives the same results; this one only saves work.) A stable radix sort of the 30-bit
    codes, three passes of 10 bits: the order np.argsort(code, kind="mergesort") gives, in O(N)."""
    n = len(points)
    code = np.zeros(n, np.int64)
    if n == 0:
        return code
    lo = np.array([points[:, d].min() for d in range(3)])
    span = np.array([points[:, d].max() for d in range(3)]) - lo
    for i in range(n):
        for d in range(3):
            cell = int(1023.0 * (points[i, d] - lo[d]) / span[d]) if span[d] > 0 else 0
            for bit in range(10):
                code[i] |= ((cell >> bit) & 1) << (3 * bit + d)
    order, swap = np.arange(n), np.empty(n, np.int64)
    for shift in range(0, 30, 10):
        start = np.zeros(1025, np.int64)
        for i in range(n):
            start[((code[order[i]] >> shift) & 1023) + 1] += 1
        for b in range(1024):
            start[b + 1] += start[b]
        for i in range(n):
            b = (code[order[i]] >> shift) & 1023
            swap[start[b]] = order[i]
            start[b] += 1
        order, swap = swap, order
    return order
