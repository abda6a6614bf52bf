"""HO-3D v2's evaluation split end to end: 'eval' records, the challenge's pred.json / pred.zip, and its scores.

``challenge_eval`` restates the server's script (shreyashampali/ho3d eval.py ``main`` with FreiHAND's EvalUtil): the
ground-truth lists and the prediction are read and checked as it reads them, and the 14 scores.txt values computed as
it computes them (plain SVD Procrustes, align_sc_tr on HO-3D joints 0 and 4, a separate vertex Procrustes for the
mesh, brute-force F-scores with strict '<'). Our own scorer (hoisdf.scoring.official) must give its numbers.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from hoidata.errors import DataError

pytestmark = pytest.mark.slow  # builds and evaluates a toy HO-3D store

SIZE = {"train_sequences": 1, "eval_sequences": 1, "frames": 4}


@pytest.fixture(scope="module")
def ho3d_root(tmp_path_factory):
    from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d
    from hoidata.toy.make import write_assets

    root = tmp_path_factory.mktemp("ho3d")
    mano_dir, models_dir = write_assets(root)
    write_toy_ho3d(root, mano_dir, models_dir, ToyHO3DSize(**SIZE), progress=False)
    return root


@pytest.fixture(scope="module")
def eval_store(ho3d_root, tmp_path_factory):
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    out = tmp_path_factory.mktemp("ho3d_eval") / "store"
    summary = build_store(load_build_config("ho3d_eval", ["record.crop_size=64"]), ho3d_root, ho3d_root / "mano",
                          ho3d_root / "models", out, progress=False)
    assert summary.written == SIZE["frames"] and summary.finished
    return out


# ---------------------------------------------------------------- the store

def test_eval_records_hold_only_what_the_split_gives(eval_store, ho3d_root):
    from hoidata import schema, store
    from hoidata.geometry.crop import project
    from hoidata.datasets.ho3d import HO3DReader

    assert store.verify_store(eval_store).ok
    members = [set(m) - {"__key__"} for m in store.read_shard_members(eval_store / "shard-000000.tar")]
    assert members == [{schema.IMG, schema.META}] * SIZE["frames"]
    frames = {f.frame_id: f for f in HO3DReader(ho3d_root, ho3d_root / "mano", "evaluation").frames()}
    for rec in store.iter_records(eval_store):
        meta, frame = rec[schema.META], frames[rec[schema.META]["frame_id"]]
        assert meta["kind"] == schema.EVAL and not set(schema.EVAL_ABSENT) & set(meta)
        np.testing.assert_allclose(meta["hand_root"], frame.root_3d)  # the given root joint, OpenCV frame
        # the given hand box, moved into the crop: the root joint projects inside it, and it lies in the crop
        u, v = project(meta["hand_root"], meta["K"])
        x1, y1, x2, y2 = meta["hand_box"]
        assert x1 <= u <= x2 and y1 <= v <= y2 and 0 < x1 < x2 < 64 and 0 < y1 < y2 < 64
        np.testing.assert_allclose(meta["object_pose"], frame.object_pose)
    labels = store.read_index(eval_store).labels
    assert set(labels["kind"].tolist()) == {"eval"} and np.isnan(labels["joints_3d"]).all()
    assert (labels["sdf_counts"] == 0).all() and np.isfinite(labels["object_pose"]).all()


def test_training_refuses_eval_records_naming_the_store_and_label(eval_store):
    from hoisdf.data import StoreSpec, build_dataset

    with pytest.raises(DataError, match=f"{eval_store}.*'kind'.*eval.*joints_3d"):
        build_dataset([StoreSpec(eval_store)], 2, training=True)
    batch = next(iter(build_dataset([StoreSpec(eval_store)], 2, n_hand=1, n_object=1, training=False)))
    assert torch.isnan(batch["joints_3d"]).all() and torch.isfinite(batch["hand_root"]).all()


def test_inspect_draws_eval_records(eval_store, tmp_path):
    import cv2

    from hoidata.store.inspect import inspect_store

    img = cv2.imread(str(inspect_store(eval_store, n=4, out=tmp_path / "grid.png")))
    assert img is not None and img.std() > 5


# ---------------------------------------------------------------- the challenge's files, as eval.py reads them

def _search_pred_file(pred_path, pred_file_name="pred.json"):
    """eval.py's _search_pred_file: the named file, else the one .json in the folder, else give up."""
    pred_file = os.path.join(pred_path, pred_file_name)
    if os.path.exists(pred_file):
        return pred_file
    files = [os.path.join(pred_path, x) for x in os.listdir(pred_path) if x.endswith(".json")]
    if len(files) != 1:
        raise Exception("Giving up, because its not clear which file to evaluate.")
    return files[0]


