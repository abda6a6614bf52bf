"""The official evaluators' scores (hoisdf.scoring.official) on hand-made hands whose answers follow from the
construction: identical, moved by 1 cm, scaled about the wrist, another topology; and the hoisdf command's
dispatch. The fast tier's check of the scoring code; tests/test_score.py holds the golden numbers of the evaluators'
own scripts on toy data (slow)."""

from __future__ import annotations

import numpy as np
import pytest

from hoisdf.scoring.official import HO3D_SCORES, dexycb_hpe_scores, ho3d_challenge_scores

SHIFT = np.array([0.01, 0.0, 0.0])  # metres
STEP = 1 / 99  # one step of the AUC's 100 thresholds, as a share of its range
TINY = 1e-5  # cm: procrustes divides by the norm plus eval.py's epsilon, which leaves ~4e-7 cm


@pytest.fixture
def hands():
    rng = np.random.default_rng(3)
    xyz = rng.normal(scale=0.04, size=(3, 21, 3)) + [0.0, 0.0, 0.5]
    verts = rng.normal(scale=0.04, size=(3, 778, 3)) + [0.0, 0.0, 0.5]
    return xyz, verts


def test_ho3d_scores_of_the_ground_truth_itself_are_perfect(hands):
    scores = ho3d_challenge_scores(*hands, *hands)
    assert list(scores) == list(HO3D_SCORES)
    assert scores["xyz_mean3d"] == scores["mesh_mean3d"] == 0.0 and scores["xyz_auc3d"] == scores["mesh_auc3d"] == 1.0
    for name in HO3D_SCORES:  # the aligned ones: the alignment's rounding moves a point by ~1e-17 m
        if "mean3d" in name:
            assert scores[name] == pytest.approx(0.0, abs=TINY), name
        else:
            assert scores[name] == pytest.approx(1.0, abs=STEP), name
    assert all(scores[name] == 1.0 for name in HO3D_SCORES if name.startswith("f_"))


def test_ho3d_scores_of_a_moved_hand(hands):
    xyz, verts = hands
    scores = ho3d_challenge_scores(xyz + SHIFT, verts + SHIFT, xyz, verts)
    assert scores["xyz_mean3d"] == pytest.approx(1.0) and scores["mesh_mean3d"] == pytest.approx(1.0)  # cm
    for name in ("xyz_procrustes_al_mean3d", "xyz_scale_trans_al_mean3d", "mesh_al_mean3d"):
        assert scores[name] == pytest.approx(0.0, abs=TINY), name  # each alignment undoes a translation
    # every error is 10 mm: the PCK curve over 0-50 mm steps from 0 to 1 at 10 mm
    assert scores["xyz_auc3d"] == pytest.approx(0.8, abs=STEP) and scores["mesh_auc3d"] == pytest.approx(0.8, abs=STEP)
    assert scores["f_al_score_5"] == scores["f_al_score_15"] == 1.0
    assert scores["f_score_5"] < scores["f_score_15"] <= 1.0


def test_ho3d_scale_and_translation_alignment_undoes_a_scaling_about_the_wrist(hands):
    xyz, verts = hands
    wrist = xyz[:, :1]
    scores = ho3d_challenge_scores((xyz - wrist) * 1.5 + wrist, (verts - wrist) * 1.5 + wrist, xyz, verts)
    assert scores["xyz_scale_trans_al_mean3d"] == pytest.approx(0.0, abs=TINY)
    assert scores["xyz_procrustes_al_mean3d"] == pytest.approx(0.0, abs=TINY)
    assert scores["mesh_al_mean3d"] == pytest.approx(0.0, abs=TINY) and scores["xyz_mean3d"] > 1.0


def test_ho3d_points_of_another_topology_get_the_evaluators_no_mesh_values(hands):
    xyz, verts = hands
    scores = ho3d_challenge_scores(xyz, verts[:, :300], xyz, verts)
    assert (scores["mesh_mean3d"], scores["mesh_auc3d"], scores["mesh_al_mean3d"], scores["mesh_al_auc3d"]) == (
        -100.0, -1.0, -100.0, -1.0)
    assert scores["xyz_mean3d"] == 0.0 and 0.0 < scores["f_score_5"] < 1.0  # 300 of 778 points: recall falls
    empty = ho3d_challenge_scores(xyz, np.zeros((3, 0, 3)), xyz, verts)
    assert all(empty[k] == 0.0 for k in HO3D_SCORES if k.startswith("f_"))


def test_dexycb_hpe_scores_of_a_moved_hand(hands):
    gt_mm = hands[0] * 1000.0
    same = dexycb_hpe_scores(gt_mm, gt_mm)
    assert same["absolute"] == same["root-relative"] == {"mpjpe": 0.0, "auc": 1.0}
    assert same["procrustes"]["mpjpe"] == pytest.approx(0.0, abs=1e-6)
    moved = dexycb_hpe_scores(gt_mm + SHIFT * 1000.0, gt_mm)
    assert moved["absolute"]["mpjpe"] == pytest.approx(10.0)
    assert moved["absolute"]["auc"] == pytest.approx(0.8, abs=STEP)
    for alignment in ("root-relative", "procrustes"):
        assert moved[alignment]["mpjpe"] == pytest.approx(0.0, abs=1e-6), alignment
        assert moved[alignment]["auc"] == pytest.approx(1.0, abs=STEP), alignment


def test_the_hoisdf_command_dispatches_score_and_refuses_the_unknown(tmp_path, capsys):
    from hoisdf.cli import main

    assert main(["--help"]) == 0 and "usage: hoisdf {score, check}" in capsys.readouterr().out
    assert main(["nonsense"]) == 2 and "usage: hoisdf {score, check}" in capsys.readouterr().err
    missing = tmp_path / "pred.json"
    assert main(["score", "ho3d", "--pred", str(missing), "--gt", str(tmp_path)]) == 2  # reached hoisdf.scoring.cli
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hoisdf score ho3d: error: ") and str(missing) in err[0]
