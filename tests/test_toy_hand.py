"""The procedural hand: the real MANO file's layout, a hand-like rig, determinism, and bad MANO files."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import torch
import trimesh

from hoidata.errors import DataError
from hoidata.hand import load_mano, read_mano_file
from hoidata.safe_pickle import load_pickle
from hoidata.toy.hand import (
    build_toy_mano,
    mirror_to_left,
    write_mano_pickle,
    write_toy_mano,
)

REAL_LAYOUT = {  # key: (shape, dtype kind) of MANO_RIGHT.pkl v1.2 (docs/conventions.md, "The MANO file")
    "v_template": ((778, 3), "f"), "shapedirs": ((778, 3, 10), "f"), "posedirs": ((778, 3, 135), "f"),
    "J_regressor": ((16, 778), "f"), "J": ((16, 3), "f"), "weights": ((778, 16), "f"),
    "kintree_table": ((2, 16), "i"), "f": ((1538, 3), "u"), "hands_components": ((45, 45), "f"),
    "hands_mean": ((45,), "f"), "hands_coeffs": ((1554, 45), "f"),
}


@pytest.mark.parametrize("side", ["right", "left"])
def test_files_have_the_real_keys_shapes_and_dtypes(mano_dir, side):
    raw = load_pickle(mano_dir / f"MANO_{side.upper()}.pkl")
    assert set(raw) == set(REAL_LAYOUT) | {"bs_style", "bs_type"}
    for key, (shape, kind) in REAL_LAYOUT.items():
        assert raw[key].shape == shape, key
        assert raw[key].dtype.kind == kind, key
    assert scipy.sparse.issparse(raw["J_regressor"]) and raw["J_regressor"].format == "csc"
    assert raw["f"].dtype == np.uint32 and raw["kintree_table"][0, 0] == 4294967295
    assert raw["bs_style"] == "lbs" and raw["bs_type"] == "lrotmin"
    assert abs(raw["v_template"].mean(0)).max() < 1e-9  # centred like MANO's template
    np.testing.assert_allclose(raw["J"], raw["J_regressor"] @ raw["v_template"], atol=1e-12)


def test_written_files_are_deterministic(mano_dir, tmp_path):
    write_toy_mano(tmp_path)
    for name in ("MANO_RIGHT.pkl", "MANO_LEFT.pkl"):
        assert (tmp_path / name).read_bytes() == (mano_dir / name).read_bytes()


def test_mesh_is_a_disk_with_a_16_edge_wrist(mano_right):
    mesh = trimesh.Trimesh(mano_right.v_template.numpy(), mano_right.faces, process=False)
    assert mesh.euler_number == 1 and mesh.is_winding_consistent
    assert len(mano_right.wrist_loop) == 16


def test_fingertips_are_the_finger_extremities(mano_right):
    verts = mano_right.v_template.numpy()
    joints = (mano_right.j_regressor @ mano_right.v_template).numpy()
    distal = {"thumb": 15, "index": 3, "middle": 6, "ring": 12, "pinky": 9}
    for (finger, joint), tip in zip(distal.items(), (745, 317, 444, 556, 673)):
        direction = verts[tip] - joints[joint]
        finger_verts = np.flatnonzero(mano_right.vertex_parts == joint)
        assert tip == finger_verts[np.argmax((verts[finger_verts] - joints[joint]) @ direction)], finger
        assert 0.01 < np.linalg.norm(direction) < 0.04  # a distal phalanx, not a stray vertex
    for a, b in zip((745, 317, 556, 673), (744, 333, 555, 672)):  # HO-3D tips sit on the same fingertip
        assert np.linalg.norm(verts[a] - verts[b]) < 0.012


def test_joint_regressor_is_a_sparse_average_inside_the_hand(mano_right):
    reg = mano_right.j_regressor.numpy()
    np.testing.assert_allclose(reg.sum(1), 1.0, atol=1e-12)
    assert (reg >= 0).all() and ((reg > 0).sum(1) >= 50).all()
    closed = trimesh.Trimesh(mano_right.close(mano_right.v_template[None])[0].numpy(), mano_right.closed_faces)
    assert closed.contains(reg @ mano_right.v_template.numpy()).all()


def test_curling_fingers_moves_tips_toward_the_palm(mano_right):
    pose = torch.zeros(1, 48, dtype=torch.float64)
    rest = mano_right(pose)
    pose[0, 3:] = mano_right.hands_mean * 2.5  # strongly curled mean grasp
    curled = mano_right(pose)
    palm_normal = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    tips = [4, 8, 12, 16, 20]
    down = ((curled.joints[0, tips] - rest.joints[0, tips]) @ palm_normal)
    assert (down > 0.01).all()


def _write_variant(tmp_path, side="right", **changes):
    arrays = build_toy_mano()
    arrays = mirror_to_left(arrays) if side == "left" else arrays
    for key, value in changes.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    path = tmp_path / f"MANO_{side.upper()}.pkl"
    write_mano_pickle(path, arrays)
    return path


def test_wrong_shape_names_file_and_key(tmp_path):
    path = _write_variant(tmp_path, posedirs=np.zeros((778, 3, 10)))
    with pytest.raises(DataError, match=r"MANO_RIGHT\.pkl: 'posedirs': expected shape \(778, 3, 135\)"):
        read_mano_file(path)


def test_missing_key_names_file_and_key(tmp_path):
    path = _write_variant(tmp_path, hands_components=None)
    with pytest.raises(DataError, match=r"MANO_RIGHT\.pkl: 'hands_components': missing key"):
        read_mano_file(path)


@pytest.mark.slow
def test_bad_faces_and_tree(tmp_path):
    arrays = build_toy_mano()
    bad_f = arrays["f"].copy()
    bad_f[0, 0] = 9999
    with pytest.raises(DataError, match=r"'f': face indices"):
        read_mano_file(_write_variant(tmp_path, f=bad_f))
    tree = arrays["kintree_table"].copy()
    tree[0, 5] = 3
    with pytest.raises(DataError, match=r"'kintree_table': expected MANO parents"):
        read_mano_file(_write_variant(tmp_path, kintree_table=tree))


def test_truncated_and_missing_model_files(tmp_path, mano_dir):
    data = (mano_dir / "MANO_RIGHT.pkl").read_bytes()
    (tmp_path / "MANO_RIGHT.pkl").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=r"MANO_RIGHT\.pkl.*truncated or corrupt"):
        load_mano(tmp_path)
    with pytest.raises(DataError, match=r"MANO_LEFT\.pkl.*not found"):
        load_mano(tmp_path, side="left")
    with pytest.raises(ValueError, match="side must be"):
        load_mano(mano_dir, side="both")


@pytest.mark.slow
def test_inward_wound_file_is_turned_outward(tmp_path):
    """Some MANO_LEFT copies keep the right hand's winding; the layer must still face outward."""
    arrays = build_toy_mano()
    path = _write_variant(tmp_path, side="left", f=arrays["f"])
    model = load_mano(path, side="left", dtype=torch.float64)
    closed = trimesh.Trimesh(model.close(model.v_template[None])[0].numpy(), model.closed_faces, process=False)
    assert closed.is_watertight and closed.volume > 0


