"""record.sdf_points = "deepsdf": the authors' AlignSDF/DeepSDF sample blocks (hoidata.geometry.sampling_deepsdf).

The slow test compares 10^5 rows per entity with an independent implementation of AlignSDF's PreprocessMesh run
outside the project (tests/golden/sdf_deepsdf/README.md); fixed seeds, so it cannot flake.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from hoidata.geometry.sampling import SdfSampling, compute_sdf_samples
from hoidata.geometry.sampling_deepsdf import (
    BUFFER,
    FILTER,
    block_sizes,
    deepsdf_record,
    entity_points,
    joint_normalisation,
)
from hoidata.objects import load_object_mesh, repair_mesh
from hoidata.schema import SDF_QUANTUM, dequantize_sdf
from hoidata.toy.objects import write_toy_objects

GOLDEN = Path(__file__).parent / "golden" / "sdf_deepsdf" / "reference.json"
CAMERA_T = np.array([0.03, -0.02, 0.55])


def scene(mano, object_dir: Path, object_shift=(0.0, 0.0, 0.05)):
    """The README's scene: the toy hand curled (1.2 x the grasp mean, rotation seed 2) at CAMERA_T, the repaired toy
    banana (rotation seed 5) 5 cm behind it. Returns (hv, hf, parts, ov, of, watertight, root)."""
    pose = torch.zeros(1, 48, dtype=torch.float64)
    pose[0, :3] = torch.as_tensor(Rotation.random(random_state=2).as_rotvec())
    pose[0, 3:] = mano.hands_mean * 1.2
    out = mano(pose, transl=torch.as_tensor(CAMERA_T)[None])
    hv, root = mano.close(out.vertices)[0].numpy(), out.joints[0, 0].numpy()
    mesh, report = repair_mesh(load_object_mesh(write_toy_objects(object_dir, ["011_banana"])[0]))
    rot = Rotation.random(random_state=5).as_matrix()
    ov = np.asarray(mesh.vertices) @ rot.T + CAMERA_T + np.asarray(object_shift)
    return (hv, np.asarray(mano.closed_faces), np.asarray(mano.closed_face_parts), ov, np.asarray(mesh.faces),
            report.watertight, root)


@pytest.fixture(scope="module")
def banana_scene(mano_right, tmp_path_factory):
    return scene(mano_right, tmp_path_factory.mktemp("deepsdf_objects"))


def test_block_sizes_are_preprocessmesh_counts():
    assert block_sizes(20000) == (9400, 1200)  # AlignSDF's files: 18,800 near rows + 1,200 uniform
    assert block_sizes(50) == (23, 3)  # 47 near rows halve to 23 surface points: 49 rows, as the C++ gives
    with pytest.raises(ValueError):
        block_sizes(0)


def test_joint_normalisation_keeps_preprocessmesh_z_expression():
    hand = np.array([[0.0, 0.0, 0.60], [0.1, 0.05, 0.70]])  # the hand reaches further back than the object
    obj = np.array([[0.05, -0.1, 0.55], [0.08, 0.02, 0.65]])
    centre, radius = joint_normalisation(hand, obj)
    # far z = max(hand y max 0.05, object z max 0.65) = 0.65, not the box's 0.70
    assert np.allclose(centre, [0.05, -0.025, (0.55 + 0.65) / 2])
    farthest = np.linalg.norm(np.concatenate([hand, obj]) - centre, axis=1).max()
    assert radius == pytest.approx(BUFFER * farthest)


def test_blocks_filter_and_counts(banana_scene):
    hv, hf, parts, ov, of, watertight, root = banana_scene
    sampling = SdfSampling(n_hand=650, n_object=400)
    stored, counts = deepsdf_record(hv, hf, parts, ov, of, watertight, root, np.random.default_rng(3), sampling)
    centre, radius = joint_normalisation(hv, ov)
    rng = np.random.default_rng(3)  # the same draws, unfiltered
    blocks = [entity_points(hv, hf, 650, centre, radius, rng), entity_points(ov, of, 400, centre, radius, rng)]
    sizes = [len(b) for b in blocks]
    assert sizes == [649, 400]  # 650 * 47 // 50 = 611 near -> 305 surface points x 2 + 39 uniform
    sdf_h, sdf_o, _ = compute_sdf_samples(np.concatenate(blocks), hv, hf, parts, ov, of, watertight)
    keep = (np.abs(sdf_h) < FILTER * radius) & (np.abs(sdf_o) < FILTER * radius)
    assert counts.tolist() == [int(keep[:649].sum()), int(keep[649:].sum()), 0] and stored.shape[0] == counts.sum()
    xyz, q_h, q_o, _ = dequantize_sdf(stored)
    tol = 0.5 * SDF_QUANTUM + 1e-7
    assert np.abs(xyz - (np.concatenate(blocks)[keep] - root)).max() <= tol
    assert np.abs(q_h - sdf_h[keep]).max() <= tol and np.abs(q_o - sdf_o[keep]).max() <= tol
    uniform = blocks[0][-39:]  # the hand block's uniform rows lie in the cube centre +- R
    assert np.abs(uniform - centre).max() <= radius and np.abs(uniform - centre).max(0).min() > 0.8 * radius


def test_far_object_rows_are_filtered_as_pre_process_sdf_does(mano_right, tmp_path):
    hv, hf, parts, ov, of, watertight, root = scene(mano_right, tmp_path, object_shift=(0.3, 0.3, 0.3))
    stored, counts = deepsdf_record(hv, hf, parts, ov, of, watertight, root, np.random.default_rng(1),
                                    SdfSampling(n_hand=2000, n_object=2000))
    _, radius = joint_normalisation(hv, ov)
    assert counts[0] < 2000 and counts[1] < 2000  # a far object: cube corners opposite a mesh lie more than 2 R from it
    _, q_h, q_o, _ = dequantize_sdf(stored)
    assert np.abs(q_h).max() < FILTER * radius + SDF_QUANTUM and np.abs(q_o).max() < FILTER * radius + SDF_QUANTUM


def test_loader_pools_are_the_two_blocks(banana_scene):
    from hoisdf.data.loader import sample_sdf

    hv, hf, parts, ov, of, watertight, root = banana_scene
    stored, counts = deepsdf_record(hv, hf, parts, ov, of, watertight, root, np.random.default_rng(2),
                                    SdfSampling(n_hand=300, n_object=200))
    got = sample_sdf(stored, counts, np.random.default_rng(0), 250, 150, 0.05)
    assert got["hand_rows"].max() < counts[0] and got["obj_rows"].min() >= counts[0]
    assert len(set(got["hand_rows"].tolist())) == 250  # without replacement, as upstream's __getitem__


def _ecdf_distance(sample: np.ndarray, quantiles: list[float]) -> float:
    """max over the golden's levels p_i of |F_sample(q_i) - p_i|: the KS distance at the reference's quantiles."""
    levels = np.linspace(0, 1, len(quantiles))
    inner = slice(1, -1)  # the 0 and 1 levels are the reference's extremes
    below = np.searchsorted(np.sort(sample), np.asarray(quantiles)[inner], side="right") / len(sample)
    return float(np.abs(below - levels[inner]).max())


@pytest.mark.slow
def test_distribution_matches_an_independent_alignsdf_implementation(banana_scene):
    golden = json.loads(GOLDEN.read_text())
    hv, hf, parts, ov, of, watertight, root = banana_scene
    centre, radius = joint_normalisation(hv, ov)
    assert np.allclose(centre, golden["centre"], atol=1e-7) and radius == pytest.approx(golden["R"], abs=1e-7)
    n = 100_000
    stored, counts = deepsdf_record(hv, hf, parts, ov, of, watertight, root, np.random.default_rng(0),
                                    SdfSampling(n_hand=n, n_object=n))
    _, sdf_h, sdf_o, _ = dequantize_sdf(stored)
    blocks = {"hand": (sdf_h[:counts[0]], sdf_o[:counts[0]]), "obj": (sdf_o[counts[0]:], sdf_h[counts[0]:])}
    for name, (own, other) in blocks.items():
        own, other = own.astype(np.float64) / radius, other.astype(np.float64) / radius
        columns = {"own": own, "abs_own": np.abs(own), "other": other}
        # the same procedure with exact distances: two samples of one distribution (alpha = 0.001 at 10^5 rows)
        exact = golden[f"exact_{name}"]
        for column, values in columns.items():
            assert _ecdf_distance(values, exact[column]) < 0.0087, (name, column)
        assert abs((own < 0).mean() - exact["inside"]) < 0.005
        assert (counts[0 if name == "hand" else 1] == n) and exact["uniform_share"] == pytest.approx(0.06, abs=1e-9)
        # AlignSDF's own distances (point cloud of 100 renders, 11-vote sign, ambiguous points dropped): how close
        alignsdf = golden[f"alignsdf_{name}"]
        for column, values in columns.items():
            assert _ecdf_distance(values, alignsdf[column]) < 0.015, (name, column)
