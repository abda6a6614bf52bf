"""Evaluation CLI and pictures: result files, metric wiring (oracle), exports, PNGs, training curve."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from hoidata.errors import DataError

TINY = ["model.depth=18", "model.image_size=64", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16",
        "model.hand_layers=1", "model.decoder_layers=1", "model.object_layers=1"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, mano_dir):
    """A run folder with an untrained tiny model's checkpoint."""
    from hoidata.hand import load_mano
    from hoisdf.config import load_train_config
    from hoisdf.model import build_model
    from hoisdf.training.checkpoint import save_checkpoint

    cfg = load_train_config(None, TINY)
    torch.manual_seed(0)
    model = build_model(cfg.model, load_mano(mano_dir, side="right"))
    run = tmp_path_factory.mktemp("run")
    payload = {"model": model.state_dict(), "config": cfg.as_dict(), "progress": {"epoch": 3, "step": 0,
                                                                                 "global_step": 12}}
    save_checkpoint(run / "checkpoints" / "last.pt", payload)
    return run


@pytest.fixture(scope="module")
def evaluated(run_dir, tiny_store, mano_dir, tmp_path_factory):
    from hoisdf.evaluate import evaluate

    out = tmp_path_factory.mktemp("eval")
    result = evaluate(run_dir, [tiny_store], mano_dir, out, batch_size=4, vis=2, plausibility=2, progress=False)
    return out, result


def _store_size(store) -> int:
    from hoidata.store import read_index

    return len(read_index(store).keys)


