"""Exact plausibility metrics (hoisdf.scoring.plausibility, hoisdf.scoring.solids) against analytic cases,
a brute-force reference on a posed (self-intersecting) toy MANO hand, and the literature's surface-voxel script
(restated in bench/plausibility_cases.py, the table of docs/plausibility.md)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import trimesh

from hoidata.geometry.sdf import brute_force_signed_distance, signed_distance
from hoisdf.scoring.plausibility import (
    frame_metrics,
    intersection_bounds,
    self_penetration_bounds,
    summarize,
    vertex_areas,
)
from hoisdf.scoring.solids import MeshSolid, self_crossing_faces, tangled_surface
from tests.test_sdf import posed_hand

TOL = 3e-7  # m^3 (0.3 cm^3) for the analytic cases (0.65-1.8 cm^3): a few seconds in all on one core


def _bench():
    path = Path(__file__).resolve().parents[1] / "bench" / "plausibility_cases.py"
    spec = importlib.util.spec_from_file_location("plausibility_cases", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bench():
    return _bench()


@pytest.fixture(scope="module")
def curled(mano_right):
    """The toy hand curled (twice the toy grasp mean) so that its fingers press through the palm: closed, camera
    frame (tests/test_sdf.py's posed_hand)."""
    vertices, faces, _ = posed_hand(mano_right, 2.0, 2)
    return vertices, faces


def brute_winding(points, vertices, faces, chunk: int = 256) -> np.ndarray:
    """Generalized winding number by summing every face's solid angle (Van Oosterom and Strackee), numpy."""
    tri = vertices[faces][None]  # (1, F, 3, 3)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        r = tri - points[s:s + chunk, None, None, :]  # (m, F, 3, 3)
        a, b, c = r[..., 0, :], r[..., 1, :], r[..., 2, :]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("...k,...k", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("...k,...k", a, b) * lc + np.einsum("...k,...k", a, c) * lb \
            + np.einsum("...k,...k", b, c) * la
        out[s:s + chunk] = 2 * np.arctan2(det, den).sum(1) / (4 * np.pi)
    return out


# ---------------------------------------------------------------- analytic cases

def test_analytic_cases_meet_their_tolerance(bench):
    for name, case in bench.cases().items():
        exact = bench.polyhedral_volume(case["hand"], case["object"])  # manifold3d's exact boolean
        # the meshes are fine: the polyhedra are within 1 % of the analytic solids
        assert exact == pytest.approx(case["analytic"], rel=0.01), name
        est = intersection_bounds(*case["hand"], *case["object"], tolerance=TOL)
        assert est.guaranteed and est.error_bound <= TOL, name
        assert est.lower - 1e-15 <= exact <= est.upper + 1e-15, name
        assert abs(est.volume - exact) <= TOL, name
        # swapping the roles of the two meshes gives the same solid
        swapped = intersection_bounds(*case["object"], *case["hand"], tolerance=TOL)
        assert abs(swapped.volume - exact) <= TOL, name


def test_relative_tolerance_and_budget(bench):
    case = bench.cases()["cylinder through box"]
    est = intersection_bounds(*case["hand"], *case["object"], tolerance=1e-12, rel_tolerance=0.1)
    assert est.error_bound <= 0.1 * est.lower and est.lower <= case["analytic"] <= est.upper
    from hoisdf.scoring.solids import MeshSolid, Part, region_volume

    a, b = MeshSolid(*case["hand"]), MeshSolid(*case["object"])
    with pytest.raises(ValueError, match="larger tolerance"):
        region_volume([Part(a), Part(b)], np.maximum(a.lo, b.lo), np.minimum(a.hi, b.hi), 1e-12, max_cells=10_000)
    with pytest.raises(ValueError, match="positive"):
        intersection_bounds(*case["hand"], *case["object"], tolerance=0.0)


def test_surface_voxel_script_reports_a_surface_layer_not_the_solid(bench):
    """The comparison table's method: only object-surface cells inside the hand count, so the value tracks
    (object surface inside the hand) x pitch and misses the interior; our value is the solid overlap."""
    case = bench.cases()["cylinder through box"]
    exact = bench.polyhedral_volume(case["hand"], case["object"])
    coarse = bench.surface_voxel_volume(case["hand"], case["object"], 0.005)
    fine = bench.surface_voxel_volume(case["hand"], case["object"], 0.001)
    # the box's surface inside the cylinder: two ellipses of area pi r^2 / cos(tilt)
    layer = 2 * np.pi * bench.CYL_R ** 2 / np.cos(bench.TILT)
    assert fine < 0.2 * exact and fine == pytest.approx(layer * 0.001, rel=0.5)
    assert coarse < 0.5 * exact
    assert abs(intersection_bounds(*case["hand"], *case["object"], tolerance=TOL).volume - exact) <= TOL


# ---------------------------------------------------------------- a posed hand against brute force

def _points_covered_twice(vertices, faces, rng) -> np.ndarray:
    """Points where the brute-force winding number of the hand is 2 (near the faces that cross each other)."""
    tangled = self_crossing_faces(vertices, faces)
    assert tangled.any(), "the curled toy hand no longer passes through itself; pick a pose that does"
    centres = vertices[faces[tangled]].mean(1)
    points = centres[rng.integers(0, len(centres), 3000)] + rng.normal(scale=0.003, size=(3000, 3))
    w = brute_winding(points, vertices, faces)
    twice = points[np.abs(np.rint(w)) >= 2]
    assert len(twice) >= 5
    return twice


def test_self_intersecting_hand_gets_the_right_sign(curled):
    vertices, faces = curled
    twice = _points_covered_twice(vertices, faces, np.random.default_rng(0))
    solid = MeshSolid(vertices, faces)
    np.testing.assert_array_equal(np.rint(solid.winding(twice)), np.rint(brute_winding(twice, vertices, faces)))
    assert (solid.signed_distance(twice) < 0).all()  # inside the hand, though under two layers of its surface
    ref, _ = brute_force_signed_distance(twice, vertices, faces)
    np.testing.assert_allclose(solid.signed_distance(twice), ref, atol=1e-12)
    assert (signed_distance(twice, vertices, faces, watertight=False)[0] < 0).all()


@pytest.mark.slow
def test_self_penetration_volume(curled, mano_right):
    vertices, faces = curled
    est = self_penetration_bounds(vertices, faces, tolerance=1e-7)
    assert est.guaranteed and est.error_bound <= 1e-7 and est.lower > 0  # some of it is certain
    # Monte Carlo over the box of the tangled parts of the surface (outside them |w| <= 1 by construction)
    tv, _ = tangled_surface(MeshSolid(vertices, faces))
    lo, hi = tv.min(0) - 0.002, tv.max(0) + 0.002
    points = np.random.default_rng(1).uniform(lo, hi, (6000, 3))
    p = (np.abs(np.rint(brute_winding(points, vertices, faces))) >= 2).mean()
    box = float(np.prod(hi - lo))
    assert 0 < p and abs(est.volume - box * p) <= est.error_bound + 5 * box * np.sqrt(p * (1 - p) / len(points))
    flat, flat_faces, _ = posed_hand(mano_right, 0.0, 1)
    assert self_penetration_bounds(flat, flat_faces).upper == 0.0  # nothing crosses: exactly zero
    with pytest.raises(ValueError, match="closed"):
        self_penetration_bounds(flat[:778], flat_faces[:1538])


@pytest.mark.slow
def test_intersection_with_posed_hand_matches_dense_brute_force(curled):
    """A sphere placed where the curled hand covers itself twice: the exact volume (tolerance 1e-7 m^3) against a
    Monte Carlo reference whose inside test is the brute-force winding number of both meshes (20 000 points)."""
    vertices, faces = curled
    centre = _points_covered_twice(vertices, faces, np.random.default_rng(2))[0]
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.006)
    bv, bf = np.asarray(ball.vertices) + centre, np.asarray(ball.faces)
    est = intersection_bounds(vertices, faces, bv, bf, tolerance=1e-7)
    lo, hi = np.maximum(vertices.min(0), bv.min(0)), np.minimum(vertices.max(0), bv.max(0))
    rng = np.random.default_rng(3)
    points = rng.uniform(lo, hi, (20000, 3))
    inside = (np.abs(brute_winding(points, bv, bf)) > 0.5)
    inside[inside] = np.abs(brute_winding(points[inside], vertices, faces)) > 0.5
    box = float(np.prod(hi - lo))
    p = inside.mean()
    reference, sigma = box * p, box * np.sqrt(p * (1 - p) / len(points))
    assert 0.05 < p < 0.95
    assert abs(est.volume - reference) <= est.error_bound + 5 * sigma


# ---------------------------------------------------------------- contact, IVU, per-frame summary

def test_contact_area_ivu_and_summary(bench):
    box_v, box_f = bench.cases()["box and sphere (cap)"]["object"]
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.01)
    bv, bf = np.asarray(ball.vertices), np.asarray(ball.faces)
    np.testing.assert_allclose(vertex_areas(bv, bf).sum(), ball.area, rtol=1e-12)
    deep = frame_metrics(bv + [0, 0, 0.0249], bf, box_v, box_f, tolerance=TOL)  # cap of height 5.1 mm
    assert deep["penetration_depth_mm"] == pytest.approx(5.1, abs=1e-6) and deep["contact"] == 1.0
    area = vertex_areas(bv, bf)[bv[:, 2] + 0.0249 <= 0.025].sum()  # inside, or within 5 mm of the face z = 0.02
    assert deep["contact_area_cm2"] == pytest.approx(area * 1e4)
    assert deep["ivu_cm"] == pytest.approx(deep["intersection_volume_cm3"] / deep["contact_area_cm2"])
    far = frame_metrics(bv + [0, 0, 0.05], bf, box_v, box_f, tolerance=TOL)
    assert far["contact"] == 0.0 and np.isnan(far["ivu_cm"]) and far["intersection_volume_cm3"] == 0.0
    mean = summarize([deep, far], TOL)
    assert mean["contact_ratio"] == 0.5 and mean["ivu_frames"] == 1 and mean["ivu_cm"] == deep["ivu_cm"]
    assert mean["penetration_depth_mm"] == pytest.approx(2.55, abs=1e-6)
    assert np.isnan(summarize([])["contact_ratio"])


