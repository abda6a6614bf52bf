"""The field's DexYCB selections (pipelines/dexycb*.toml): stated counts, and each rule as its public code applies it.

The reference rules below are written in this test from the consumers' code, on the raw toy files (labels npz,
meta.yml, textured_simple.obj), independently of the reader:

- gSDF ``preprocess/cocoify_dexycb.py`` ``preprocess``: mano_side 'right', frame % 5 == 0, then a cKDTree on the
  778 MANO vertices queried with every posed object vertex; kept if the minimum is <= 0.005 m;
- HandOccNet ``data/DEX_YCB/DEX_YCB.py`` ``load_data`` / HOISDF ``data/dexycb.py``: ``get_bbox(joint_2d, 1.5)``
  then ``process_bbox`` (``common/utils/preprocessing.py``) must not return None;
- ArtiBoost ``anakin/datasets/dexycb.py`` ``DexYCB.load_dataset``: right hands, joint_2d not all -1,
  ``cdist(posed object vertices, joint_3d).min() * 1000 <= FILTER_THRESH``;
- UniHOPE ``data_creation/prepare_grasp_dexycb.py`` ``main``: ``inverse(pose_y) @ pose_y(labels_000000)``
  turned more than 5 degrees or moved more than 0.05 m.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh
import yaml
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from hoidata.datasets.dexycb import DexYCBReader
from hoidata.datasets.dexycb_layout import SERIALS, SUBJECTS
from hoidata.datasets.dexycb_selection import hand_box_ok, object_motion
from hoidata.hand import load_mano
from hoidata.objects import YCB_CLASSES
from hoidata import build_sdf as runner
from hoidata.records.settings import load_build_config, stated_count_warnings

STATED = {"dexycb": (29656, 5928), "dexycb_full": (401507, 78005), "dexycb_artiboost": (168280, 32968),
          "dexycb_grasping": (237256, 45624)}


def handoccnet_box(joint_img: np.ndarray, width=640, height=480):
    """HandOccNet's get_bbox(expansion 1.5) then process_bbox(expansion 1.0) up to its None test."""
    j = joint_img.astype(np.float32)
    xmin, ymin, xmax, ymax = min(j[:, 0]), min(j[:, 1]), max(j[:, 0]), max(j[:, 1])
    xc, w = (xmin + xmax) / 2.0, (xmax - xmin) * 1.5
    yc, h = (ymin + ymax) / 2.0, (ymax - ymin) * 1.5
    x, y, w, h = np.array([xc - 0.5 * w, yc - 0.5 * h, w, h]).astype(np.float32)
    x1, y1 = np.max((0, x)), np.max((0, y))
    x2 = np.min((width - 1, x1 + np.max((0, w - 1))))
    y2 = np.min((height - 1, y1 + np.max((0, h - 1))))
    return None if not (w * h > 0 and x2 >= x1 and y2 >= y1) else (x1, y1, x2 - x1, y2 - y1)


def test_presets_state_their_counts():
    for name, (train, test) in STATED.items():
        cfg = load_build_config(name)
        assert cfg.dataset.expected_frames == {"train": train, "test": test}
        assert cfg.dataset.setup == "s0" and cfg.dataset.splits == ("train", "test")
    artiboost = load_build_config("dexycb_artiboost").dataset
    assert (artiboost.sides, artiboost.proximity_mm, artiboost.proximity_to) == (("right",), 50.0, "hand_joints")
    grasping = load_build_config("dexycb_grasping").dataset
    assert (grasping.motion_deg, grasping.motion_m, grasping.box_splits) == (5.0, 0.05, ("train",))
    assert load_build_config("dexycb").dataset.box_splits == ()


