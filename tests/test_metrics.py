"""Evaluation metrics: known transforms give known errors; AUC, F-score and grouping edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from hoisdf.scoring import metrics as M


@pytest.fixture
def joints():
    rng = np.random.default_rng(0)
    return rng.normal(scale=0.05, size=(6, 21, 3)) + np.array([0.0, 0.0, 0.6])


def _rigid(rot: np.ndarray, t) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, t
    return pose


def test_identical_inputs_give_zero_error(joints):
    assert np.allclose(M.mje(joints, joints), 0)
    assert np.allclose(M.pa_mje(joints, joints), 0, atol=1e-8)  # align_w_scale's 1e-8 m shrinks the fit by ~1e-7
    assert np.allclose(M.pa_mje(joints, joints, reflection=False), 0, atol=1e-8)
    assert np.allclose(M.st_mje(joints, joints), 0)
    assert np.allclose(M.mme(joints, joints), 0)
    assert M.auc(M.point_errors(joints, joints)) == 1.0


def test_translation_only_changes_absolute_mje(joints):
    t = np.array([0.01, -0.02, 0.03])
    pred = joints + t
    assert np.allclose(M.mje(pred, joints), np.linalg.norm(t))
    assert np.allclose(M.mje(pred, joints, root_relative=True), 0)
    # A different root: only one moved joint, wrist-relative error spreads over the others.
    pred2 = joints.copy()
    pred2[:, 0] += t
    assert np.allclose(M.mje(pred2, joints, root_relative=True), 20 * np.linalg.norm(t) / 21)


def _align_w_scale(g, p):
    """FreiHAND / HO-3D eval.py ``align_w_scale`` (also dex-ycb-toolkit's procrustes row), restated for one set."""
    from scipy.linalg import orthogonal_procrustes

    t1, t2 = g.mean(0), p.mean(0)
    s1, s2 = np.linalg.norm(g - t1) + 1e-8, np.linalg.norm(p - t2) + 1e-8
    r, s = orthogonal_procrustes((g - t1) / s1, (p - t2) / s2)
    return ((p - t2) / s2) @ r.T * s * s1 + t1, np.linalg.det(r)


def test_procrustes_removes_similarity_and_the_official_one_a_reflection(joints):
    rots = Rotation.random(len(joints), random_state=1).as_matrix()
    pred = 1.7 * np.einsum("nij,nkj->nki", rots, joints) + np.array([0.3, -0.1, 0.2])
    for reflection in (True, False):
        assert np.allclose(M.pa_mje(pred, joints, reflection=reflection), 0, atol=1e-8)
        assert np.allclose(M.procrustes_align(pred, joints, reflection=reflection), joints, atol=1e-8)
    assert np.all(M.mje(pred, joints) > 0.05)
    mirrored = joints * np.array([-1.0, 1.0, 1.0])  # a reflection: no proper rotation undoes it
    assert np.allclose(M.pa_mje(mirrored, joints), 0, atol=1e-8)  # the evaluators' alignment admits it
    assert np.all(M.pa_mje(mirrored, joints, reflection=False) > 1e-3)
    metrics = M.joint_metrics(mirrored, joints)
    assert np.all(metrics["pa_mje"] < 1e-8) and np.all(metrics["pa_mje_no_reflection"] > 1e-3)
    # Rigid only: a scaled copy keeps an error.
    assert np.all(M.point_errors(M.procrustes_align(2 * joints, joints, scale=False), joints).mean(1) > 1e-3)


def test_procrustes_matches_freihand_align_w_scale(joints):
    rng = np.random.default_rng(5)
    rot = Rotation.random(random_state=5).as_matrix()
    near = 0.9 * joints @ rot.T + rng.normal(scale=0.01, size=joints.shape)
    flat = joints * np.array([1.0, 1.0, 0.05])  # near-flat hands: the best fit is a mirror image for some
    flat_pred = flat * np.array([-1.0, 1.0, 1.0]) @ rot.T + rng.normal(scale=0.003, size=joints.shape)
    dets = []
    for pred, gt in ((near, joints), (flat_pred, flat)):
        for p, g, ours in zip(pred, gt, M.procrustes_align(pred, gt)):
            ref, det = _align_w_scale(g, p)
            np.testing.assert_allclose(ours, ref, atol=1e-12)
            dets.append(det)
    assert min(dets) < 0 < max(dets)  # both proper and improper fits were exercised


def test_procrustes_single_set_and_degenerate():
    gt = np.random.default_rng(2).normal(size=(21, 3))
    assert M.procrustes_align(gt + 1.0, gt).shape == (1, 21, 3)
    flat = np.zeros((21, 3))
    assert np.allclose(M.procrustes_align(flat, gt)[0], gt.mean(0))


def test_st_mje_scale_translation_but_not_rotation(joints):
    wrist = joints[:, :1]
    pred = (joints - wrist) * 0.8 + wrist + np.array([0.05, 0.0, -0.02])
    assert np.allclose(M.st_mje(pred, joints), 0, atol=1e-12)
    rot = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    rotated = (joints - wrist) @ rot.T + wrist
    assert np.all(M.st_mje(rotated, joints) > 1e-3)
    assert np.allclose(M.pa_mje(rotated, joints), 0, atol=1e-8)
    # The scale comes from wrist -> middle MCP (joint 9): stretching only that bone changes the result.
    moved = joints.copy()
    moved[:, 9] = wrist[:, 0] + 2 * (joints[:, 9] - wrist[:, 0])
    assert not np.allclose(M.st_mje(moved, joints), M.mje(moved, joints, root_relative=True))


def test_auc_edge_and_hand_computed_cases():
    assert M.auc(np.zeros(50)) == 1.0
    assert M.auc(np.full(50, 0.0501)) == 0.0
    # thresholds [0, 1, 2]: errors {0, 1.5} -> PCK [0.5, 0.5, 1] -> area 0.5 + 0.75 = 1.25, / 2.
    assert M.auc([0.0, 1.5], lo=0.0, hi=2.0, steps=3) == pytest.approx(0.625)
    # 25 mm everywhere on 0-50 mm in 100 steps: PCK jumps halfway between threshold 49 and 50.
    assert M.auc(np.full(10, 0.025)) == pytest.approx(0.5)
    assert np.allclose(M.pck_curve([0.0, 1.0, 2.0], [0.5, 1.0, 3.0]), [1 / 3, 2 / 3, 1.0])
    errs = np.random.default_rng(3).uniform(0, 0.06, size=(7, 21))
    assert M.auc_per_sample(errs).mean() == pytest.approx(M.auc(errs))
    with pytest.raises(ValueError):
        M.auc([0.1], lo=1.0, hi=0.5)


def test_vauc_and_pa_mesh(joints):
    pred = joints + 0.1  # far away but a pure translation
    assert np.allclose(M.vauc(pred, joints), 0.0)
    # Rounding leaves aligned errors of ~1e-17, above the first threshold (0): that costs half a step.
    assert np.all(M.vauc(pred, joints, procrustes=True) >= 1.0 - 0.5 / 99 - 1e-12)
    assert np.allclose(M.pa_mme(pred, joints), 0, atol=1e-8)


def test_f_score_edge_cases():
    pts = np.random.default_rng(4).uniform(size=(30, 3))
    assert M.f_score(pts, pts, 0.005) == (1.0, 1.0, 1.0)
    assert M.f_score(np.zeros((0, 3)), pts, 0.005) == (0.0, 0.0, 0.0)
    assert M.f_score(pts, [], 0.005) == (0.0, 0.0, 0.0)
    assert M.f_score(pts, pts + 10.0, 0.005) == (0.0, 0.0, 0.0)
    # Prediction = GT plus as many far points: precision 1/2, recall 1, F = 2/3.
    f, precision, recall = M.f_score(np.concatenate([pts, pts + 10.0]), pts, 0.005)
    assert (precision, recall) == (0.5, 1.0) and f == pytest.approx(2 / 3)
    batch = np.stack([pts, pts])
    assert np.allclose(M.f_scores(batch, batch + np.array([0.004, 0, 0]), 0.005), 1.0)
    assert np.allclose(M.f_scores(batch, batch + np.array([0.006, 0, 0]), 0.005), 0.0)
    assert np.allclose(M.f_scores(batch, batch + np.array([0.006, 0, 0]), 0.005, procrustes=True), 1.0)


def test_object_metrics_translation_and_symmetry():
    cyl = trimesh.creation.cylinder(radius=0.04, height=0.1, sections=12)
    verts = np.asarray(cyl.vertices)
    gt = np.stack([_rigid(Rotation.random(random_state=s).as_matrix(), [0.0, 0.05, 0.6]) for s in range(3)])
    t = np.array([0.003, -0.004, 0.012])
    shifted = gt.copy()
    shifted[:, :3, 3] += t
    for name in ("oce", "mce", "box_corner_error", "add"):
        fn = getattr(M, name)
        args = (shifted[:, :3, 3], gt[:, :3, 3]) if name == "oce" else (shifted, gt, verts)
        assert np.allclose(fn(*args), np.linalg.norm(t)), name
    # Rotating by the cylinder's symmetry angle (30 degrees about its axis, z) maps vertices onto
    # vertices: ADD-S vanishes while ADD does not.
    sym = np.stack([p @ _rigid(Rotation.from_euler("z", 30, degrees=True).as_matrix(), 0) for p in gt])
    assert np.allclose(M.add_s(sym, gt, verts), 0, atol=1e-9)
    assert np.all(M.add(sym, gt, verts) > 0.01)
    assert np.allclose(M.add_s(gt, gt, [verts] * 3), 0)


def test_mce_is_camera_axis_aligned_box():
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    verts = np.asarray(box.vertices)
    gt = _rigid(np.eye(3), [0, 0, 0.5])[None]
    # A 90-degree turn about z maps the cube's camera-aligned box onto itself: upstream MCE sees
    # nothing, the true corner error sees the corners moved.
    turned = _rigid(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0, 0, 0.5])[None]
    assert np.allclose(M.mce(turned, gt, verts), 0, atol=1e-12)
    # Corner (a, b, c) -> (-b, a, c): |(a + b, b - a, 0)| = sqrt(2 (a^2 + b^2)) = 0.1 for a, b = +-0.05.
    assert M.box_corner_error(turned, gt, verts)[0] == pytest.approx(0.1)