def test_depth_and_contact_on_posed_hand_match_brute_force(mano_right):
    """Penetration depth and contact area of a posed toy hand against a sphere sunk into its palm side, from the
    brute-force signed distance (every hand vertex against every object face)."""
    vertices, faces, _ = posed_hand(mano_right, 1.0, 4)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.015)
    bv, bf = np.asarray(ball.vertices) + vertices[:778].mean(0), np.asarray(ball.faces)
    got = frame_metrics(vertices, faces, bv, bf, tolerance=1e-6, rel_tolerance=0.05, n_points=778)
    ref, _ = brute_force_signed_distance(vertices[:778], bv, bf)
    assert (ref < 0).any() and got["penetration_depth_mm"] == pytest.approx(-ref.min() * 1e3, abs=1e-9)
    area = vertex_areas(vertices, faces)[:778][ref <= 0.005].sum()
    assert got["contact_area_cm2"] == pytest.approx(area * 1e4, rel=1e-12)
    assert got["vertex_contact_ratio"] == pytest.approx((ref <= 0.005).mean())
    assert got["ivu_cm"] == pytest.approx(got["intersection_volume_cm3"] / got["contact_area_cm2"])


def test_inherited_membership_changes_no_number(bench, monkeypatch):
    """Children inside a parent's decided ball take its inside/outside instead of casting rays
    (hoisdf.scoring.solids._child_hints): the bounds and the estimate are the same as with every centre asked."""
    from hoisdf.scoring import solids

    cases = bench.cases()
    pairs = [(cases["two spheres (lens)"]["hand"], cases["two spheres (lens)"]["object"]),
             (cases["box and sphere (cap)"]["hand"], cases["box and sphere (cap)"]["object"])]
    tight = 3e-9  # m^3: exact cells meet TOL on the first level; this needs children
    with_hints = [intersection_bounds(*h, *o, tight) for h, o in pairs]
    asked = {"n": 0}
    real = solids._child_hints

    def no_hints(parts, per_part, open_, radius):
        hints = real(parts, per_part, open_, radius)
        asked["n"] += sum(int(known.sum()) for known, _ in hints)
        return [(np.zeros_like(known), member) for known, member in hints]

    monkeypatch.setattr(solids, "_child_hints", no_hints)
    without = [intersection_bounds(*h, *o, tight) for h, o in pairs]
    assert asked["n"] > 0  # the hints did spare ray casts
    assert with_hints == without


