"""The numba BVH backend of hoidata.geometry.sdf.signed_distance against the brute-force reference
and libigl (the previous backend, kept as the verifier): exact distances, the same signs; the signed
ray crossing count against libigl's exact winding number; the kept tree shapes across poses."""

from __future__ import annotations

import igl
import numpy as np
import pytest
import trimesh
from test_sdf import near_and_inside, posed_hands, posed_objects

from hoidata.errors import DataError
from hoidata.geometry import bvh as bvh_module
from hoidata.geometry.bvh import INTERIOR, MeshBVH, morton_order, topology
from hoidata.geometry.sampling import compute_sdf_samples
from hoidata.geometry.sdf import (
    brute_force_signed_distance,
    closest_point_on_triangles,
    signed_distance,
    validate_mesh,
)
from hoidata.geometry.signs import is_closed, winding_numbers
from hoidata.records.settings import load_build_config

# Metres: float64 rounding of distances up to ~0.6 m (one unit in the last place of 0.5 is 1.1e-16).
# Both backends and the reference compute the same closest point; they differ only in rounding.
EXACT = 2e-16


@pytest.fixture(scope="module")
def hands(mano_right):
    return posed_hands(mano_right)


@pytest.fixture(scope="module")
def objects(tmp_path_factory):
    return posed_objects(tmp_path_factory.mktemp("bvh_models"), 20)


def query_points(vertices, faces, root, seed: int) -> np.ndarray:
    """Near-surface and inside points plus far ones in the 0.64 m cube the sampler uses."""
    rng = np.random.default_rng(seed)
    return np.concatenate([near_and_inside(vertices, faces, 600, rng), root + rng.uniform(-0.32, 0.32, (200, 3))])


@pytest.mark.parametrize("pose", [pytest.param("flat", marks=pytest.mark.slow), "curled"])
@pytest.mark.parametrize("watertight", [False, True])
def test_bvh_hand_distances_exact_and_signs_as_igl(hands, pose, watertight):
    vertices, faces, root = hands[pose]
    points = query_points(vertices, faces, root, 1)
    got, face = signed_distance(points, vertices, faces, watertight)
    old, _ = signed_distance(points, vertices, faces, watertight, backend="igl")
    ref, ref_face = brute_force_signed_distance(points, vertices, faces)
    assert np.abs(np.abs(got) - np.abs(ref)).max() < EXACT
    assert np.abs(np.abs(old) - np.abs(ref)).max() < EXACT
    assert np.array_equal(np.sign(got), np.sign(old))  # the same sign rule as the previous backend
    if not watertight or pose == "flat":  # winding number (or no self-overlap): the reference's sign
        assert np.array_equal(np.sign(got), np.sign(ref))
    # the returned face attains the distance (the reference's own face, where they round alike)
    tri = vertices[faces[face]]
    own = np.linalg.norm(points - closest_point_on_triangles(points, tri[:, 0], tri[:, 1], tri[:, 2]), axis=1)
    assert np.abs(own - np.abs(got)).max() < EXACT
    assert np.mean(face == ref_face) > 0.8


@pytest.mark.parametrize("name", [pytest.param("011_banana", marks=pytest.mark.slow), "002_master_chef_can"])
def test_bvh_object_pseudonormal_at_corners_and_edges(objects, name):
    """Points right off the corners and edges, where the pseudonormal needs the vertex and edge
    normals (the interior case is the face normal): same signs as libigl and the reference."""
    vertices, faces = objects[name]
    v, f = validate_mesh(vertices, faces)
    rng = np.random.default_rng(2)
    # off each corner and edge along its own normal, both sides: the closest point is often that
    # corner or edge itself (wherever the surface is convex there)
    vertex_n = igl.per_vertex_normals(v, f)
    pick = rng.integers(0, len(v), 300)
    corners = v[pick] + rng.choice([-1e-3, 1e-3], (300, 1)) * vertex_n[pick]
    face_n = igl.per_face_normals(v, f, np.ones(3) / np.sqrt(3))
    adjacent = igl.triangle_triangle_adjacency(f)[0]
    g = rng.integers(0, len(f), 300)
    edge_n = face_n[g] + face_n[adjacent[g, 0]]  # the face's edge 0 (corners 0 -> 1) and the face across it
    mid = 0.5 * (v[f[g, 0]] + v[f[g, 1]])
    edges = mid + rng.choice([-1e-3, 1e-3], (300, 1)) * edge_n / np.linalg.norm(edge_n, axis=1, keepdims=True)
    points = np.concatenate([corners, edges])
    _, _, _, feature = MeshBVH(v, f).closest(points)
    assert (feature != INTERIOR).mean() > 0.3
    got, _ = signed_distance(points, vertices, faces, True)
    old, _ = signed_distance(points, vertices, faces, True, backend="igl")
    ref, _ = brute_force_signed_distance(points, vertices, faces)
    assert np.array_equal(np.sign(got), np.sign(old)) and np.array_equal(np.sign(got), np.sign(ref))
    assert np.abs(got - ref).max() < EXACT and (got < 0).sum() > 100


