"""Evaluator result files: HO-3D pred.json / pred.zip and DexYCB HPE text files round-trip exactly."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from hoidata.errors import DataError
from hoisdf.scoring import submissions as E


@pytest.fixture
def preds():
    """Three samples whose joints and vertices all have distinct coordinates, at positive OpenCV depth."""
    rng = np.random.default_rng(0)
    joints = np.arange(3 * 21 * 3, dtype=np.float64).reshape(3, 21, 3) * 1e-3 + np.array([0.0, 0.0, 0.5])
    verts = rng.normal(scale=0.05, size=(3, 778, 3)) + np.array([0.0, 0.0, 0.5])
    return ["SM1/0002", "SM1/0000", "MPM10/0001"], joints, verts


def test_ho3d_roundtrip_in_evaluation_order(tmp_path, preds):
    ids, joints, verts = preds
    order = ["SM1/0000", "SM1/0002", "MPM10/0001"]
    path = E.write_ho3d_pred(tmp_path / "pred.json", ids, joints, verts, order=order)
    back_j, back_v = E.read_ho3d_pred(path)
    rows = [ids.index(f) for f in order]
    np.testing.assert_array_equal(back_j, joints[rows])  # JSON floats round-trip exactly
    np.testing.assert_array_equal(back_v, verts[rows])


def test_ho3d_file_layout_is_opengl_mano_order(tmp_path, preds):
    ids, joints, verts = preds
    path = E.write_ho3d_pred(tmp_path / "pred.json", ids, joints, verts)
    xyz, vlist = json.loads(path.read_text())
    xyz, vlist = np.array(xyz), np.array(vlist)
    assert xyz.shape == (3, 21, 3) and vlist.shape == (3, 778, 3)
    flip = np.array([1.0, -1.0, -1.0])
    assert np.all(xyz[..., 2] < 0)  # the scene is at negative z in OpenGL
    np.testing.assert_array_equal(vlist, verts * flip)
    # HO-3D order: MANO joints (wrist, index x3, middle x3, pinky x3, ring x3, thumb x3), then the tips.
    dex = {"wrist": 0, "index_mcp": 5, "middle_mcp": 9, "little_mcp": 17, "ring_mcp": 13, "thumb_mcp": 1,
           "thumb_tip": 4, "index_tip": 8, "middle_tip": 12, "ring_tip": 16, "little_tip": 20}
    ho3d = {"wrist": 0, "index_mcp": 1, "middle_mcp": 4, "little_mcp": 7, "ring_mcp": 10, "thumb_mcp": 13,
            "thumb_tip": 16, "index_tip": 17, "middle_tip": 18, "ring_tip": 19, "little_tip": 20}
    for name, k in dex.items():
        np.testing.assert_array_equal(xyz[:, ho3d[name]], joints[:, k] * flip, err_msg=name)


def test_ho3d_tip_replacement_and_zip(tmp_path, preds):
    ids, joints, verts = preds
    path = E.write_ho3d_pred(tmp_path / "pred.zip", ids, joints, verts, tip_vertices=E.HO3D_TIP_VERTICES)
    with zipfile.ZipFile(path) as zf:
        assert zf.namelist() == ["pred.json"]
    back_j, back_v = E.read_ho3d_pred(path)
    np.testing.assert_array_equal(back_j[:, [4, 8, 12, 16, 20]], verts[:, [744, 333, 444, 555, 672]])
    np.testing.assert_array_equal(back_j[:, :4], joints[:, :4])
    np.testing.assert_array_equal(back_v, verts)


def test_ho3d_missing_frame_and_bad_input(tmp_path, preds):
    ids, joints, verts = preds
    with pytest.raises(ValueError, match="SM1/0001"):
        E.write_ho3d_pred(tmp_path / "pred.json", ids, joints, verts, order=["SM1/0000", "SM1/0001"])
    assert not (tmp_path / "pred.json").exists()
    with pytest.raises(ValueError, match="two predictions"):
        E.write_ho3d_pred(tmp_path / "pred.json", ids[:2] + ids[:1], joints, verts)
    with pytest.raises(ValueError, match="positive z"):
        E.write_ho3d_pred(tmp_path / "pred.json", ids, -joints, verts)
    with pytest.raises(ValueError, match="joints"):
        E.write_ho3d_pred(tmp_path / "pred.json", ids, joints[:, :20], verts)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([[[[0.0, 0.0, 0.0]] * 20], [[[0.0, 0.0, 0.0]] * 778]]))
    with pytest.raises(DataError, match="xyz_list"):
        E.read_ho3d_pred(bad)
    bad.write_text("[1, 2")
    with pytest.raises(DataError, match="bad.json"):
        E.read_ho3d_pred(bad)


def test_dexycb_hpe_roundtrip_and_columns(tmp_path, preds):
    _, joints, _ = preds
    ids = [7, 0, 123456]
    path = E.write_dexycb_hpe(tmp_path / "res.txt", ids, joints)
    lines = path.read_text().splitlines()
    assert len(lines) == 3 and all(len(line.split(",")) == 64 for line in lines)
    first = lines[0].split(",")
    assert first[0] == "7" and float(first[1 + 3 * 2 + 2]) == pytest.approx(joints[0, 2, 2] * 1000)  # mm
    back_ids, back_j = E.read_dexycb_hpe(path)
    np.testing.assert_array_equal(back_ids, ids)
    np.testing.assert_allclose(back_j, joints, atol=1e-9)


def test_dexycb_hpe_malformed_lines_name_the_line(tmp_path, preds):
    _, joints, _ = preds
    path = E.write_dexycb_hpe(tmp_path / "res.txt", [0, 1, 2], joints)
    good = path.read_text().splitlines()
    cases = {
        "short": good[1].rsplit(",", 1)[0],
        "text": good[1].rsplit(",", 1)[0] + ",abc",
        "duplicate": good[0],
        "index": "1.5" + good[1][1:],
    }
    for name, line in cases.items():
        path.write_text("\n".join([good[0], line, good[2]]) + "\n")
        with pytest.raises(DataError, match="line 2") as err:
            E.read_dexycb_hpe(path)
        assert "res.txt" in str(err.value), name
    with pytest.raises(ValueError, match="unique"):
        E.write_dexycb_hpe(tmp_path / "x.txt", [1, 1, 2], joints)