def test_pca_basis_moves_by_round_off_when_the_grasps_do(mano_dir):
    """The toy's PCA basis is a well-posed function of its grasps, so every CPU's kernels give it to ~1e-15: the 11
    directions the grasps span come from the SVD (with a sign rule), the 34 others are built without a
    decomposition. An SVD's own basis of those 34 is arbitrary: OpenBLAS's Haswell and SkylakeX kernels gave rows up
    to 1.6 apart, and here a 1e-13 nudge of the grasps turns them about as far."""
    from hoidata.toy.hand import pca_basis

    raw = load_pickle(mano_dir / "MANO_RIGHT.pkl")
    comps, coeffs = raw["hands_components"], raw["hands_coeffs"]
    grasps = coeffs @ comps + raw["hands_mean"]  # the 1554 synthetic grasps the file was made from
    np.testing.assert_allclose(comps @ comps.T, np.eye(45), rtol=0, atol=1e-12)
    assert np.abs(coeffs[:, 11:]).max() < 1e-12 < np.abs(coeffs[:, :11]).min(0).max()  # 11 spanned directions
    again, _, _ = pca_basis(grasps)
    nudged, _, _ = pca_basis(grasps + np.random.default_rng(0).normal(scale=1e-13, size=grasps.shape))
    assert np.abs(again - comps).max() < 1e-9 and np.abs(nudged - comps).max() < 1e-9
