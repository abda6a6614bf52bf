"""One reader factory for every pipeline (issue 24, item 1): ``hoidata.datasets.open_reader`` / ``read_splits``.

The class closed here: a command that reads a dataset with other files than it builds from. DexYCB's proximity
filter reads posed object models, so ``--models X`` must reach the reader as it reaches the SDF and mask stage;
a published frame list must be checked by every command that reads one; an unknown dataset name is one line.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_faults_edges import _one_error_line

from hoidata.cli import main as hoidata
from hoidata.datasets import open_reader, read_splits
from hoidata.errors import DataError

CAN, BOX = "002_master_chef_can", "003_cracker_box"  # the tiny toy's right-hand and left-hand objects
# the dexycb preset (5 mm proximity filter) on the tiny toy: every frame of its one train camera, both hands
FILTERED = ['dataset.splits=["train"]', "dataset.complete_subjects=false", "dataset.frame_stride=1",
            'dataset.sides=["right","left"]']
SMALL = ["record.crop_size=128", "record.sdf_samples_hand=256", "record.sdf_samples_object=128", "store.records_per_shard=64"]



def _scaled_models(models: Path, dst: Path, scales: dict[str, float]) -> Path:
    """A copy of a YCB models folder with each named object's mesh scaled about its model origin."""
    shutil.copytree(models, dst)
    for name, factor in scales.items():
        path = dst / name / "textured_simple.obj"
        lines = [" ".join(["v", *(repr(float(x) * factor) for x in line.split()[1:4])]) if line.startswith("v ")
                 else line for line in path.read_text().splitlines()]
        path.write_text("\n".join(lines) + "\n")
    return dst


def _dexycb(overrides=()):
    from hoidata.records.settings import load_build_config

    return load_build_config("dexycb", [*FILTERED, *overrides])


def _read(root: Path, models: Path):
    d = _dexycb().dataset
    return read_splits("dexycb", root, root / "mano", d.splits, models_dir=models, dexycb=d.dexycb_setting())


@pytest.mark.slow  # reads the tiny toy DexYCB
def test_an_unknown_dataset_name_is_one_line_naming_the_field(tiny_dexycb):
    from hoidata.export.job import export_frames
    from hoidata.build_sdf import read_frames

    cfg = _dexycb()
    cfg = replace(cfg, dataset=replace(cfg.dataset, name="ho4d"))  # past the settings' own check: the callers'
    calls = (lambda: open_reader("ho4d", tiny_dexycb, tiny_dexycb / "mano", "train"),
             lambda: read_splits("dexycb_v2", tiny_dexycb, tiny_dexycb / "mano", ["train"]),
             lambda: read_frames(cfg, tiny_dexycb, tiny_dexycb / "mano"),  # build-sdf's reading
             lambda: export_frames(cfg, tiny_dexycb, tiny_dexycb / "mano", tiny_dexycb / "models", ["train"]))
    for call in calls:
        with pytest.raises(DataError) as caught:
            call()
        text = str(caught.value)
        assert "\n" not in text and "'dataset.name'" in text and "expected one of dexycb, ho3d" in text, text
    with pytest.raises(DataError, match="'dataset.frame_list': frame lists hold DexYCB"):  # HO-3D has no ids
        open_reader("ho3d", tiny_dexycb, tiny_dexycb / "mano", "train", frame_ids=[1])


@pytest.mark.slow  # reads the tiny toy DexYCB
def test_build_and_export_both_check_a_frame_list(tiny_dexycb, tmp_path, capsys):
    """An id the dataset does not have stops build-sdf and export alike, naming the list; nothing is written."""
    frames = _read(tiny_dexycb, tiny_dexycb / "models").frames
    listed = tmp_path / "ids.json"
    listed.write_text(json.dumps([f"{frames[0].sample_index:08d}", "99999999"]))  # one id past the split's end
    common = ["--dataset", "dexycb", "--root", str(tiny_dexycb), *FILTERED, f"dataset.frame_list={listed}"]
    for command, out in ((["build-sdf", *SMALL], tmp_path / "store"), (["export", "--format", "gsdf"], tmp_path / "x")):
        assert hoidata([command[0], "--out", str(out), *common, *command[1:]]) == 2, command
        _one_error_line(capsys.readouterr().err, str(listed), "1 listed ids are not frames", "99999999")
        assert not out.exists(), command  # nothing written
    with pytest.raises(DataError, match="one split"):  # a list holds one split's ids, whoever reads it
        read_splits("dexycb", tiny_dexycb, tiny_dexycb / "mano", ["train", "test"], frame_list=listed)