def test_bundles_and_units(joints):
    out = M.joint_metrics(joints + 0.002, joints)
    assert set(out) == {"mje", "rr_mje", "pa_mje", "pa_mje_no_reflection", "st_mje", "auc", "rr_auc", "pa_auc"}
    assert np.allclose(out["mje"], 0.002 * np.sqrt(3))
    mesh = M.mesh_metrics(joints, joints)
    assert {"f5", "f15", "pa_f5", "pa_f15", "vauc", "pa_vauc"} <= set(mesh)
    rep = M.report_units({"mje": 0.0123, "pa_f5": 0.7, "vauc": 0.8, "add_s": 0.001})
    assert rep == pytest.approx({"mje": 12.3, "pa_f5": 0.7, "vauc": 0.8, "add_s": 1.0})


def test_per_group_mean_and_summarize():
    values = np.array([1.0, 2.0, 3.0, np.nan, 5.0])
    groups = np.array(["mug", "box", "mug", "box", "can"])
    assert M.per_group_mean(values, groups) == {"box": 2.0, "can": 5.0, "mug": 2.0}
    assert np.isnan(M.per_group_mean([np.nan], ["x"])["x"])
    assert M.per_group_mean([1.0, 3.0], [7, 7]) == {7: 2.0}
    summary = M.summarize({"mje": values * 1e-3, "f5": np.array([1, 0, 1, 0, 1.0])}, groups)
    assert summary["all"] == pytest.approx({"mje": 2.75, "f5": 0.6})
    assert summary["mug"] == pytest.approx({"mje": 2.0, "f5": 1.0})
    assert summary["box"]["f5"] == 0.0
    with pytest.raises(ValueError):
        M.summarize({"a": np.zeros(2), "b": np.zeros(3)})
    with pytest.raises(ValueError):
        M.per_group_mean([1.0], ["a", "b"])


