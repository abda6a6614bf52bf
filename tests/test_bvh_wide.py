"""The wide view of the BVH (hoidata.geometry.bvh_wide): its blocks and children cover the tree's faces exactly
once, and its vector-lane queries give bit for bit what the scalar point-triangle routine and the watertight ray
test give face by face (the brute force below), ties to the lowest face index included."""

from __future__ import annotations

import igl
import numba
import numpy as np
import pytest
import trimesh

from hoidata.geometry.bvh import RAYS, MeshBVH
from hoidata.geometry.bvh_wide import LANES, point_triangle, widen


@numba.njit(cache=True)
def _brute_closest(points, tri, order):
    """Every face in leaf order: the least squared distance, the lowest face index among equal ones."""
    n = len(points)
    dist, face, weights, feature = np.empty(n), np.empty(n, np.int64), np.empty((n, 2)), np.empty(n, np.int8)
    for i in range(n):
        best, best_k, bv, bw, bf = np.inf, -1, 0.0, 0.0, 0
        for k in range(len(tri)):
            d2, v, w, f = point_triangle(points[i, 0], points[i, 1], points[i, 2], tri, k)
            if d2 < best or (d2 == best and order[k] < order[best_k]):
                best, best_k, bv, bw, bf = d2, k, v, w, f
        dist[i], face[i], weights[i, 0], weights[i, 1], feature[i] = np.sqrt(best), best_k, bv, bw, bf
    return dist, face, weights, feature


def _soup(n_faces: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A random triangle soup with shared vertices, and two faces repeated (exact ties)."""
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(max(3, n_faces), 3)) * 0.05 + 0.5
    faces = np.stack([rng.choice(len(vertices), 3, replace=False) for _ in range(n_faces)])
    if n_faces > 4:
        faces[-1], faces[-2] = faces[0], faces[1][[1, 2, 0]]
    return vertices, faces.astype(np.int64)


@pytest.mark.parametrize("n_faces", [1, 7, 8, 9, 33, 700])
def test_closest_is_the_brute_force_minimum_bit_for_bit(n_faces):
    vertices, faces = _soup(n_faces, n_faces)
    rng = np.random.default_rng(1)
    points = np.concatenate([vertices + rng.normal(size=vertices.shape) * 1e-3, vertices[faces].mean(1),
                             0.5 + rng.uniform(-0.3, 0.3, (300, 3)), vertices[:5]])  # near, on faces, far, corners
    bvh = MeshBVH(vertices, faces)
    got = bvh.closest(points)
    dist, face, weights, feature = _brute_closest(points, bvh.tri, bvh.order)
    expected = (dist, bvh.order[face], weights, feature)
    for a, b in zip(got, expected, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("n_faces", [1, 8, 9, 700])
def test_wide_view_holds_each_face_once(n_faces):
    vertices, faces = _soup(n_faces, 3)
    bvh = MeshBVH(vertices, faces)
    nodes, ref, leaf_of = widen(bvh.left, bvh.count)
    covered = np.zeros(n_faces, np.int64)
    for node in np.flatnonzero(leaf_of >= 0):
        assert bvh.count[node] <= LANES or bvh.left[node] < 0
        covered[bvh.start[node]:bvh.start[node] + bvh.count[node]] += 1
    assert np.array_equal(covered, np.ones(n_faces, np.int64))
    assert nodes.shape[1] == 8 and len(np.unique(nodes[nodes >= 0])) == (nodes >= 0).sum()
    *_, first, count = bvh.wide()
    assert sorted(zip(first, count)) == sorted((bvh.start[k], bvh.count[k]) for k in np.flatnonzero(leaf_of >= 0))


def test_crossings_are_the_winding_number_of_a_closed_mesh():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    vertices = np.asarray(sphere.vertices) * [1.0, 0.6, 1.3] + [0.1, -0.02, 0.5]
    faces = np.asarray(sphere.faces, dtype=np.int64)
    rng = np.random.default_rng(4)
    points = np.concatenate([vertices.mean(0) + rng.uniform(-0.08, 0.08, (400, 3)), vertices[:20],
                             vertices.mean(0) + 0.001 * RAYS])  # inside and outside, corners, the centre
    count, undecided = MeshBVH(vertices, faces).crossings(points)
    assert undecided[400:420].all()  # a ray from a corner starts on the surface
    decided = ~undecided
    winding = igl.winding_number(vertices, faces, points[decided])
    assert np.array_equal(count[decided], np.round(winding).astype(np.int64))
    assert 0 < count[decided].sum() < decided.sum()  # both inside and outside points