def test_hand_box_rule_is_handoccnets():
    rng = np.random.default_rng(0)
    cases = [rng.uniform(-400, 1000, size=(21, 2)) * rng.uniform(0.01, 1.0) + rng.uniform(-600, 900, size=2)
             for _ in range(3000)]
    cases += [np.full((21, 2), 100.0), np.array([[-300.0, -200.0]] * 20 + [[-250.0, -150.0]]),  # degenerate; off top-left
              np.array([[700.0, 100.0]] * 20 + [[760.0, 200.0]]), np.array([[100.0, 500.0]] * 20 + [[200.0, 560.0]])]
    got = [hand_box_ok(c) for c in cases]
    want = [handoccnet_box(c) is not None for c in cases]
    assert got == want
    assert got[-4:] == [False, True, False, False]  # a box wholly above-left of the image passes, as in the loader
    assert 0.2 < np.mean(got) < 0.9


def test_object_motion_is_unihopes():
    rng = np.random.default_rng(1)
    for _ in range(20):
        R0, R = (trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3] for _ in range(2))
        first, pose = np.c_[R0, rng.normal(size=3)], np.c_[R, rng.normal(size=3)]
        inv = np.c_[R.T, -R.T @ pose[:, 3]]  # np_inverse, then np_concatenate(inv, first)
        rel_R, rel_t = inv[:, :3] @ R0, inv[:, :3] @ first[:, 3] + inv[:, 3]
        deg = np.arccos(np.clip(0.5 * (np.trace(rel_R) - 1), -1.0, 1.0)) * 180.0 / np.pi
        assert object_motion(pose, first) == pytest.approx((deg, np.linalg.norm(rel_t)), abs=1e-9)


def _raw_samples(root, split):
    """(subject, sequence, serial, frame, meta, labels) of every frame on disk in s0 <split> (toolkit order)."""
    subjects = {"train": range(10), "val": (0, 1), "test": range(2, 10)}[split]
    for s in subjects:
        folder = root / SUBJECTS[s]
        if not folder.is_dir():
            continue
        for i, seq in enumerate(sorted(p.name for p in folder.iterdir() if p.is_dir())):
            if (i % 5 != 4) != (split == "train"):
                continue
            meta = yaml.safe_load((folder / seq / "meta.yml").read_text())
            for serial in SERIALS:
                for f in range(meta["num_frames"]):
                    path = folder / seq / serial / f"labels_{f:06d}.npz"
                    if path.is_file():
                        yield SUBJECTS[s], seq, serial, f, meta, dict(np.load(path))


def _reference(root, split, rule, **kw) -> set:
    mano = {side: load_mano(root / "mano", side=side, fix_left_shapedirs=side == "right", dtype=torch.float64)
            for side in ("right", "left")}
    kept = set()
    for subject, seq, serial, f, meta, lab in _raw_samples(root, split):
        side, grasp = meta["mano_sides"][0], meta["ycb_grasp_ind"]
        if np.all(lab["joint_3d"] == -1) and np.all(lab["joint_2d"] == -1) and not np.any(lab["pose_m"]):
            continue  # HandOccNet's parse_data skip; the toy marks all three at once
        name = YCB_CLASSES[meta["ycb_ids"][grasp]]
        mesh = trimesh.load(root / "models" / name / "textured_simple.obj", process=False)
        rt = lab["pose_y"][grasp].astype(np.float64)
        obj = np.asarray(mesh.vertices) @ rt[:, :3].T + rt[:, 3]
        if rule(side=side, frame=f, lab=lab, obj=obj, mano=mano[side], betas=_betas(root, meta), rt=rt,
                first=np.load(root / subject / seq / serial / "labels_000000.npz")["pose_y"][grasp], split=split, **kw):
            kept.add((subject, seq, serial, f))
    return kept


def _betas(root, meta):
    return yaml.safe_load((root / "calibration" / f"mano_{meta['mano_calib'][0]}" / "mano.yml").read_text())["betas"]


def gsdf_rule(side, frame, lab, obj, mano, betas, **_):
    if side != "right" or frame % 5 != 0:
        return False
    pose = np.asarray(lab["pose_m"][0], np.float64)
    full = np.concatenate([pose[:3], mano.hands_mean.double().numpy() + pose[3:48] @ mano.hands_components.double().numpy()])
    with torch.no_grad():
        verts = mano(torch.as_tensor(full)[None], torch.as_tensor(betas, dtype=torch.float64)[None],
                     torch.as_tensor(pose[48:51])[None]).vertices[0].numpy()
    return cKDTree(verts).query(obj)[0].min() <= 0.005