# ---------------------------------------------------------------- physical plausibility (hoisdf.scoring.plausibility)

def _box(extents, centre):
    mesh = trimesh.creation.box(extents=extents)
    return np.asarray(mesh.vertices) + np.asarray(centre), np.asarray(mesh.faces)


def _sphere(radius, centre):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return np.asarray(mesh.vertices) + np.asarray(centre), np.asarray(mesh.faces)


def test_penetration_depth_of_sphere_pushed_into_box():
    from hoisdf.scoring.plausibility import contact, penetration_depth

    box_v, box_f = _box((0.1, 0.1, 0.1), (0, 0, 0))  # top face at z = 0.05
    # The sphere's lowest vertex (a pole of the icosphere) sits 7 mm below the top face.
    sph_v, _ = _sphere(0.02, (0, 0, 0.05 + 0.02 - 0.007))
    assert penetration_depth(sph_v, box_v, box_f) == pytest.approx(0.007, abs=1e-9)
    assert contact(sph_v, box_v, box_f)


def test_intersection_volume_of_overlapping_boxes():
    from hoisdf.scoring.plausibility import intersection_bounds, intersection_volume

    a_v, a_f = _box((0.1, 0.1, 0.1), (0, 0, 0))
    b_v, b_f = _box((0.1, 0.08, 0.06), (0.0637, 0.013, -0.021))  # b: x 13.7..113.7, y -27..53, z -51..9 mm
    exact = 0.0363 * 0.077 * 0.059  # the overlap: x 13.7..50, y -27..50, z -50..9 mm
    # An overlap this large (surface 274 cm^2) meets 5 % of its volume cheaply; an absolute 0.1 cm^3 would need
    # ~1e9 cells (the work grows as area^3 / tolerance^2).
    est = intersection_bounds(a_v, a_f, b_v, b_f, tolerance=1e-7, rel_tolerance=0.05)
    assert est.lower <= exact <= est.upper and est.error_bound <= 0.05 * exact
    assert abs(est.volume - exact) <= est.error_bound
    # coincident surfaces: every cell along them stays undecided, the relative bound still ends it
    same = intersection_volume(a_v, a_f, a_v, a_f, tolerance=1e-7, rel_tolerance=0.05)
    assert same == pytest.approx(1e-3, rel=0.05)


