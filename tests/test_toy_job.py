"""The main job (python -m hoisdf.toy) end to end at a reduced size: data, stores, training, evaluation, report."""

from __future__ import annotations

import json

import pytest

from hoisdf.toy import beats_baseline, main

pytestmark = pytest.mark.slow  # the main job, end to end


def test_main_job_end_to_end_reduced(tmp_path, capsys):
    out = tmp_path / "toy_run"
    small = ["model.grid_resolution=16", "model.hand_queries=64", "model.object_queries=32", "train.batch_size=4",
             "train.workers=1"]
    assert main(["--out", str(out), "--sequences", "5", "--frames", "2", "--steps", "3", "--vis", "2", *small]) == 0
    report = out / "report"
    hpe = [p.name for p in report.glob("dexycb_hpe_*.txt")]
    assert hpe == ["dexycb_hpe_s0_test_subset.txt"]  # the toy has 3 of the toolkit's 8 cameras
    for name in ("metrics.json", "per_object.csv", "training_curve.png", "store_grid.png", "summary.json", *hpe):
        assert (report / name).is_file() and (report / name).stat().st_size > 0, name
    assert len(list((report / "vis").glob("*.png"))) == 2
    metrics = json.loads((report / "metrics.json").read_text())
    assert metrics["samples"] > 0 and metrics["baseline"]["peeks_at_evaluated_labels"] is False
    summary = json.loads((report / "summary.json").read_text())
    assert set(summary["beats_mean_pose_baseline"]) == {"rr_mje", "pa_mje", "oce", "add_s"}
    assert summary["train_steps"] == 3
    printed = capsys.readouterr().out
    assert "model vs mean-pose baseline" in printed and "HOISDF (this run)" in printed
    # a second run resumes: stores and the trained run are kept, evaluation is repeated
    before = (out / "run" / "checkpoints" / "last.pt").stat().st_mtime_ns
    assert main(["--out", str(out), "--sequences", "5", "--frames", "2", "--steps", "3", "--vis", "0", *small]) == 0
    assert (out / "run" / "checkpoints" / "last.pt").stat().st_mtime_ns == before


def test_beats_baseline_compares_lower_is_better():
    model = {"rr_mje": 10.0, "pa_mje": 5.0, "oce": 30.0}
    baseline = {"rr_mje": 12.0, "pa_mje": 4.0, "oce": 31.0, "add_s": 9.0}
    assert beats_baseline(model, baseline) == {"rr_mje": True, "pa_mje": False, "oce": True}


def test_sizes_and_steps_must_be_positive(tmp_path, capsys):
    """0 would silently mean make-toy's default size or an unlimited training run: refused before anything runs."""
    import pytest

    for flag, value in (("--steps", "0"), ("--sequences", "-1"), ("--frames", "two")):
        with pytest.raises(SystemExit) as exit_info:
            main(["--out", str(tmp_path / "run"), flag, value])
        assert exit_info.value.code == 2
        assert f"argument {flag}: expected a whole number >= 1" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