@pytest.mark.slow
def test_evaluate_writes_finite_metrics_for_every_sample(evaluated, tiny_store):
    out, result = evaluated
    n = _store_size(tiny_store)
    data = json.loads((out / "metrics.json").read_text())
    assert data["samples"] == n == result["samples"]
    assert data["epoch"] == 3 and data["global_step"] == 12 and data["checkpoint"].endswith("last.pt")
    assert sum(data["counts"]["per_object"].values()) == n
    for section in (data["overall"], data["baseline"]["overall"]):
        for name in ("rr_mje", "mje", "pa_mje", "st_mje", "rr_auc", "oce", "mce", "add_s", "ome", "mme", "pa_mme",
                     "f5", "f15", "pa_f5"):
            assert section[name] is not None and np.isfinite(section[name]), name
    assert 0 < data["overall"]["pa_mje"] <= data["overall"]["rr_mje"] + 1e-9  # alignment can only help
    plaus = data["plausibility"]["model"]
    assert plaus["num_samples"] == 2 and 0 <= plaus["contact_ratio"] <= 1
    with open(out / "per_object.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["object"] for r in rows][-1] == "all"
    assert sum(int(r["samples"]) for r in rows[:-1]) == n == int(rows[-1]["samples"])
    assert float(rows[-1]["rr_mje"]) == pytest.approx(data["overall"]["rr_mje"], rel=1e-5)
    assert "PA-MJE" in result["table"] and "mean-pose baseline" in result["table"]


@pytest.mark.slow
def test_hpe_file_reads_back_to_the_predicted_joints(evaluated, run_dir, tiny_store, mano_dir):
    from hoidata.hand import load_mano
    from hoisdf.evaluation.inference import infer, load_for_eval
    from hoisdf.scoring.submissions import read_dexycb_hpe

    out, _ = evaluated
    from hoidata.store import read_index

    ids, joints = read_dexycb_hpe(out / "dexycb_hpe_s0_train_subset.txt")  # 1 camera of the toolkit's 8: a subset
    mano = load_mano(mano_dir, side="right")
    model, config, _ = load_for_eval(run_dir, mano, torch.device("cpu"))
    col = infer(model, mano, config, [tiny_store], 4, torch.device("cpu"), progress=False)
    assert ids.tolist() == read_index(tiny_store).labels["sample_index"].tolist()  # the toolkit's ids, store order
    # mirrored records (left hands) go back to the toolkit's frame: x negated
    mirrored = col.get("mirrored").astype(bool)
    assert 0 < mirrored.sum() < len(mirrored)
    sign = np.where(mirrored[:, None, None], np.array([-1.0, 1.0, 1.0]), 1.0)
    np.testing.assert_allclose(joints, col.get("joints") * sign, atol=1e-8)  # metres; the file is mm, 6 decimals
    # camera frame: the joints sit near the GT wrist, not at the origin
    assert np.linalg.norm(joints[:, 0] - (col.get("gt_joints") * sign)[:, 0], axis=-1).max() < 1e-6


@pytest.mark.slow
def test_vis_writes_non_blank_pictures(evaluated):
    out, _ = evaluated
    pngs = sorted((out / "vis").glob("*.png"))
    assert len(pngs) == 2
    for png in pngs:
        img = cv2.imread(str(png))
        assert img is not None and img.shape[0] >= 256 and img.shape[1] > 2 * 256
        assert img.std() > 10 and len(np.unique(img.reshape(-1, 3), axis=0)) > 50


def _oracle_forward(self, batch, points="field", **_):
    """Ground truth in the model's output format (hand relative to the root, object pose model -> camera)."""
    from hoisdf.training.losses import hand_targets, mirrored_shape_mano

    gt = hand_targets(self.mano, mirrored_shape_mano(self.mano), batch)
    b = len(batch["key"])
    zeros = torch.zeros(b, 4, 3)
    return {"joints": batch["joints_3d"] - batch["hand_root"][:, None], "verts": gt["verts"],
            "obj_rotation": batch["object_pose"][:, :3, :3], "obj_translation": batch["object_pose"][:, :3, 3],
            "hand_query": zeros, "hand_query_sdf": zeros[..., 0], "obj_query": zeros, "obj_query_sdf": zeros[..., 0]}


@pytest.mark.slow
def test_oracle_predictions_score_zero_and_the_baseline_does_not(run_dir, tiny_store, mano_dir, tmp_path,
                                                                 monkeypatch):
    from hoisdf.evaluate import evaluate
    from hoisdf.model.hoisdf import HOISDF

    monkeypatch.setattr(HOISDF, "forward", _oracle_forward)
    result = evaluate(run_dir, [tiny_store], mano_dir, tmp_path, batch_size=8, plausibility=0, progress=False,
                      baseline_store=tiny_store)
    model, base = result["overall"], result["baseline"]["overall"]
    for name in ("rr_mje", "mje", "pa_mje", "st_mje", "oce", "mce", "add_s", "ome", "mme", "pa_mme"):
        assert model[name] < 1e-3, (name, model[name])  # millimetres
    assert model["rr_auc"] == pytest.approx(1.0, abs=0.01) and model["f5"] == pytest.approx(1.0)
    for name in ("rr_mje", "pa_mje", "oce", "add_s", "mme"):
        assert base[name] > 1.0, (name, base[name])
    assert result["baseline"]["peeks_at_evaluated_labels"] is True
    assert result["plausibility"] == {"skipped": "--plausibility 0"}
    # the HPE file holds the dataset's own labels: left hands un-mirrored
    from hoidata.store import read_index
    from hoisdf.scoring.submissions import read_dexycb_hpe

    lab = read_index(tiny_store).labels
    ids, joints = read_dexycb_hpe(tmp_path / "dexycb_hpe_s0_train_subset.txt")
    rows = [lab["sample_index"].tolist().index(i) for i in ids]
    original = np.where(lab["mirrored"][rows][:, None, None], lab["joints_3d"][rows] * [-1, 1, 1], lab["joints_3d"][rows])
    np.testing.assert_allclose(joints, original, atol=1e-6)


def test_mirrored_records_get_the_mirrored_object_mesh():
    """A mirrored record's pose [M R M | M t] applied to its sample mesh gives the mirror image M (R v + t) of the
    original scene object, wound outward (positive volume)."""
    import trimesh

    from hoidata.geometry.rotation import axis_angle_to_matrix
    from hoisdf.evaluation.model_scores import sample_meshes

    box = trimesh.creation.box(extents=(0.05, 0.08, 0.1))
    box.apply_translation((0.03, 0.01, -0.02))  # not symmetric in x
    objects = {"box": (np.asarray(box.vertices), np.asarray(box.faces))}
    R = axis_angle_to_matrix(torch.tensor([[0.4, -0.9, 0.3]]))[0].double().numpy()
    t, M = np.array([0.05, -0.02, 0.6]), np.diag([-1.0, 1.0, 1.0])
    (v0, _), (v1, f1), (v2, _) = sample_meshes(objects, ["box", "box", "box"], [False, True, True])
    assert v1 is v2 and v0 is objects["box"][0]  # shared, not copied per sample
    posed = v1 @ (M @ R @ M).T + M @ t
    np.testing.assert_allclose(posed, (objects["box"][0] @ R.T + t) @ M, atol=1e-12)
    assert trimesh.Trimesh(v1, f1, process=False).volume > 0


@pytest.mark.slow
def test_cli_help_runs():
    proc = subprocess.run([sys.executable, "-m", "hoisdf.evaluate", "--help"], capture_output=True, text=True,
                          timeout=120, check=False)
    assert proc.returncode == 0 and "--ckpt" in proc.stdout and "--ho3d-order" in proc.stdout


@pytest.mark.slow
def test_cli_default_out_limit_and_ho3d_skip(run_dir, tiny_store, mano_dir, tmp_path, capsys):
    from hoisdf.evaluate import main

    order = tmp_path / "evaluation.txt"
    order.write_text("SM1/0000\n")
    args = ["--ckpt", str(run_dir / "checkpoints" / "last.pt"), "--shards", str(tiny_store), "--mano",
            str(mano_dir), "--limit", "3", "--plausibility", "0", "--no-progress"]
    assert main([*args, "--ho3d-order", str(order)]) == 2  # a pred.json was asked for that no store can give
    assert "none of the stores is an HO-3D store" in capsys.readouterr().err
    rc = main(args)
    printed = capsys.readouterr().out
    assert rc == 0 and "mean-pose baseline" in printed
    out = run_dir / f"eval-{tiny_store.name}"
    assert json.loads((out / "metrics.json").read_text())["samples"] == 3
    assert len((out / "dexycb_hpe_s0_train_subset.txt").read_text().splitlines()) == 3
    assert not (out / "pred.json").exists() and "dexycb_hpe_s0_train_subset.txt: a subset of s0_train" in printed


@pytest.mark.slow
def test_ho3d_export_follows_the_evaluation_list(tiny_store, tmp_path):
    from hoisdf.evaluation.inference import Collected
    from hoisdf.evaluation.outputs import export
    from hoisdf.scoring.submissions import read_dexycb_hpe, read_ho3d_pred

    rng = np.random.default_rng(0)
    joints = rng.normal(size=(3, 21, 3)) * 0.05 + [0, 0, 0.6]
    verts = rng.normal(size=(3, 778, 3)) * 0.05 + [0, 0, 0.6]
    col = Collected(keys=["a", "b", "c"], store=[0, 0, 0], rows=[4, 5, 7], names=["x"] * 3,
                    frame_ids=["SM1_0001", "SM1_0000", "MPM10_0003"])
    col.add(joints=joints, verts=verts, gt_joints=joints, ho3d=np.ones(3))
    order = tmp_path / "evaluation.txt"
    order.write_text("SM1/0000\nMPM10/0003\nSM1/0001\n")
    files, _ = export(col, [tiny_store], tmp_path, order)
    assert sorted(Path(f).name for f in files.values()) == ["dexycb_hpe_s0_train_subset.txt", "pred.json", "pred.zip"]
    back_j, back_v = read_ho3d_pred(tmp_path / "pred.zip")
    np.testing.assert_allclose(back_j, joints[[1, 2, 0]], atol=1e-12)
    np.testing.assert_allclose(back_v, verts[[1, 2, 0]], atol=1e-12)
    from hoidata.store import read_index

    ids, hpe = read_dexycb_hpe(tmp_path / "dexycb_hpe_s0_train_subset.txt")
    assert ids.tolist() == read_index(tiny_store).labels["sample_index"][[4, 5, 7]].tolist()
    assert np.allclose(hpe, joints, atol=1e-8)
    order.write_text("SM1/0000\nSM1/0009\n")  # a frame without prediction: an error naming it, nothing written
    (tmp_path / "pred.json").unlink()
    with pytest.raises(DataError, match="pred.json: not written: no prediction for frame 'SM1/0009'"):
        export(col, [tiny_store], tmp_path, order)
    assert not (tmp_path / "pred.json").exists()


@pytest.mark.slow
def test_missing_checkpoint_is_a_data_error_naming_it(tiny_store, mano_dir, tmp_path):
    from hoisdf.evaluate import evaluate

    missing = tmp_path / "no-run"
    with pytest.raises(DataError, match=str(missing)):
        evaluate(missing, [tiny_store], mano_dir, tmp_path / "out", progress=False)


def test_training_curve_plot(tmp_path):
    from hoisdf.evaluation.visualize import plot_training_curve, read_curve

    path = tmp_path / "metrics.csv"
    rows = [["split", "epoch", "step", "name", "value"]]
    for step in range(0, 50, 10):
        rows += [["train", 0, step, "total", 10 / (step + 1)], ["train", 0, step, "sdf_hand", 1 / (step + 1)]]
    rows += [["val", 0, 49, "total", 0.5], ["val", 0, 49, "mje_mm", 30.0], ["val", 1, 99, "mje_mm", 25.0]]
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    curves = read_curve(path)
    assert curves["train"]["total"][0].tolist() == [0, 10, 20, 30, 40]
    assert curves["val"]["mje_mm"][1].tolist() == [30.0, 25.0]
    png = plot_training_curve(path, tmp_path / "curve.png")
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] > 800 and img.std() > 5
    path.write_text("split,epoch,step,name\ntrain,0,0,total\n")
    with pytest.raises(DataError, match="value"):
        plot_training_curve(path, tmp_path / "bad.png")