def challenge_eval(gt_path, pred_path) -> dict:
    """The challenge server's scores.txt values for the files in gt_path (ref/) and pred_path (res/), restated."""
    from scipy.linalg import orthogonal_procrustes

    xyz_list = json.loads(Path(os.path.join(gt_path, "evaluation_xyz.json")).read_text())
    verts_list = json.loads(Path(os.path.join(gt_path, "evaluation_verts.json")).read_text())
    with open(_search_pred_file(pred_path)) as fi:
        pred = json.load(fi)
    assert len(pred) == 2, "Expected format mismatch."
    assert len(pred[0]) == len(xyz_list), "Expected format mismatch."
    assert len(pred[1]) == len(xyz_list), "Expected format mismatch."

    def align_w_scale(mtx1, mtx2):
        t1, t2 = mtx1.mean(0), mtx2.mean(0)
        a, b = mtx1 - t1, mtx2 - t2
        s1, s2 = np.linalg.norm(a) + 1e-8, np.linalg.norm(b) + 1e-8
        r, s = orthogonal_procrustes(a / s1, b / s2)
        return np.dot(b / s2, r.T) * s * s1 + t1

    def align_sc_tr(mtx1, mtx2):
        s = np.sqrt(np.sum(np.square(mtx2[4] - mtx2[0])))
        p = mtx2 / s if s > 0 else mtx2.copy()
        p = p * np.sqrt(np.sum(np.square(mtx1[4] - mtx1[0])))
        return p - p[0:1] + mtx1[0:1]

    def fscore(gt, pr, th):
        d = np.linalg.norm(gt[:, None] - pr[None], axis=-1)
        d1, d2 = d.min(1), d.min(0)  # each gt point's nearest prediction, each prediction's nearest gt point
        recall, precision = float(np.mean(d2 < th)), float(np.mean(d1 < th))
        return 2 * recall * precision / (recall + precision) if recall + precision > 0 else 0.0

    dist = {k: [] for k in ("xyz", "pa", "st", "mesh", "mesh_al")}
    f, fa = [], []
    for idx in range(len(xyz_list)):
        xyz, verts = np.array(xyz_list[idx]), np.array(verts_list[idx])
        xyz_pred, verts_pred = np.array(pred[0][idx]), np.array(pred[1][idx])
        assert verts_pred.shape == verts.shape  # shape_is_mano: the only case our files produce
        dist["xyz"].append(np.linalg.norm(xyz - xyz_pred, axis=1))
        dist["mesh"].append(np.linalg.norm(verts - verts_pred, axis=1))
        dist["st"].append(np.linalg.norm(xyz - align_sc_tr(xyz, xyz_pred), axis=1))
        dist["pa"].append(np.linalg.norm(xyz - align_w_scale(xyz, xyz_pred), axis=1))
        verts_al = align_w_scale(verts, verts_pred)
        dist["mesh_al"].append(np.linalg.norm(verts - verts_al, axis=1))
        f.append([fscore(verts, verts_pred, t) for t in (0.005, 0.015)])
        fa.append([fscore(verts, verts_al, t) for t in (0.005, 0.015)])
    thresholds = np.linspace(0.0, 0.05, 100)

    def measures(d):  # EvalUtil.get_measures: means of per-keypoint means and AUCs
        per_kp = np.stack(d).T
        pck = (per_kp[:, :, None] <= thresholds).mean(1)
        aucs = np.trapezoid(pck, thresholds, axis=1) / np.trapezoid(np.ones_like(thresholds), thresholds)
        return float(per_kp.mean(1).mean()) * 100, float(aucs.mean())

    names = {"xyz": "xyz", "pa": "xyz_procrustes_al", "st": "xyz_scale_trans_al", "mesh": "mesh", "mesh_al": "mesh_al"}
    out = {}
    for key, name in names.items():
        out[f"{name}_mean3d"], out[f"{name}_auc3d"] = measures(dist[key])
    f, fa = np.array(f).T, np.array(fa).T
    for k, t in enumerate((5, 15)):
        out[f"f_score_{t}"], out[f"f_al_score_{t}"] = float(f[k].mean()), float(fa[k].mean())
    return out


