"""``hoisdf score contact`` (hoisdf.scoring.score_contact) end to end on a toy HO-3D v2 evaluation split: a pred.json
written by hand in the challenge layout (the JSON list [xyz_list, verts_list], OpenGL, metres, evaluation.txt order;
shreyashampali/ho3d eval.py reads it so) and an .npz of the same hands; object poses from the store's index, checked
against the dataset's own annotations; bad files give one line naming file, entry and field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hoisdf.scoring.cli import main

pytestmark = pytest.mark.slow  # scores a toy HO-3D evaluation store end to end

@pytest.fixture(scope="module")
def split(ho3d_small, ho3d_small_eval_store):
    """(toy HO-3D root, its evaluation store): the session's small HO-3D (conftest)."""
    return ho3d_small, ho3d_small_eval_store


def _truth(root):
    """The split's hidden ground truth in the challenge layout: joints (N, 21, 3), vertices (N, 778, 3), OpenGL."""
    return (np.array(json.loads((root / "evaluation_xyz.json").read_text())),
            np.array(json.loads((root / "evaluation_verts.json").read_text())))


def _write_pred(path, xyz, verts):
    path.write_text(json.dumps([np.asarray(xyz).tolist(), np.asarray(verts).tolist()]))
    return path


def _score(capsys, *argv) -> tuple[int, str, str]:
    code = main(["contact", *[str(a) for a in argv]])
    out, err = capsys.readouterr()
    return code, out, err


def test_scores_hand_written_pred_json_and_npz_alike(split, tmp_path, capsys):
    from hoidata.datasets.ho3d import HO3DReader
    from hoidata.hand import load_mano
    from hoidata.store import read_index
    from hoisdf.scoring.plausibility import frame_metrics

    root, store = split
    xyz, verts = _truth(root)
    pred = _write_pred(tmp_path / "pred.json", xyz, verts)
    out = tmp_path / "contact.json"
    code, text, _ = _score(capsys, "--pred", pred, "--store", store, "--mano", root / "mano", "--order",
                           root / "evaluation.txt", "--out", out)
    assert code == 0 and "penetration depth (mm)" in text and "IVU (cm)" in text
    result = json.loads(out.read_text())
    order = (root / "evaluation.txt").read_text().split()
    assert [f["id"] for f in result["frames"]] == [o.replace("/", "_") for o in order] and not result["subset"]

    # the same frames from the dataset's own annotations (the reader's object pose, the model file)
    mano = load_mano(root / "mano", side="right")
    index = read_index(store)
    frames = {f.frame_id: f for f in HO3DReader(root, root / "mano", "evaluation").frames()}
    cv = verts * np.array([1.0, -1.0, -1.0])
    closed = mano.close(__import__("torch").as_tensor(cv)).numpy().astype(np.float64)
    for k, got in enumerate(result["frames"]):
        frame = frames[got["id"]]
        v, f = index.objects[frame.object_name]
        obj = np.asarray(v, np.float64) @ frame.object_pose[:3, :3].T + frame.object_pose[:3, 3]
        want = frame_metrics(closed[k], np.asarray(mano.closed_faces), obj, f, 1e-7, 0.005, 778, 0.05)
        for key in ("penetration_depth_mm", "contact", "contact_area_cm2", "intersection_volume_cm3"):
            assert got[key] == pytest.approx(want[key], abs=1e-9), key
    assert result["mean"]["num_samples"] == 3  # ho3d_small: one evaluation sequence of 3 frames

    # the .npz form: OpenCV vertices and record keys give the same numbers (here in 2 worker processes)
    labels = index.labels
    keys = [str(labels["key"][list(labels["frame_id"]).index(f["id"])]) for f in result["frames"]]
    np.savez(tmp_path / "hands.npz", verts=cv, keys=np.array(keys))
    code, _, _ = _score(capsys, "--pred", tmp_path / "hands.npz", "--store", store, "--mano", root / "mano",
                        "--out", tmp_path / "npz.json", "--limit", "2", "--workers", "2")
    npz = json.loads((tmp_path / "npz.json").read_text())
    assert code == 0 and npz["subset"] and len(npz["frames"]) == 2
    for a, b, key in zip(npz["frames"], result["frames"], keys):
        assert a == {**b, "id": key}


def test_hands_pushed_into_the_object_score_worse(split, tmp_path, capsys):
    from hoidata.store import read_index

    root, store = split
    xyz, verts = _truth(root)
    index = read_index(store)
    order = [o.replace("/", "_") for o in (root / "evaluation.txt").read_text().split()]
    rows = [list(index.labels["frame_id"]).index(o) for o in order]
    centre = np.array([index.labels["object_pose"][r][:3, 3] for r in rows]) * [1.0, -1.0, -1.0]  # OpenGL
    moved = verts + 0.6 * (centre[:, None, :] - verts.mean(1, keepdims=True))  # hand centroid 60 % of the way in
    results = []
    for name, v in (("truth", verts), ("moved", moved)):
        _write_pred(tmp_path / f"{name}.json", xyz, v)
        code, _, err = _score(capsys, "--pred", tmp_path / f"{name}.json", "--store", store, "--mano", root / "mano",
                              "--order", root / "evaluation.txt", "--out", tmp_path / f"{name}_out.json")
        assert code == 0, err
        results.append(json.loads((tmp_path / f"{name}_out.json").read_text())["mean"])
    truth, moved_mean = results
    assert moved_mean["penetration_depth_mm"] > truth["penetration_depth_mm"] + 1.0
    assert moved_mean["intersection_volume_cm3"] > truth["intersection_volume_cm3"]
    assert moved_mean["contact_ratio"] == 1.0