def handoccnet_rule(lab, split, box_splits=("train", "val", "test"), **_):
    return split not in box_splits or handoccnet_box(lab["joint_2d"][0]) is not None


def artiboost_rule(side, lab, obj, thresh=50.0, **_):
    if side == "left" or np.all(lab["joint_2d"] == -1.0):
        return False
    return not cdist(obj, lab["joint_3d"][0]).min() * 1000.0 > thresh


def grasping_rule(lab, rt, first, split, **_):
    deg, metres = object_motion(rt, first.astype(np.float64))
    return handoccnet_rule(lab, split, box_splits=("train",)) and (deg > 5 or metres > 0.05)


CASES = [("dexycb", [], gsdf_rule, {}), ("dexycb_full", [], handoccnet_rule, {}),
         ("dexycb_artiboost", [], artiboost_rule, {}),
         ("dexycb_artiboost", ["dataset.proximity_mm=4.0"], artiboost_rule, {"thresh": 4.0}),  # the toy joints lie close
         ("dexycb_grasping", [], grasping_rule, {})]


@pytest.mark.slow
@pytest.mark.parametrize("preset,overrides,rule,kw", CASES, ids=[f"{c[0]}{'-' + c[1][0] if c[1] else ''}" for c in CASES])
def test_presets_select_what_their_rules_say(dexycb_s0, preset, overrides, rule, kw):
    dataset = load_build_config(preset, ["dataset.complete_subjects=false", *overrides]).dataset
    picked, total = {}, 0
    for split in ("train", "test"):
        reader = DexYCBReader(dexycb_s0, dexycb_s0 / "mano", split, dataset.dexycb_setting())
        picked[split] = {(f.source["subject"], f.source["sequence"], f.source["serial"], f.source["frame"])
                         for f in reader.frames()}
        assert picked[split] == _reference(dexycb_s0, split, rule, **kw)
        total += len(picked[split])
    candidates = sum(1 for split in ("train", "test") for _ in _raw_samples(dexycb_s0, split))
    assert picked["test"] and 0 < total < candidates  # the rule does select on the toy, it is not all or nothing
    if kw.get("thresh", 50.0) < 50.0:  # the distance to the joints bites: fewer than with no distance limit
        loose = sum(len(_reference(dexycb_s0, split, rule, thresh=np.inf)) for split in ("train", "test"))
        assert total < loose


@pytest.mark.slow
def test_a_complete_build_warns_when_its_count_differs(dexycb_s0, monkeypatch, capsys):
    cfg = load_build_config("dexycb_full")
    assert stated_count_warnings(cfg.dataset, ["train"] * 401507 + ["test"] * 78005) == []
    lines = stated_count_warnings(cfg.dataset, ["train"] * 401507 + ["test"] * 78004)
    assert lines == ["hoidata: warning: setting 'dexycb_full' selected 78004 test frames; its pipeline TOML states "
                     "78005 for the full dataset"]
    assert stated_count_warnings(replace(cfg.dataset, complete_subjects=False), ["test"]) == []  # not a full read

    class Stop(Exception):
        pass

    frames, _ = runner.read_frames(load_build_config("dexycb_full", ["dataset.complete_subjects=false"]), dexycb_s0,
                                   dexycb_s0 / "mano")
    monkeypatch.setattr(runner, "read_frames", lambda *a, **k: (frames, []))
    monkeypatch.setattr(runner.StoreWriter, "pin", lambda *a, **k: (_ for _ in ()).throw(Stop()))
    with pytest.raises(Stop):
        runner.build_store(cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", dexycb_s0 / "unused")
    err = capsys.readouterr().err.splitlines()
    n_train = sum(f.split == "train" for f in frames)
    assert err == [f"hoidata: warning: setting 'dexycb_full' selected {n_train} train frames; its pipeline TOML "
                   "states 401507 for the full dataset",
                   f"hoidata: warning: setting 'dexycb_full' selected {len(frames) - n_train} test frames; its "
                   "pipeline TOML states 78005 for the full dataset"]