def test_draw_result_marks_projected_joints_and_query_points_get_a_colour_bar():
    from hoisdf.evaluation.visualize import (
        GT_COLOR,
        PRED_COLOR,
        draw_query_points,
        draw_result,
        project,
    )

    K = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    joints = np.zeros((21, 3)) + [0.0, 0.0, 0.5]
    joints[:, 0] = np.linspace(-0.1, 0.1, 21)
    uv, front = project(joints, K)
    assert front.all() and np.allclose(uv[:, 1], 50) and np.allclose(uv[[0, -1], 0], [30, 70])
    img = np.zeros((100, 100, 3), np.uint8)
    out = draw_result(img, K, pred_joints=joints, gt_joints=joints + [0, 0.05, 0])
    assert tuple(out[50, 50]) == PRED_COLOR and tuple(out[60, 50]) == GT_COLOR and out[5, 5].sum() == 0
    behind = draw_result(img, K, pred_joints=joints * [1, 1, -1])
    assert behind.sum() == 0  # points behind the camera are not drawn
    pts = draw_query_points(np.full((100, 100, 3), 128, np.uint8), K, joints, np.linspace(-0.01, 0.01, 21))
    assert pts.shape == (100, 164, 3)
    assert pts[50, 30, 2] > pts[50, 30, 0] and pts[50, 70, 0] > pts[50, 70, 2]  # inside blue, outside red
