"""The ablation runner (``python -m hoisdf.toy --ablation NAME``): variants trained side by side, one table."""

from __future__ import annotations

import json

import pytest
import torch

from hoisdf.ablation import TABLES, markdown_table, run_table, training_runs

pytestmark = pytest.mark.slow  # trains and evaluates several runs

SMALL = ["model.image_size=64", "model.grid_resolution=12", "model.hand_queries=24", "model.object_queries=12",
         "model.hand_layers=1", "model.decoder_layers=1", "train.batch_size=2", "train.workers=0",
         "train.point_sampling_epoch=0", "train.log_every=1"]


def test_sampling_table_trains_three_runs_and_evaluates_four_rows(tiny_store, mano_dir, tmp_path):
    out = tmp_path / "ablation"
    summary = run_table("sampling", tiny_store, tiny_store, mano_dir, out, steps=2, seed=0, extra=SMALL)
    assert [r["label"] for r in summary["rows"]] == [r.label for r in TABLES["sampling"]]
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["absolute_distance__ours", "random", "signed_distance"]
    for row in summary["rows"]:
        assert all(row["ours"][m] is not None and row["ours"][m] > 0 for m in ("rr_mje", "oce")), row
    # the gradient row: the absolute run's weights, evaluated with the gradient step
    derived = torch.load(out / "derived" / "field_gradient" / "checkpoints" / "last.pt", weights_only=True)
    source = torch.load(out / "runs" / "absolute_distance__ours" / "checkpoints" / "last.pt", weights_only=True)
    assert derived["config"]["model"]["sampling"] == "gradient" and source["config"]["model"]["sampling"] == "absolute"
    assert all(torch.equal(derived["model"][k], source["model"][k]) for k in source["model"])
    data = json.loads((out / "table.json").read_text())
    assert data["steps_per_variant"] == 2 and (out / "ablation.png").stat().st_size > 10_000
    table = (out / "table.md").read_text()
    assert "| Random | " in table and "/ 25.8 |" in table and "mean-pose baseline" in table
    # a second call resumes: no variant is trained again
    before = (out / "runs" / "random" / "checkpoints" / "last.pt").stat().st_mtime_ns
    assert not run_table("sampling", tiny_store, tiny_store, mano_dir, out, 2, 0, SMALL)["train_seconds"]
    assert (out / "runs" / "random" / "checkpoints" / "last.pt").stat().st_mtime_ns == before
    # a larger budget resumes every variant from its checkpoint instead of starting again
    assert len(run_table("sampling", tiny_store, tiny_store, mano_dir, out, 3, 0, SMALL)["train_seconds"]) == 3
    last = torch.load(out / "runs" / "random" / "checkpoints" / "last.pt", weights_only=True)
    assert last["progress"]["global_step"] == 3


def test_feature_augmentation_rows_run_without_cross_fields():
    for row in TABLES["feature_augmentation"]:
        assert 'model.cross_field="none"' in row.train, row.label
    assert len(training_runs(TABLES["feature_augmentation"])) == 4
    assert len(training_runs(TABLES["sampling"])) == 3


def test_unknown_table_is_refused(tiny_store, mano_dir, tmp_path):
    with pytest.raises(ValueError, match="unknown ablation"):
        run_table("colour", tiny_store, tiny_store, mano_dir, tmp_path, 1, 0, [])


def test_markdown_table_marks_missing_values():
    summary = {"table": "pose_regressor", "steps_per_variant": 5, "seed": 0,
               "rows": [{"label": "x", "ours": {"rr_mje": 1.0, "pa_mje": 2.0, "oce": None, "mce": None, "add_s": None},
                         "paper": {"rr_mje": 10.4, "pa_mje": 5.49}}],
               "mean_pose_baseline": {"rr_mje": 3.0, "pa_mje": 4.0, "oce": 5.0, "mce": 6.0, "add_s": 7.0}}
    text = markdown_table(summary)
    assert "| x | 1.0 / 10.4 | 2.0 / 5.5 | - / - | - / - | - / - |" in text