def test_crossings_equal_exact_winding_number_through_self_overlap(hands):
    """The curled hand passes through itself; the crossing count equals libigl's exact winding number
    (integral off the surface) everywhere, the points near the overlap included, where the
    pseudonormal test gets the side wrong."""
    vertices, faces, root = hands["curled"]
    v, f = validate_mesh(vertices, faces)
    points = np.concatenate([query_points(v, f, root, 3), near_and_inside(v, f, 20000, np.random.default_rng(6))])
    count, undecided = MeshBVH(v, f).crossings(points)
    exact = igl.winding_number(v, f, points)
    assert not undecided.any()
    assert np.array_equal(count, np.round(exact).astype(np.int64)) and np.abs(exact - count).max() < 1e-6
    pseudo, _ = signed_distance(points, v, f, watertight=True)
    overlap = (pseudo < 0) != (count != 0)
    assert overlap.sum() >= 10 and (count == 1).sum() > 1000


def test_shared_winding_numbers_are_every_ray_s_with_fewer_rays(hands, monkeypatch):
    """Given the distances and the query order, points inside a surface-free ball of a predecessor take its
    winding number: the same numbers as a ray from every point (the curled hand's self-overlap included, where
    the pseudonormal gets the side wrong), from at most 70 % of the rays."""
    vertices, faces, root = hands["curled"]
    v, f = validate_mesh(vertices, faces)
    points = np.concatenate([query_points(v, f, root, 7), near_and_inside(v, f, 20000, np.random.default_rng(6))])
    bvh = MeshBVH(v, f)
    visit = morton_order(points)
    dist = bvh.closest(points, visit)[0]
    every = winding_numbers(points, v, f, bvh)
    rays, crossings = [], MeshBVH.crossings
    monkeypatch.setattr(MeshBVH, "crossings", lambda self, p: rays.append(len(p)) or crossings(self, p))
    shared = winding_numbers(points, v, f, bvh, dist, visit)
    assert np.array_equal(shared, every)
    assert ((signed_distance(points, v, f, watertight=True)[0] < 0) != (every != 0)).sum() >= 10  # the overlap
    assert rays == [int(rays[0])] and rays[0] < 0.7 * len(points)
    # any order gives the same numbers; through the sign of the hand's SDF too
    order = np.random.default_rng(9).permutation(len(points))
    assert np.array_equal(winding_numbers(points, v, f, bvh, dist, order), every)
    assert np.array_equal(signed_distance(points, v, f, False, visit=order)[0], signed_distance(points, v, f, False)[0])


