"""Tests for hoidata.geometry.sdf and hoidata.geometry.sampling: libigl against the brute-force
reference, the reference against analytic shapes, holes, sampling layout, quantization, parts."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from hoidata.geometry import sdf as sdf_module
from hoidata.geometry.sampling import (
    SdfSampling,
    build_sdf_record,
    compute_sdf_samples,
    sample_query_points,
    split_counts,
    surface_points,
)
from hoidata.geometry.sdf import (
    brute_force_signed_distance,
    closest_point_on_triangles,
    signed_distance,
)
from hoidata.objects import load_object_mesh, repair_mesh
from hoidata.schema import NO_PART, SDF_QUANTUM, dequantize_sdf
from hoidata.toy.objects import write_toy_objects

EXACT = 1e-9  # metres: libigl and the reference are both exact float64 computations
CAMERA_T = np.array([0.03, -0.02, 0.55])  # a typical hand position in the camera frame, metres


def posed_hand(mano, curl: float, seed: int):
    """Closed hand (vertices (779, 3), faces (1554, 3)) and root (3,), camera frame, metres:
    fingers at ``curl`` times the toy grasp mean, a random global rotation, 0.55 m from the camera."""
    pose = torch.zeros(1, 48, dtype=torch.float64)
    pose[0, :3] = torch.as_tensor(Rotation.random(random_state=seed).as_rotvec())
    pose[0, 3:] = mano.hands_mean * curl
    out = mano(pose, transl=torch.as_tensor(CAMERA_T)[None])
    return mano.close(out.vertices)[0].numpy(), np.asarray(mano.closed_faces), out.joints[0, 0].numpy()


def near_and_inside(vertices, faces, n: int, rng) -> np.ndarray:
    """Points near the surface (3 and 10 mm offsets, about half inside) plus points deep inside:
    vertices pulled a little toward the mesh centroid."""
    tri = vertices[faces[rng.integers(0, len(faces), n)]]
    w = rng.dirichlet(np.ones(3), n)
    near = np.einsum("nk,nkd->nd", w, tri) + rng.normal(size=(n, 3)) * np.repeat([0.01, 0.003], [n - n // 2, n // 2])[:, None]
    pulled = vertices[rng.integers(0, len(vertices), n // 4)]
    pulled = pulled + 0.15 * (vertices.mean(0) - pulled)
    return np.concatenate([near, pulled])


def posed_hands(mano) -> dict:
    """The toy hand flat, and curled so that it passes through itself."""
    return {"flat": posed_hand(mano, 0.0, 1), "curled": posed_hand(mano, 1.2, 2)}


def posed_objects(root, seed: int) -> dict:
    """{name: (vertices, faces)}: repaired toy objects (watertight), rotated at random (``seed`` + k) and moved
    into the camera frame 5 cm behind the hand."""
    out = {}
    for k, path in enumerate(write_toy_objects(root, ["011_banana", "002_master_chef_can"])):
        mesh, report = repair_mesh(load_object_mesh(path))
        assert report.watertight
        rot = Rotation.random(random_state=seed + k).as_matrix()
        out[path.parent.name] = (np.asarray(mesh.vertices) @ rot.T + CAMERA_T + [0, 0, 0.05], np.asarray(mesh.faces))
    return out


@pytest.fixture(scope="module")
def hands(mano_right):
    return posed_hands(mano_right)


@pytest.fixture(scope="module")
def objects(tmp_path_factory):
    return posed_objects(tmp_path_factory.mktemp("sdf_models"), 10)


def assert_matches_reference(points, vertices, faces, watertight):
    got, face = signed_distance(points, vertices, faces, watertight)
    ref, _ = brute_force_signed_distance(points, vertices, faces)
    assert np.abs(got - ref).max() < EXACT
    assert np.array_equal(np.sign(got), np.sign(ref))
    # The returned face attains the distance (ties between faces sharing the closest point are fine).
    tri = vertices[faces[face]]
    own = np.linalg.norm(points - closest_point_on_triangles(points, tri[:, 0], tri[:, 1], tri[:, 2]), axis=1)
    assert np.abs(own - np.abs(got)).max() < EXACT
    return got


# ---------------------------------------------------------------- the reference itself

def test_brute_force_unit_cube_is_analytic():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    points = np.random.default_rng(0).uniform(-1.5, 1.5, (3000, 3))
    q = np.abs(points) - 0.5
    analytic = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
    ref, _ = brute_force_signed_distance(points, box.vertices, box.faces)
    assert np.abs(ref - analytic).max() < 1e-12
    assert (ref < 0).sum() > 100  # about 1/27 of the points are inside


def test_brute_force_sphere_is_within_faceting_of_analytic():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inradius = np.min(np.einsum("ij,ij->i", normals / np.linalg.norm(normals, axis=1, keepdims=True), v[f[:, 0]]))
    points = np.random.default_rng(1).uniform(-1.6, 1.6, (1000, 3))
    radius = np.linalg.norm(points, axis=1)
    ref, _ = brute_force_signed_distance(points, v, f)
    # The polyhedron lies between the inscribed radius and the unit sphere.
    assert np.abs(ref - (radius - 1.0)).max() <= 1.0 - inradius + 1e-12
    assert np.all(ref[radius < inradius] < 0) and np.all(ref[radius > 1.0] > 0)


# ---------------------------------------------------------------- libigl against the reference

@pytest.mark.parametrize("pose", [pytest.param("flat", marks=pytest.mark.slow), "curled"])
def test_igl_matches_reference_on_posed_hand(hands, pose):
    vertices, faces, root = hands[pose]
    rng = np.random.default_rng(3)
    points = np.concatenate([near_and_inside(vertices, faces, 600, rng), root + rng.uniform(-0.15, 0.15, (100, 3))])
    got = assert_matches_reference(points, vertices, faces, watertight=False)
    assert (got < 0).sum() > 200  # the test really covers inside points
    if pose == "flat":  # no self-overlap in the flat pose: the pseudonormal sign is exact as well
        assert_matches_reference(points, vertices, faces, watertight=True)


def test_default_hand_sign_survives_self_overlap(hands):
    """The curled toy hand passes through itself (thumb base and palm). Where the pseudonormal and
    the winding-number sign disagree, the brute-force reference must side with the winding number,
    which is why compute_sdf_samples uses it for the hand by default."""
    vertices, faces, _ = hands["curled"]
    points = near_and_inside(vertices, faces, 20000, np.random.default_rng(6))
    pseudo, _ = signed_distance(points, vertices, faces, watertight=True)
    winding, _ = signed_distance(points, vertices, faces, watertight=False)
    differ = np.sign(pseudo) != np.sign(winding)
    assert differ.any(), "the curled toy hand no longer self-overlaps; pick a pose that does"
    ref, _ = brute_force_signed_distance(points[differ], vertices, faces)
    assert np.array_equal(np.sign(ref), np.sign(winding[differ]))
    default, _, _ = compute_sdf_samples(points[differ], vertices, faces, np.zeros(len(faces), np.int64),
                                        vertices, faces, True)
    assert np.array_equal(default, winding[differ])


@pytest.mark.parametrize("watertight", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_igl_matches_reference_on_toy_object(objects, watertight):
    vertices, faces = objects["011_banana"]
    points = near_and_inside(vertices, faces, 500, np.random.default_rng(4))
    got = assert_matches_reference(points, vertices, faces, watertight)
    assert (got < 0).sum() > 150


def test_open_object_uses_winding_number_and_keeps_signs(objects, monkeypatch):
    vertices, closed_faces = objects["002_master_chef_can"]
    hole = 100
    faces = np.delete(closed_faces, hole, axis=0)
    rng = np.random.default_rng(5)
    points = near_and_inside(vertices, closed_faces, 800, rng)
    truth, _ = signed_distance(points, vertices, closed_faces, watertight=True)
    calls = []
    real = sdf_module.igl.fast_winding_number
    monkeypatch.setattr(sdf_module.igl, "fast_winding_number", lambda *a: calls.append(1) or real(*a))
    hand_v, hand_f = vertices + 1.0, closed_faces  # any mesh far away: only the object matters here
    _, got, _ = compute_sdf_samples(points, hand_v, hand_f, np.zeros(len(hand_f), np.int64), vertices, faces,
                                    obj_watertight=False, hand_pseudonormal=True)
    assert len(calls) == 1  # the object, not the hand
    # Clearly inside/outside: away from the surface and from the hole.
    far_from_hole = np.linalg.norm(points - vertices[closed_faces[hole]].mean(0), axis=1) > 0.01
    clear = (np.abs(truth) > 0.002) & far_from_hole
    assert clear.sum() > 500 and (truth[clear] < 0).sum() > 100
    assert np.array_equal(np.sign(got[clear]), np.sign(truth[clear]))
    assert np.abs(np.abs(got) - np.abs(brute_force_signed_distance(points, vertices, faces)[0])).max() < EXACT


def test_winding_sign_equals_exact_winding_number_at_a_hole(objects, monkeypatch):
    """Near a hole the winding number is fractional: the fast estimate is ambiguous there and the
    exact one must decide, so the sign equals thresholding libigl's exact winding number."""
    vertices, closed_faces = objects["002_master_chef_can"]
    hole = 100
    faces = np.delete(closed_faces, hole, axis=0).astype(np.int64)
    a, b, c = vertices[closed_faces[hole]]
    normal = np.cross(b - a, c - a) / np.linalg.norm(np.cross(b - a, c - a))
    rng = np.random.default_rng(11)
    points = (a + b + c) / 3 + np.linspace(-0.003, 0.003, 400)[:, None] * normal + rng.normal(0, 5e-4, (400, 3))
    exact = []
    real = sdf_module.igl.winding_number
    monkeypatch.setattr(sdf_module.igl, "winding_number", lambda *args: exact.append(len(args[2])) or real(*args))
    inside = sdf_module.winding_inside(points, vertices, faces)
    assert exact and exact[0] < len(points)  # only the ambiguous points were recomputed
    assert np.array_equal(inside, np.abs(real(vertices, faces, points)) > 0.5)
    assert 0 < inside.sum() < len(points)


