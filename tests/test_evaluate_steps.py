"""``hoisdf.evaluate`` in steps (issue 34): options, collect, score, write and the one place metrics.json's content
is built, each run here without a checkpoint or a store (the whole command on a store: tests/test_evaluate.py)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hoisdf.evaluate import EvalOptions, build_parser, options_from_args, result_dict, score_collected
from hoisdf.evaluation.inference import Collected


def test_the_flags_are_the_options():
    args = build_parser().parse_args(["--ckpt", "run", "--shards", "s", "--mano", "m", "--batch-size", "3", "--vis",
                                      "2", "--boxes", "predicted", "--plausibility", "0", "--workers", "0",
                                      "--precision", "bf16", "--no-progress", "--limit", "5"])
    assert options_from_args(args) == EvalOptions(batch_size=3, vis=2, boxes="predicted", plausibility=0, workers=0,
                                                  precision="bf16", progress=False, limit=5)
    assert options_from_args(build_parser().parse_args(["--ckpt", "r", "--shards", "s", "--mano", "m"])) == EvalOptions()


def test_options_refuse_what_no_evaluation_can_run():
    EvalOptions().check()
    with pytest.raises(ValueError, match="boxes must be"):
        EvalOptions(boxes="oracle").check()
    with pytest.raises(ValueError, match="--ho3d-gt scores the pred.json that --ho3d-order writes"):
        EvalOptions(ho3d_gt="gt").check()


def _collected(n: int = 4) -> Collected:
    """``n`` samples of one object: the prediction is the ground truth moved by 1 cm (joints) and 2 cm (object)."""
    rng = np.random.default_rng(0)
    joints = rng.normal(0.0, 0.05, (n, 21, 3)) + [0.0, 0.0, 0.5]
    pose = np.tile(np.eye(4), (n, 1, 1))
    pose[:, :3, 3] = [0.05, 0.0, 0.5]
    moved = pose.copy()
    moved[:, 0, 3] += 0.02
    col = Collected(keys=[f"k{i}" for i in range(n)], store=[0] * n, rows=list(range(n)), names=["cube"] * n,
                    frame_ids=[str(i) for i in range(n)])
    col.add(joints=joints + [0.01, 0.0, 0.0], gt_joints=joints, root=joints[:, 0], obj_pose=moved, gt_obj_pose=pose,
            obj_center=pose[:, :3, 3], ho3d=np.zeros(n), mirrored=np.zeros(n), upstream_crop=np.array([1, 0, 0, 1.0]))
    return col


def _cube():
    verts = np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.03, 0.03) for z in (-0.03, 0.03)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                      [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return verts, faces


def _index(kind: int = 2):
    return SimpleNamespace(objects={"cube": _cube()}, labels={"kind": np.array([kind])})


def test_score_collected_scores_the_samples_without_a_model(tmp_path):
    store = tmp_path / "store"
    scored = score_collected(_collected(), None, [store], {store: _index()}, EvalOptions(plausibility=0))
    assert scored.summary["all"]["mje"] == pytest.approx(10.0)  # mm: every joint 1 cm off
    assert scored.summary["all"]["oce"] == pytest.approx(20.0)  # the object centre 2 cm off
    assert scored.counts == {"cube": 4} and scored.baseline is None and scored.baseline_store == store
    assert scored.plausibility == {"skipped": "no predicted hand mesh"}
    with pytest.raises(Exception, match="no mesh in the store index for \\['cube'\\]"):
        score_collected(_collected(), None, [store], {store: SimpleNamespace(objects={}, labels={})}, EvalOptions())


def test_the_result_dict_is_built_in_one_place(tmp_path):
    store = tmp_path / "store"
    col = _collected()
    scored = score_collected(col, None, [store], {store: _index()}, EvalOptions(plausibility=0))
    written = {"files": {"hpe:x": "f.txt"}, "dexycb_hpe": {}}
    result = result_dict({"checkpoint": "c.pt", "epoch": 1}, [store], "cpu", col, scored, "a note", written,
                         EvalOptions(precision="bf16"))
    assert list(result)[:4] == ["checkpoint", "epoch", "stores", "device"] and list(result)[-2:] == list(written)
    assert result["samples"] == 4 and result["precision"]["mode"] == "bf16" and result["notes"] == ["a note"]
    assert result["counts"] == {"per_object": {"cube": 4}, "hand_metrics": 4, "object_metrics": 4}
    assert result["upstream_crop_records"] == 2 and result["baseline"]["peeks_at_evaluated_labels"]
    assert "has no hand labels" in result["baseline"]["overall"]["skipped"]
    assert result["overall"] == scored.summary["all"] and result["per_object"] == {"cube": scored.summary["cube"]}
    assert Path(result["stores"][0]) == store


def test_write_outputs_writes_the_result_files_without_a_model(tmp_path, capsys):
    from hoisdf.evaluate import write_outputs

    store = tmp_path / "store"
    col = _collected()
    index = _index()
    index.labels.update({"dataset": np.array(["dexycb"] * 4), "split": np.array(["test"] * 4),
                         "sample_index": np.arange(4)})
    index.provenance, index.skipped = {}, []
    scored = score_collected(col, None, [store], {store: index}, EvalOptions(plausibility=0))
    written = write_outputs(tmp_path / "out", col, scored, None, [store], {store: index}, None, EvalOptions())
    hpe = tmp_path / "out" / "dexycb_hpe_unknown_test_subset.txt"  # the store records no toolkit split size
    assert written["files"] == {f"hpe:{store}:unknown_test": str(hpe)} and hpe.is_file()
    assert written["dexycb_hpe"][hpe.name]["samples"] == 4 and "ho3d_challenge" not in written
    assert (tmp_path / "out" / "per_object.csv").read_text().count("cube") == 1
    assert not (tmp_path / "out" / "vis").exists() and "a subset of unknown_test" in capsys.readouterr().out