@pytest.mark.slow
def test_separated_and_touching_meshes():
    from hoisdf.scoring.plausibility import (
        contact,
        intersection_volume,
        penetration_depth,
        plausibility_report,
    )

    box_v, box_f = _box((0.1, 0.1, 0.1), (0, 0, 0))
    far_v, far_f = _sphere(0.02, (0, 0, 0.05 + 0.02 + 0.02))  # 2 cm gap
    assert penetration_depth(far_v, box_v, box_f) == 0.0
    assert intersection_volume(far_v, far_f, box_v, box_f) == 0.0
    assert not contact(far_v, box_v, box_f)
    near_v, near_f = _sphere(0.02, (0, 0, 0.05 + 0.02 + 0.003))  # 3 mm gap
    assert contact(near_v, box_v, box_f, threshold=0.005)
    assert intersection_volume(near_v, near_f, box_v, box_f) == 0.0
    assert not contact(near_v, box_v, box_f, threshold=0.002)
    assert penetration_depth(near_v, box_v, box_f) == 0.0
    deep_v, deep_f = _sphere(0.02, (0, 0, 0.05 + 0.02 - 0.01))
    rep = plausibility_report([(far_v, far_f, box_v, box_f), (deep_v, deep_f, box_v, box_f)], rel_tolerance=0.05)
    assert rep["num_samples"] == 2 and rep["contact_ratio"] == 0.5
    assert rep["penetration_depth_mm"] == pytest.approx(5.0, abs=1e-6)
    # Spherical cap of height 10 mm on a 20 mm sphere: pi h^2 (3 r - h) / 3 = 5.236 cm^3, mean over 2.
    # (the icosphere is 3 % short of the analytic cap, the tolerance 5 %)
    assert rep["intersection_volume_cm3"] == pytest.approx(np.pi * 1.0 * (6.0 - 1.0) / 3 / 2, rel=0.06)
    assert np.isnan(plausibility_report([])["contact_ratio"])


def test_intersection_volume_converges_to_exact_boolean():
    from hoisdf.scoring.plausibility import intersection_bounds

    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    ball.apply_translation([0, 0, 0.06])  # 10 mm cap
    exact = box.intersection(ball).volume  # manifold3d boolean
    for tolerance in (1e-6, 4e-7):
        est = intersection_bounds(ball.vertices, ball.faces, box.vertices, box.faces, tolerance=tolerance)
        assert est.lower <= exact <= est.upper and est.error_bound <= tolerance
        assert abs(est.volume - exact) <= tolerance