@pytest.mark.slow  # reads the tiny toy DexYCB
def test_build_sdf_filters_and_samples_with_the_models_folder_it_is_given(tiny_dexycb, tmp_path, capsys):
    """``--models X``: X's larger can is what the right-hand records' object SDFs measure, and X's half-size box
    is what the proximity filter measures (every left-hand frame is then too far; with ROOT/models 6 stay)."""
    from hoidata import schema
    from hoidata.geometry.sdf import signed_distance
    from hoidata.objects import load_object_mesh, object_mesh_path, repair_mesh
    from hoidata.store import iter_records, read_index

    x = _scaled_models(tiny_dexycb / "models", tmp_path / "X", {CAN: 1.1, BOX: 0.5})
    own, other = _read(tiny_dexycb, tiny_dexycb / "models"), _read(tiny_dexycb, x)
    assert sum(f.side == "left" for f in own.frames) == 6 and not any(f.side == "left" for f in other.frames)
    out = tmp_path / "store"
    argv = ["build-sdf", "--dataset", "dexycb", "--root", str(tiny_dexycb), "--models", str(x), "--out", str(out)]
    assert hoidata([*argv, *FILTERED, *SMALL]) == 0
    capsys.readouterr()
    index = read_index(out)
    assert index.keys == [f"dexycb-train-{f.frame_id}" for f in other.frames]  # filtered with X: 8 right hands
    too_far = [s for s in index.skipped if "hand-object distance" in s["reason"]]
    left = {f"labels_{i:06d}.npz" for i in range(8)}  # every frame of the left-hand sequence, too far from X's box
    assert len(too_far) == 8 and {Path(s["path"]).name for s in too_far} == left, too_far
    camera = {f.frame_id.rsplit("_", 1)[0] for f in own.frames if f.side == "left"}
    assert {s["frame_id"].rsplit("_", 1)[0] for s in too_far} == camera
    meshes = [repair_mesh(load_object_mesh(object_mesh_path(m, CAN))) for m in (x, tiny_dexycb / "models")]
    checked = 0
    for record in iter_records(out):  # every record a right hand holding X's can: its object SDF is X's
        meta = record[schema.META]
        xyz, _, sdf_object, _ = schema.dequantize_sdf(record[schema.SDF])
        points = xyz.astype(np.float64) + np.asarray(meta["hand_root"])
        pose = np.asarray(meta["object_pose"])
        want = [signed_distance(points, np.asarray(geo.vertices) @ pose[:3, :3].T + pose[:3, 3], np.asarray(geo.faces),
                                bool(report.watertight))[0] for geo, report in meshes]  # as the build's object_asset
        assert meta["object_name"] == CAN and not meta["mirrored"]
        assert np.abs(sdf_object - want[0]).max() < 1e-4  # quantised to 0.02 mm
        assert np.abs(sdf_object - want[1]).max() > 2e-3  # ROOT/models' can is 10 % smaller
        checked += 1
    assert checked == 8


@pytest.mark.slow  # reads the tiny toy DexYCB
def test_export_reads_the_models_folder_it_is_given(tiny_dexycb, tmp_path, capsys):
    """``hoidata export --models Y`` with a model missing from Y: its frames are skipped naming Y's file, the
    others exported; with Y's box halved instead, export selects the frames build-sdf selects with Y."""
    y = tmp_path / "Y"
    shutil.copytree(tiny_dexycb / "models", y)
    shutil.rmtree(y / BOX)
    out = tmp_path / "export"
    argv = ["export", "--format", "handoccnet", "--dataset", "dexycb", "--root", str(tiny_dexycb), "--models", str(y)]
    assert hoidata([*argv, "--out", str(out), *FILTERED]) == 0
    printed = capsys.readouterr().out
    assert f"{y / BOX / 'textured_simple.obj'}: mesh file not found" in printed, printed
    doc = json.loads((out / "annotations" / "DEX_YCB_s0_train_data.json").read_text())
    assert len(doc["images"]) == 8  # the right hands, whose can Y has
    half = _scaled_models(tiny_dexycb / "models", tmp_path / "half", {BOX: 0.5})
    from hoidata.export.job import export_frames

    exported, skips, _ = export_frames(_dexycb(), tiny_dexycb, tiny_dexycb / "mano", half, ("train",))
    assert [f.frame_id for f in exported] == [f.frame_id for f in _read(tiny_dexycb, half).frames]
    assert sum("hand-object distance" in s.reason for s in skips) == 8


@pytest.mark.slow  # reads the tiny toy DexYCB
def test_the_grasp_source_reads_the_models_folder_it_is_given(tiny_dexycb, tmp_path):
    """render-synthetic's DexYCB grasp source (the dexycb preset's 5 mm filter) measures the models it is given:
    with the can halved no right-hand grasp is close enough. (render_synthetic passes its --models: issue 24.)"""
    import torch

    from hoidata.hand import load_mano
    from hoidata.synth.source import load_grasps

    mano = load_mano(tiny_dexycb / "mano", side="right", dtype=torch.float64)
    assert [g.object_name for g in load_grasps(tiny_dexycb, mano)] == [CAN, CAN]  # frames 0 and 5 (stride 5)
    half = _scaled_models(tiny_dexycb / "models", tmp_path / "half", {CAN: 0.5})
    with pytest.raises(DataError, match="no right-hand grasps"):
        load_grasps(tiny_dexycb, mano, tiny_dexycb / "mano", half)
    # the command passes its --models on: nothing is rendered from grasps the models it renders would refuse
    out = tmp_path / "synthetic"
    code = hoidata(["render-synthetic", "--source", str(tiny_dexycb), "--models", str(half), "--out", str(out),
                    "--count", "1"])
    assert code == 2 and not (out / "build.json").exists()


@pytest.mark.parametrize("name", ["ho4d", "DexYCB", ""])
def test_open_reader_refuses_an_unknown_name_before_reading_anything(tmp_path, name):
    """Fast tier: the name is checked before any file is opened (the folder here does not even exist)."""
    with pytest.raises(DataError, match="dataset.name") as err:
        open_reader(name, tmp_path / "absent", tmp_path / "mano", "train")
    assert len(str(err.value).splitlines()) == 1