def test_frames_on_worker_processes_equal_frames_here(bench):
    """frame_metrics_many on 2 spawned processes: the same numbers, in the samples' order."""
    from hoisdf.scoring.plausibility import frame_metrics_many

    box_v, box_f = bench.cases()["box and sphere (cap)"]["object"]
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.01)
    bv, bf = np.asarray(ball.vertices), np.asarray(ball.faces)
    samples = [(bv + [0, 0, z], bf, box_v, box_f) for z in (0.05, 0.0249, 0.027, 0.05)]
    here = frame_metrics_many(samples, 1, tolerance=TOL)
    there = frame_metrics_many(samples, 2, tolerance=TOL)
    assert [f["contact"] for f in here] == [0.0, 1.0, 1.0, 0.0]
    for a, b in zip(here, there):
        np.testing.assert_equal(a, b)


def test_a_volume_does_not_depend_on_which_pose_of_its_faces_came_first(bench):
    """A cube's column integral sums over the faces met in tree order, and a face array's tree shape is kept across
    poses (the build refits it), so a volume once depended in its last bits on the pose of the same faces a process
    had seen first: 15 of 20 earlier poses moved this one on bb9a884, and a pytest worker disagreed with a fresh
    process. The scorer's solids build each pose's own tree (MeshBVH pose_shape)."""
    from hoidata.geometry import bvh
    from hoisdf.scoring.plausibility import frame_metrics

    box_v, box_f = bench.cases()["box and sphere (cap)"]["object"]
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.01)
    bv, bf = np.asarray(ball.vertices) + [0, 0, 0.027], np.asarray(ball.faces)
    bvh._TOPOLOGIES.clear()
    fresh = frame_metrics(bv, bf, box_v, box_f, tolerance=TOL)
    for seed in range(4):
        rng = np.random.default_rng(seed)
        bvh._TOPOLOGIES.clear()
        bvh.topology(bv * rng.uniform(0.5, 2, 3) + rng.normal(0, 0.01, bv.shape), bf)  # another pose came first
        bvh.topology(box_v + rng.normal(0, 0.01, box_v.shape), box_f)
        assert frame_metrics(bv, bf, box_v, box_f, tolerance=TOL) == fresh  # bit for bit: same inputs, same process


def test_the_evaluator_report_and_the_scorer_share_one_budget(mano_right, monkeypatch):
    """The evaluator's report (scoring.plausibility_of) spends at most the scorer's cell budget per volume, with the
    same tolerances (docs/plausibility.md, "How exact"): one constant, not two that drift apart."""
    from hoisdf.scoring import plausibility, score_contact
    from hoisdf.evaluation.model_scores import plausibility_of

    seen = []

    def record(*sample, **settings):
        seen.append(settings)
        return dict.fromkeys((*plausibility.SUMMARY_KEYS, "contact", "tolerance_met"), 0.0)

    monkeypatch.setattr(plausibility, "frame_metrics", record)
    box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    plausibility_of({"model": (np.zeros((2, 778, 3)), np.tile(np.eye(4), (2, 1, 1)), [(box.vertices, box.faces)] * 2)},
                    mano_right, progress=False)
    assert len(seen) == 2
    assert {s["max_cells"] for s in seen} == {score_contact.MAX_CELLS} == {plausibility.BUDGET}
    assert {s["rel_tolerance"] for s in seen} == {plausibility.REL_TOLERANCE}
    assert {s["tolerance"] for s in seen} == {plausibility.TOLERANCE}