def test_toy_writes_the_challenge_ground_truth(ho3d_root):
    import pickle

    from hoisdf.scoring.submissions import HO3D_TIP_VERTICES

    order = (ho3d_root / "evaluation.txt").read_text().split()
    xyz = np.array(json.loads((ho3d_root / "evaluation_xyz.json").read_text()))
    verts = np.array(json.loads((ho3d_root / "evaluation_verts.json").read_text()))
    assert xyz.shape == (len(order), 21, 3) and verts.shape == (len(order), 778, 3)
    assert (xyz[..., 2] < 0).all() and (verts[..., 2] < 0).all()  # OpenGL: in front of the camera at negative z
    np.testing.assert_allclose(xyz[:, 16:], verts[:, list(HO3D_TIP_VERTICES)], atol=1e-9)  # HO-3D order: tips last
    for i, entry in enumerate(order):
        seq, fid = entry.split("/")
        meta = pickle.loads((ho3d_root / "evaluation" / seq / "meta" / f"{fid}.pkl").read_bytes())
        np.testing.assert_allclose(xyz[i, 0], meta["handJoints3D"], atol=1e-12)  # the root the split gives


# ---------------------------------------------------------------- submissions from evaluate, scored

def _oracle(ho3d_root, offset=(0.0, 0.0, 0.0), noise: float = 0.0):
    """A forward pass returning the challenge's ground truth (optionally offset by `offset` metres in OpenCV and
    with per-point noise seeded by the key), in the model's output format."""
    from hoisdf.scoring.submissions import from_ho3d

    order = (ho3d_root / "evaluation.txt").read_text().split()
    gt_j, gt_v = from_ho3d(np.array(json.loads((ho3d_root / "evaluation_xyz.json").read_text())),
                           np.array(json.loads((ho3d_root / "evaluation_verts.json").read_text())))

    def forward(self, batch, points="field", **_):
        rows = [order.index("/".join(k.split("-")[-1].rsplit("_", 1))) for k in batch["key"]]
        root = batch["hand_root"][:, None].double().numpy()
        out = {}
        for name, gt in (("joints", gt_j), ("verts", gt_v)):
            pts = gt[rows] + np.asarray(offset)
            for i, key in enumerate(batch["key"]):
                pts[i] += np.random.default_rng(sum(map(ord, key + name))).normal(scale=noise, size=pts[i].shape)
            out[name] = torch.as_tensor(pts - root, dtype=torch.float32)
        zeros = torch.zeros(len(rows), 4, 3)
        return {**out, "obj_rotation": batch["object_pose"][:, :3, :3], "obj_translation": batch["object_pose"][:, :3, 3],
                "hand_query": zeros, "hand_query_sdf": zeros[..., 0], "obj_query": zeros, "obj_query_sdf": zeros[..., 0]}
    return forward


def _evaluate(untrained_run, eval_store, ho3d_root, mano_dir, out, monkeypatch, **oracle):
    from hoisdf.evaluate import evaluate
    from hoisdf.model.hoisdf import HOISDF

    monkeypatch.setattr(HOISDF, "forward", _oracle(ho3d_root, **oracle))
    return evaluate(untrained_run, [eval_store], mano_dir, out, batch_size=3, plausibility=0, progress=False, workers=0,
                    ho3d_order=ho3d_root / "evaluation.txt", ho3d_gt=ho3d_root)


def test_oracle_submission_scores_zero(untrained_run, eval_store, ho3d_root, mano_dir, tmp_path, monkeypatch):
    result = _evaluate(untrained_run, eval_store, ho3d_root, mano_dir, tmp_path, monkeypatch)
    scores = json.loads((tmp_path / "metrics.json").read_text())["ho3d_challenge"]
    assert scores == pytest.approx(result["ho3d_challenge"]) and scores["samples"] == SIZE["frames"]
    for name in ("xyz_mean3d", "xyz_procrustes_al_mean3d", "xyz_scale_trans_al_mean3d", "mesh_mean3d", "mesh_al_mean3d"):
        assert abs(scores[name]) < 1e-5, name  # cm
    for name in ("xyz_auc3d", "xyz_procrustes_al_auc3d", "mesh_auc3d"):  # float32 noise > 0 misses only t = 0
        assert 1.0 - 0.5 / 99 - 1e-9 <= scores[name] <= 1.0, name
    assert scores["f_score_5"] == scores["f_al_score_15"] == 1.0
    lines = (tmp_path / "scores.txt").read_text().splitlines()
    assert [ln.split(":")[0] for ln in lines][:2] == ["xyz_mean3d", "xyz_auc3d"] and len(lines) == 14
    assert result["baseline"]["overall"]["skipped"].endswith("has no hand labels; --baseline-store TRAIN")
    assert np.isfinite(result["overall"]["oce"]) and result["overall"]["oce"] < 1e-3  # the object pose is given