# ---------------------------------------------------------------- sampling

def test_split_counts_sum_and_defaults():
    assert split_counts(4096, 2048, 0.1).tolist() == [3687, 1843, 614]
    assert split_counts(5, 3, 0.5).tolist() == [2, 2, 4]  # round(2.5) goes up
    for n_hand, n_object, frac in [(0, 7, 0.3), (7, 0, 1.0), (1, 1, 0.25), (0, 0, 0.1), (999, 1, 0.999)]:
        counts = split_counts(n_hand, n_object, frac)
        assert counts.sum() == n_hand + n_object and np.all(counts >= 0)
        assert counts[0] <= n_hand and counts[1] <= n_object


def test_sampling_layout_and_determinism(hands, objects):
    hv, hf, root = hands["curled"]
    ov, of = objects["011_banana"]
    points, counts = sample_query_points(hv, hf, ov, of, root, np.random.default_rng(7))
    assert points.shape == (6144, 3) and counts.tolist() == [3687, 1843, 614]
    again, _ = sample_query_points(hv, hf, ov, of, root, np.random.default_rng(7))
    other, _ = sample_query_points(hv, hf, ov, of, root, np.random.default_rng(8))
    assert np.array_equal(points, again) and not np.allclose(points, other)

    n_h, n_o, _ = counts
    d_hand = np.abs(signed_distance(points, hv, hf, True)[0])
    d_obj = np.abs(signed_distance(points, ov, of, True)[0])
    for dist, n in ((d_hand[:n_h], n_h), (d_obj[n_h:n_h + n_o], n_o)):
        wide, narrow = dist[: n - n // 2], dist[n - n // 2:]  # 10 mm block, then 3 mm block
        assert wide.max() < 5 * 0.010 and np.mean(wide < 4 * 0.010) > 0.99
        assert narrow.max() < 5 * 0.003 and np.mean(narrow < 4 * 0.003) > 0.99
        assert np.median(wide) > 2 * np.median(narrow)
    uniform = points[n_h + n_o:] - root
    assert np.abs(uniform).max() <= 0.32 and np.abs(uniform).max(0).min() > 0.3


def test_surface_points_are_the_numpy_draws_bit_for_bit(hands, objects):
    """The compiled area-weighted sampler gives the bits of its numpy form (np.cross and norm areas, rng.choice
    by area, two rng.random draws) and leaves the generator in the same state."""
    for vertices, faces in (hands["curled"][:2], objects["011_banana"]):
        for n in (1, 7, 3000):
            rng, ref_rng = np.random.default_rng(n), np.random.default_rng(n)
            got = surface_points(vertices, faces, n, rng)
            tri = vertices[faces]
            areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            pick = ref_rng.choice(len(faces), size=n, p=areas / areas.sum())
            r1, r2 = ref_rng.random(n), ref_rng.random(n)
            s, t = np.sqrt(r1), tri[pick]
            want = (1 - s)[:, None] * t[:, 0] + (s * (1 - r2))[:, None] * t[:, 1] + (s * r2)[:, None] * t[:, 2]
            assert np.array_equal(got, want) and rng.random() == ref_rng.random()


def test_record_round_trip_and_parts(hands, objects):
    hv, hf, root = hands["curled"]
    ov, of = objects["011_banana"]
    parts = np.arange(len(hf)) % 16
    args = (hv, hf, parts, ov, of, True, root)
    sampling = SdfSampling(n_hand=900, n_object=300, part_radius=0.01)
    stored, counts = build_sdf_record(*args, np.random.default_rng(9), sampling)
    assert stored.dtype == np.int16 and stored.shape == (1200, 6) and counts.sum() == 1200

    points, _ = sample_query_points(hv, hf, ov, of, root, np.random.default_rng(9), n_hand=900, n_object=300)
    sdf_h, sdf_o, part = compute_sdf_samples(points, hv, hf, parts, ov, of, True, part_radius=0.01)
    xyz, q_h, q_o, q_part = dequantize_sdf(stored)
    tol = 0.5 * SDF_QUANTUM + 1e-7  # rounding plus float32 storage of up to 0.35 m
    assert np.abs(xyz - (points - root)).max() <= tol
    assert np.abs(q_h - sdf_h).max() <= tol and np.abs(q_o - sdf_o).max() <= tol
    assert np.array_equal(q_part, part)

    _, face = signed_distance(points, hv, hf, watertight=False)
    near = np.abs(sdf_h) <= 0.01
    assert near.sum() > 100 and (~near).sum() > 100
    assert np.all(part[~near] == NO_PART)
    assert np.array_equal(part[near], parts[face[near]])


# ---------------------------------------------------------------- bad input

def test_bad_input_raises(hands, objects):
    hv, hf, root = hands["flat"]
    ov, of = objects["011_banana"]
    p = np.zeros((4, 3))
    bad_calls = [
        lambda: signed_distance(np.zeros((4, 2)), hv, hf, True),
        lambda: signed_distance(np.full((4, 3), np.nan), hv, hf, True),
        lambda: signed_distance(p, hv, np.zeros((0, 3), np.int64), True),
        lambda: signed_distance(p, hv, hf + len(hv), True),
        lambda: signed_distance(p, hv, hf.astype(np.float64), True),
        lambda: signed_distance(p, hv[:, :2], hf, False),
        lambda: brute_force_signed_distance(p, np.inf * hv, hf),
        lambda: compute_sdf_samples(p, hv, hf, np.zeros(3, np.int64), ov, of, True),
        lambda: sample_query_points(hv, hf, ov, of, root, np.random.default_rng(0), n_hand=-1),
        lambda: sample_query_points(hv, hf, ov, of, root, np.random.default_rng(0), uniform_fraction=1.5),
        lambda: sample_query_points(hv, hf, ov, of, root, np.random.default_rng(0), cube=0.0),
        lambda: sample_query_points(hv, hf, ov, of, root, np.random.default_rng(0), sigmas=(0.01, -1.0)),
        lambda: sample_query_points(hv, hf, ov, of, root[:2], np.random.default_rng(0)),
        lambda: sample_query_points(hv, hf, ov, of, root, 0),
    ]
    for call in bad_calls:
        with pytest.raises(ValueError):
            call()
    empty, face = signed_distance(np.zeros((0, 3)), hv, hf, True)
    assert empty.shape == (0,) and face.shape == (0,)