def test_a_point_across_the_surface_casts_its_own_ray():
    """Two points 0.2 apart on either side of a unit cube's face, each 0.1 from it, do not share (the segment
    crosses the face); two inside points 0.05 apart, 0.1 and 0.15 deep, do; exactly at the ball's radius, not."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    v, f = validate_mesh(box.vertices, box.faces)
    bvh = MeshBVH(v, f)
    points = np.array([[0.4, 0.0, 0.0], [0.6, 0.0, 0.0], [0.0, 0.0, 0.35], [0.0, 0.0, 0.4], [0.0, 0.0, 0.5]])
    dist = bvh.closest(points)[0]
    rays, crossings = [], MeshBVH.crossings

    def counted(self, p):
        rays.append(len(p))
        return crossings(self, p)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(MeshBVH, "crossings", counted)
        winding = winding_numbers(points, v, f, bvh, dist, np.arange(5))
    # 0.4 casts, 0.6 (outside, across the face) casts, (0, 0, 0.35) casts (0.36 from its predecessor, which is
    # 0.1 from the surface), (0, 0, 0.4) shares (0.05 from it, 0.15 from the surface), (0, 0, 0.5) lies on the
    # surface (distance 0): it cannot be in a surface-free ball, it casts
    assert rays == [4]
    assert winding[:4].tolist() == [1.0, 0.0, 1.0, 1.0]


def test_undecided_rays_fall_back_to_exact_winding_number(monkeypatch):
    """Axis-aligned rays from points on a grid through a cube's corners and edges meet edges exactly:
    those points are flagged, and their winding number comes from libigl's exact formula."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    v, f = validate_mesh(box.vertices, box.faces)
    axis = np.eye(3)
    monkeypatch.setattr(bvh_module, "RAYS", np.concatenate([axis, -axis])[[0, 3, 1, 4, 2, 5]])  # +x, -x, +y, ...)
    grid = np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, 5)] * 3), -1).reshape(-1, 3) * 0.98
    grid[:, 0] = np.where(np.abs(grid[:, 0]) > 0.4, grid[:, 0], 0.0)  # x = 0: the cube's diagonal edges
    bvh = MeshBVH(v, f)
    _, undecided = bvh.crossings(grid)
    assert undecided.any()
    winding = winding_numbers(grid, v, f, bvh)
    assert np.abs(winding - igl.winding_number(v, f, grid)).max() < 1e-9
    assert set(np.round(winding).tolist()) == {1.0}


def test_is_closed(hands, objects):
    _, faces, _ = hands["flat"]
    faces = np.asarray(faces, dtype=np.int64)
    assert is_closed(faces)
    assert not is_closed(faces[1:])  # a hole
    flipped = faces.copy()
    flipped[0] = flipped[0, ::-1]
    assert not is_closed(flipped)  # inconsistent orientation


def test_open_mesh_keeps_winding_fallback(objects):
    """An open mesh (a face removed) is not closed: the fast-winding-number path decides its sign."""
    vertices, faces = objects["002_master_chef_can"]
    open_faces = np.delete(faces, 100, axis=0)
    points = near_and_inside(vertices, faces, 300, np.random.default_rng(5))
    got, _ = signed_distance(points, vertices, open_faces, False)
    old, _ = signed_distance(points, vertices, open_faces, False, backend="igl")
    assert np.array_equal(np.sign(got), np.sign(old))
    assert np.abs(got - old).max() < EXACT


def test_tree_shape_kept_and_refit_for_a_new_pose(hands):
    """The flat hand's tree shape serves the curled hand (same faces): refit, still exact."""
    flat, faces, _ = hands["flat"]
    curled, _, root = hands["curled"]
    v0, f = validate_mesh(flat, faces)
    v1, _ = validate_mesh(curled, faces)
    bvh_module._TOPOLOGIES.clear()
    first = topology(v0, f)
    assert topology(v1, f) is first
    points = query_points(v1, f, root, 4)
    dist, _, _, _ = MeshBVH(v1, f).closest(points)
    ref, _ = brute_force_signed_distance(points, v1, f)
    assert np.abs(dist - np.abs(ref)).max() < EXACT


def test_sdf_samples_same_with_either_backend_and_setting_checked(hands, objects):
    hv, hf, root = hands["curled"]
    ov, of = objects["011_banana"]
    points = query_points(hv, hf, root, 6)
    parts = np.arange(len(hf)) % 16
    new = compute_sdf_samples(points, hv, hf, parts, ov, of, True)
    old = compute_sdf_samples(points, hv, hf, parts, ov, of, True, backend="igl")
    for a, b in zip(new[:2], old[:2]):
        assert np.abs(a - b).max() < EXACT and np.array_equal(np.sign(a), np.sign(b))
    with pytest.raises(ValueError, match="backend"):
        signed_distance(points, hv, hf, True, backend="trimesh")
    with pytest.raises(DataError, match="record.sdf_backend"):
        load_build_config("toy", ['record.sdf_backend="trimesh"'])
    assert load_build_config("toy").record.sdf_backend == "bvh"