def test_offset_submission_scores_the_offset(untrained_run, eval_store, ho3d_root, mano_dir, tmp_path, monkeypatch):
    scores = _evaluate(untrained_run, eval_store, ho3d_root, mano_dir, tmp_path, monkeypatch,
                       offset=(0.006, -0.008, 0.0))["ho3d_challenge"]  # 1 cm
    assert scores["xyz_mean3d"] == pytest.approx(1.0, abs=1e-5) and scores["mesh_mean3d"] == pytest.approx(1.0, abs=1e-5)
    thresholds = np.linspace(0, 0.05, 100)
    assert scores["xyz_auc3d"] == pytest.approx(np.trapezoid((thresholds >= 0.01).astype(float), thresholds) / 0.05)
    for name in ("xyz_procrustes_al_mean3d", "xyz_scale_trans_al_mean3d", "mesh_al_mean3d"):
        assert abs(scores[name]) < 1e-5, name  # a translation is aligned away
    assert scores["f_al_score_5"] == pytest.approx(1.0) and scores["f_score_5"] < 1.0


def test_submission_files_are_what_eval_py_reads_and_scores(untrained_run, eval_store, ho3d_root, mano_dir, tmp_path,
                                                            monkeypatch):
    """A noisy oracle's pred.zip, unpacked into res/ beside the ground truth in ref/ (the server's layout), gives
    the restated eval.py's numbers, and ours equal them."""
    import shutil

    ours = _evaluate(untrained_run, eval_store, ho3d_root, mano_dir, tmp_path / "out", monkeypatch, noise=0.004,
                     offset=(0.004, 0.0, 0.003))["ho3d_challenge"]
    with zipfile.ZipFile(tmp_path / "out" / "pred.zip") as zf:
        assert zf.namelist() == ["pred.json"]  # flat: the server's search does not look into folders
        zf.extractall(tmp_path / "res")
    (tmp_path / "ref").mkdir()
    for name in ("evaluation_xyz.json", "evaluation_verts.json"):
        shutil.copy(ho3d_root / name, tmp_path / "ref" / name)
    official = challenge_eval(tmp_path / "ref", tmp_path / "res")
    assert set(official) <= set(ours)
    for name, value in official.items():
        assert ours[name] == pytest.approx(value, abs=1e-9), name
    assert 0.3 < official["xyz_mean3d"] < 5 and 0 < official["f_score_5"] < 1  # a real, non-trivial error
    # the same files in one folder (the current eval.py's local layout) are found too
    shutil.copy(tmp_path / "res" / "pred.json", tmp_path / "ref" / "pred.json")
    assert challenge_eval(tmp_path / "ref", tmp_path / "ref") == official


def test_ho3d_gt_needs_the_order_and_matching_lengths(untrained_run, eval_store, ho3d_root, mano_dir, tmp_path):
    from hoisdf.evaluate import evaluate
    from hoisdf.scoring.official import score_ho3d_submission
    from hoisdf.scoring.submissions import write_ho3d_pred

    with pytest.raises(ValueError, match="--ho3d-order"):
        evaluate(untrained_run, [eval_store], mano_dir, tmp_path, progress=False, ho3d_gt=ho3d_root)
    pred = write_ho3d_pred(tmp_path / "pred.json", ["SM1/0000"], np.full((1, 21, 3), 0.5), np.full((1, 778, 3), 0.5))
    with pytest.raises(DataError, match="1 samples, the ground truth .* has 4"):
        score_ho3d_submission(pred, ho3d_root)
    with pytest.raises(DataError, match="evaluation_xyz.json"):
        score_ho3d_submission(pred, tmp_path)