def test_bad_files_get_one_line(split, tmp_path, capsys):
    root, store = split
    xyz, verts = _truth(root)
    base = ["--store", store, "--mano", root / "mano"]
    nan = verts.copy()
    nan[1, 5, 0] = np.nan
    cases = [
        (["--pred", _write_pred(tmp_path / "nan.json", xyz, nan).as_posix(), "--order", root / "evaluation.txt"],
         ["nan.json", "verts_list[1]", "point 5"]),
        (["--pred", _write_pred(tmp_path / "short.json", xyz[:2], verts[:2]), "--order", root / "evaluation.txt"],
         ["short.json", "verts_list", "2 entries"]),
        (["--pred", _write_pred(tmp_path / "few.json", xyz, verts[:, :700]), "--order", root / "evaluation.txt"],
         ["few.json", "verts_list", "778"]),
        (["--pred", tmp_path / "few.json"], ["few.json", "--order"]),
    ]
    far = verts.copy()
    far[1] *= 1e30  # coordinates no float64 bound holds (issue 44, part 5): refused before any bound is printed
    cases.append((["--pred", _write_pred(tmp_path / "far.json", xyz, far), "--order", root / "evaluation.txt"],
                  ["far.json", "verts_list", "entry 1", "beyond the 100 m"]))
    np.savez(tmp_path / "nokeys.npz", verts=verts)
    cases.append((["--pred", tmp_path / "nokeys.npz"], ["nokeys.npz", "'keys'", "missing"]))
    np.savez(tmp_path / "unknown.npz", verts=verts[:1], keys=np.array(["ho3d-evaluation-XX_0000"]))
    cases.append((["--pred", tmp_path / "unknown.npz"], ["unknown.npz", "entry 0", "XX_0000"]))
    dup = root / "dup.txt"
    first = (root / "evaluation.txt").read_text().split()[0]
    dup.write_text("\n".join([first] * 3))
    good = _write_pred(tmp_path / "good.json", xyz[:3], verts[:3])
    cases.append((["--pred", good, "--order", dup], ["dup.txt", "line 2", "twice"]))
    for argv, words in cases:
        code, out, err = _score(capsys, *argv, *base)
        assert code == 2 and len(err.strip().splitlines()) == 1, (argv, err)
        for word in words:
            assert word in err, (word, err)


def test_older_contact_definitions_beside_the_exact_ones(split, tmp_path, capsys):
    """--contact-definition gsdf / grasptta: each frame also gets that script's numbers (hoisdf.scoring.
    contact_legacy, checked against the scripts themselves in tests/test_contact_definitions.py), the means are
    printed beside the exact ones, and the exact numbers are unchanged."""
    from hoidata.hand import load_mano
    from hoisdf.scoring.contact_legacy import gsdf_frame

    root, store = split
    xyz, verts = _truth(root)
    pred = _write_pred(tmp_path / "pred.json", xyz, verts)
    base = ["--pred", pred, "--store", store, "--mano", root / "mano", "--order", root / "evaluation.txt"]
    code, _, _ = _score(capsys, *base, "--out", tmp_path / "exact.json")
    exact = json.loads((tmp_path / "exact.json").read_text())
    for definition in ("gsdf", "grasptta"):
        out = tmp_path / f"{definition}.json"
        code, text, err = _score(capsys, *base, "--contact-definition", definition, "--out", out)
        assert code == 0, err
        assert f"{definition} definition" in text and "rigorous bound" in text
        result = json.loads(out.read_text())
        assert result["legacy"]["definition"] == definition and result["mean"] == exact["mean"]
        frames = result["frames"]
        contact = [f[f"{definition}_contact"] for f in frames]
        assert result["legacy"]["mean"]["contact_ratio"] == pytest.approx(np.mean(contact))
    # gSDF's numbers per frame, recomputed from the closed hands and the store's posed objects
    from hoidata.store import read_index
    from hoisdf.scoring.score_contact import match_records, posed_objects

    mano = load_mano(root / "mano", side="right")
    cv = verts * np.array([1.0, -1.0, -1.0])
    closed = mano.close(__import__("torch").as_tensor(cv)).numpy().astype(np.float64)
    index = read_index(store)
    ids = [f["id"] for f in json.loads((tmp_path / "gsdf.json").read_text())["frames"]]
    objects = posed_objects(index, match_records(index, ids, "frame_id", pred))
    for k, frame in enumerate(json.loads((tmp_path / "gsdf.json").read_text())["frames"]):
        want = gsdf_frame(closed[k], np.asarray(mano.closed_faces), *objects[k])
        assert frame["gsdf_intersection_volume_cm3"] == pytest.approx(want["intersection_volume_cm3"], abs=1e-12)
        assert frame["gsdf_contact"] == want["contact"]
