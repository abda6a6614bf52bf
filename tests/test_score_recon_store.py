"""``hoisdf score recon --gt-store``: the ground truth posed from a store's labels (hoisdf.scoring.recon_store)
equals the meshes the build's own code poses from the dataset's annotations, and bad input is one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from hoisdf.scoring.cli import main

pytestmark = pytest.mark.slow  # builds the tiny toy store (session fixture) and poses its hands


def test_store_ground_truth_equals_the_readers_meshes(tiny_store, tiny_dexycb, tmp_path):
    from hoidata.datasets.dexycb import DexYCBReader
    from hoidata.hand import load_mano
    from hoidata.records.records import posed_hand
    from hoidata.records.settings import load_build_config
    from hoidata.store import read_index
    from hoisdf.scoring.recon_store import write_store_gt

    made = write_store_gt(tiny_store, tmp_path, ("hand", "obj"), tiny_dexycb / "mano")
    index = read_index(tiny_store)
    mirrored = np.asarray(index.labels["mirrored"], bool)
    assert made == {"records": int((~mirrored).sum()), "mirrored_left_out": int(mirrored.sum())}
    assert made["records"] > 0 and made["mirrored_left_out"] > 0  # the tiny store has both
    cfg = load_build_config("toy", [])
    frames = {f.frame_id: f for f in DexYCBReader(tiny_dexycb, tiny_dexycb / "mano", "train",
                                                  cfg.dataset.dexycb_setting()).frames() if f.side == "right"}
    mano = load_mano(tiny_dexycb / "mano", side="right")
    written = sorted(tmp_path.glob("*_hand.obj"))
    assert len(written) == made["records"] == len(frames)
    for path in written:
        frame = frames[path.name.removesuffix("_hand.obj")]
        mesh = trimesh.load(str(path), process=False)
        # the build's pose of the same frame (float32 MANO, as the gSDF export) within float32 rounding
        assert np.abs(mesh.vertices - posed_hand(frame, mano)).max() < 1e-6
        obj = trimesh.load(str(path.with_name(path.name.replace("_hand", "_obj"))), process=False)
        raw = index.objects[frame.object_name][0].astype(np.float64)
        pose = np.asarray(frame.object_pose)
        assert np.abs(obj.vertices - (raw @ pose[:3, :3].T + pose[:3, 3])).max() < 1e-6


def test_cli_scores_a_store_and_its_own_meshes_perfectly(tiny_store, tiny_dexycb, tmp_path, capsys):
    from hoisdf.scoring.recon_store import write_store_gt

    pred = tmp_path / "pred"
    pred.mkdir()
    write_store_gt(tiny_store, pred, ("hand", "obj"), tiny_dexycb / "mano")  # the truth as the prediction
    out = tmp_path / "scores.json"
    fast = ["--chamfer-tolerance", "0.01", "--f-tolerance", "0.01", "--parts", "obj"]
    assert main(["recon", "--pred", str(pred), "--gt-store", str(tiny_store), "--protocol", "exact",
                 "--out", str(out), *fast]) == 0
    text = capsys.readouterr().out
    assert "mirrored (left-hand) records of the store left out" in text
    result = json.loads(out.read_text())
    assert result["settings"]["gt_layout"] == "posed from a store" and result["parts"]["obj"]["failures"] == 0
    assert result["parts"]["obj"]["f_5mm"] > 0.99 and result["parts"]["obj"]["chamfer"] < 0.01


@pytest.mark.parametrize("breaks, words", [
    ("no_mano", ["--mano", "needs the MANO folder"]),
    ("no_store", ["missing_store"]),
    ("no_pred", ["pred", "prediction folder not found"]),
])
def test_bad_store_input_is_one_line_and_writes_nothing(tiny_store, tmp_path, capsys, breaks, words):
    pred = tmp_path / "pred"
    pred.mkdir()
    out = tmp_path / "scores.json"
    out.write_text("kept")
    args = ["recon", "--pred", pred, "--gt-store", tiny_store, "--out", out]
    if breaks == "no_store":
        args[4] = tmp_path / "missing_store"
    elif breaks == "no_pred":
        pred.rmdir()
    code = main([str(a) for a in args])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("hoisdf score recon: error:"), err
    assert all(w in err for w in words), err
    assert out.read_text() == "kept"
