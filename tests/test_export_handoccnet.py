"""``hoidata export --format handoccnet``: the files HandOccNet's loaders open, read back as those loaders read them.

Loaders emulated (namepllet/HandOccNet): ``data/DEX_YCB/DEX_YCB.py`` and ``data/HO3D/HO3D.py``, classes ``DEX_YCB``
/ ``HO3D``, ``load_data`` and the start of ``__getitem__``, with pycocotools' ``COCO`` and the box functions of
``common/utils/preprocessing.py`` (``get_bbox``, ``process_bbox`` with its squaring to the 256x256 input). The
files are checked field by field against the raw toy files as the writer the loaders come with
(``data_parsing/DEX_YCB.py`` / ``data_parsing/HO3D.py`` at 495aa16) computes them, and against our records.
"""

from __future__ import annotations

import json
import pickle
import shutil

import cv2
import numpy as np
import pytest
import torch
import yaml
from pycocotools.coco import COCO

from hoidata.datasets.dexycb import DexYCBReader
from hoidata.datasets.dexycb_layout import SERIALS, SUBJECTS
from hoidata.errors import DataError
from hoidata.export import export_dataset
from hoidata.hand import load_mano, mean_relative_to_flat
from hoidata.records.settings import load_build_config

pytestmark = pytest.mark.slow  # exports the toy DexYCB s0 and HO-3D trees

HO3D_TO_DEXYCB = [0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20]  # jointsMapManoToSimple


def get_bbox(joint_img, expansion=1.5):
    x, y = joint_img[:, 0], joint_img[:, 1]
    xc, w, yc, h = (min(x) + max(x)) / 2.0, (max(x) - min(x)) * expansion, (min(y) + max(y)) / 2.0, (max(y) - min(y)) * expansion
    return np.array([xc - 0.5 * w, yc - 0.5 * h, w, h]).astype(np.float32)


def process_bbox(bbox, width, height, expansion=1.25):
    x, y, w, h = bbox
    x1, y1 = np.max((0, x)), np.max((0, y))
    x2, y2 = np.min((width - 1, x1 + np.max((0, w - 1)))), np.min((height - 1, y1 + np.max((0, h - 1))))
    if not (w * h > 0 and x2 >= x1 and y2 >= y1):
        return None
    w, h = x2 - x1, y2 - y1
    cx, cy = x1 + w / 2.0, y1 + h / 2.0
    w = h = max(w, h)  # cfg.input_img_shape (256, 256): aspect ratio 1
    return np.array([cx - w * expansion / 2.0, cy - h * expansion / 2.0, w * expansion, h * expansion])


def toolkit_ids(root, split):
    """The toolkit's s0 enumeration: (subject, sequence, serial, frame) -> index."""
    ids, n = {}, 0
    for s in {"train": range(10), "test": range(2, 10)}[split]:
        folder = root / SUBJECTS[s]
        if not folder.is_dir():
            continue
        for i, seq in enumerate(sorted(p.name for p in folder.iterdir() if p.is_dir())):
            if (i % 5 != 4) == (split == "train"):
                frames = yaml.safe_load((folder / seq / "meta.yml").read_text())["num_frames"]
                for serial in SERIALS:
                    for f in range(frames):
                        ids[n], n = (SUBJECTS[s], seq, serial, f), n + 1
    return ids


@pytest.fixture(scope="module")
def dex_export(dexycb_s0, tmp_path_factory):
    out = tmp_path_factory.mktemp("handoccnet") / "DEX_YCB" / "data"
    cfg = load_build_config("dexycb_full", ["dataset.complete_subjects=false"])
    summary = export_dataset("handoccnet", cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", out, progress=False)
    return out, summary, cfg


def load_dexycb(root_dir, data_split):
    """DEX_YCB.load_data (+ the flips of __getitem__) as the loader does it; returns its datalist."""
    db = COCO(str(root_dir / "annotations" / f"DEX_YCB_s0_{data_split}_data.json"))
    datalist = []
    for aid in db.anns.keys():
        ann = db.anns[aid]
        img = db.loadImgs(ann["image_id"])[0]
        img_path = root_dir / img["file_name"]
        joints_coord_cam = np.array(ann["joints_coord_cam"], dtype=np.float32)
        cam_param = {k: np.array(v, dtype=np.float32) for k, v in ann["cam_param"].items()}
        joints_img = np.array(ann["joints_img"], dtype=np.float32)
        bbox = process_bbox(get_bbox(joints_img[:, :2]), img["width"], img["height"], expansion=1.0)
        if data_split == "train" and bbox is None:
            continue
        data = {"id": aid, "img_path": img_path, "shape": (img["height"], img["width"]), "cam": joints_coord_cam,
                "cam_param": cam_param, "joints_img": joints_img, "hand_type": ann["hand_type"], "bbox": bbox}
        if data_split == "train":
            data["pose"] = np.array(ann["mano_param"]["pose"], dtype=np.float32)
            data["shape_params"] = np.array(ann["mano_param"]["shape"], dtype=np.float32)
            pose = data["pose"].reshape(-1, 3).copy()
            if ann["hand_type"] == "left":
                pose[:, 1:] *= -1
            cv2.Rodrigues(pose[0])  # the root pose goes through Rodrigues for the rotation augmentation
        datalist.append(data)
    return datalist


def test_dexycb_files_are_where_handoccnet_looks(dex_export):
    out, summary, _ = dex_export
    assert summary.finished and summary.written == summary.items > 0
    names = sorted(p.name for p in (out / "annotations").iterdir())
    assert names == ["DEX_YCB_s0_test_data.json", "DEX_YCB_s0_train_data.json", "DEX_YCB_s0_val_data.json"]
    assert (out / "annotations" / "DEX_YCB_s0_val_data.json").read_bytes() == \
        (out / "annotations" / "DEX_YCB_s0_test_data.json").read_bytes()  # the name HandOccNet's HEAD opens
    for split in ("train", "val"):
        data = load_dexycb(out, split)
        assert data
        for d in data:
            img = cv2.imread(str(d["img_path"]))  # load_img raises IOError when this is None
            assert img is not None and img.shape[:2] == d["shape"] == (480, 640)
            assert d["cam"].shape == (21, 3) and d["joints_img"].shape == (21, 2)
            assert all(v.shape == (2,) for v in d["cam_param"].values()) and d["hand_type"] in ("right", "left")
            if split == "train":
                assert d["pose"].shape == (48,) and d["shape_params"].shape == (10,)
    hands = {d["hand_type"] for d in load_dexycb(out, "train")}
    assert hands == {"right", "left"}


def test_dexycb_fields_follow_handoccnets_writer(dex_export, dexycb_s0):
    out, _, cfg = dex_export
    comps = {side: load_mano(dexycb_s0 / "mano", side=side, dtype=torch.float64).hands_components.numpy()
             for side in ("right", "left")}
    for split in ("train", "test"):
        doc = json.loads((out / "annotations" / f"DEX_YCB_s0_{split}_data.json").read_text())
        assert set(doc) == {"images", "annotations"}
        ids = toolkit_ids(dexycb_s0, split)
        images = {im["id"]: im for im in doc["images"]}
        for ann in doc["annotations"]:
            subject, seq, serial, f = ids[ann["id"]]  # image id = toolkit sample index
            assert ann["image_id"] == ann["id"]
            assert images[ann["id"]] == {"id": ann["id"], "file_name": f"{subject}/{seq}/{serial}/color_{f:06d}.jpg",
                                         "width": 640, "height": 480}
            folder = dexycb_s0 / subject / seq
            lab = np.load(folder / serial / f"labels_{f:06d}.npz")
            meta = yaml.safe_load((folder / "meta.yml").read_text())
            intr = yaml.safe_load((dexycb_s0 / "calibration" / "intrinsics" / f"{serial}_640x480.yml").read_text())["color"]
            betas = yaml.safe_load((dexycb_s0 / "calibration" / f"mano_{meta['mano_calib'][0]}" / "mano.yml").read_text())
            side = meta["mano_sides"][0]
            assert ann["joints_coord_cam"] == lab["joint_3d"][0].tolist()
            assert ann["joints_img"] == lab["joint_2d"][0].tolist()
            assert ann["cam_param"] == {"focal": [intr["fx"], intr["fy"]], "princpt": [intr["ppx"], intr["ppy"]]}
            assert ann["hand_type"] == side and ann["mano_param"]["shape"] == betas["betas"]
            pose_m = lab["pose_m"][0].astype(np.float64)
            want = np.concatenate([pose_m[:3], pose_m[3:48] @ comps[side]])  # PCA -> axis-angle, no hands_mean
            np.testing.assert_allclose(ann["mano_param"]["pose"], want, rtol=0, atol=1e-9)
        n_valid = sum(1 for (sub, seq, ser, f) in ids.values()
                      if (dexycb_s0 / sub / seq / ser / f"labels_{f:06d}.npz").is_file()
                      and not np.all(np.load(dexycb_s0 / sub / seq / ser / f"labels_{f:06d}.npz")["joint_3d"] == -1))
        assert len(doc["annotations"]) == n_valid  # every annotated frame (the toy's boxes all pass)


def test_dexycb_pose_convention_against_our_records(dex_export, dexycb_s0):
    """The mean-relative pose, with hands_mean added as the loaders' flat_hand_mean=False layer does, is our
    pose, and MANO gives the annotated joints with it."""
    out, _, cfg = dex_export
    doc = json.loads((out / "annotations" / "DEX_YCB_s0_train_data.json").read_text())
    anns = {a["id"]: a for a in doc["annotations"]}
    frames = list(DexYCBReader(dexycb_s0, dexycb_s0 / "mano", "train", cfg.dataset.dexycb_setting()).frames())
    assert sorted(anns) == sorted(f.sample_index for f in frames)
    for frame in frames[::3]:
        ann = anns[frame.sample_index]
        mano = load_mano(dexycb_s0 / "mano", side=frame.side, fix_left_shapedirs=frame.side == "right", dtype=torch.float64)
        pose = mean_relative_to_flat(np.asarray(ann["mano_param"]["pose"]), mano.hands_mean.double().numpy())
        np.testing.assert_allclose(pose, frame.mano_pose, atol=1e-9)
        np.testing.assert_allclose(ann["joints_coord_cam"], frame.joints_3d, atol=0)
        with torch.no_grad():
            joints = mano(torch.as_tensor(pose)[None], torch.as_tensor(ann["mano_param"]["shape"])[None],
                          torch.as_tensor(frame.mano_transl)[None]).joints[0].numpy()
        np.testing.assert_allclose(joints, ann["joints_coord_cam"], atol=2e-5)


def test_ho3d_files_follow_handoccnet(ho3d_small, tmp_path):
    out = tmp_path / "HO3D" / "data"
    cfg = load_build_config("ho3d")
    summary = export_dataset("handoccnet", cfg, ho3d_small, ho3d_small / "mano", ho3d_small / "models", out,
                             progress=False)
    assert summary.finished and sorted(summary.files) == ["annotations/HO3D_evaluation_data.json",
                                                          "annotations/HO3D_train_data.json"]
    mean = load_mano(ho3d_small / "mano", dtype=torch.float64).hands_mean.numpy()
    flip = np.array([1.0, -1.0, -1.0])
    for split in ("train", "evaluation"):
        lines = (ho3d_small / f"{split}.txt").read_text().split()
        db = COCO(str(out / "annotations" / f"HO3D_{split}_data.json"))  # HO3D.load_data
        assert list(db.anns.keys()) == list(range(len(lines)))  # evaluation.txt order: predictions are dumped so
        for aid in db.anns.keys():
            ann, img = db.anns[aid], db.loadImgs(db.anns[aid]["image_id"])[0]
            seq, fid = lines[aid].split("/")
            assert img["file_name"] == f"{seq}/rgb/{fid}.png" and (out / split / img["file_name"]).is_file()
            with open(ho3d_small / split / seq / "meta" / f"{fid}.pkl", "rb") as f:
                meta = pickle.load(f, encoding="latin1")
            cam = {k: np.array(v, dtype=np.float32) for k, v in ann["cam_param"].items()}
            K = meta["camMat"]
            assert ann["cam_param"] == {"focal": [K[0, 0], K[1, 1]], "princpt": [K[0, 2], K[1, 2]]}
            if split == "train":
                joints = np.array(ann["joints_coord_cam"], dtype=np.float32)
                uv = joints[:, :2] / joints[:, 2:] * cam["focal"] + cam["princpt"]  # cam2pixel
                assert process_bbox(get_bbox(uv), img["width"], img["height"], expansion=1.0) is not None
                np.testing.assert_allclose(ann["joints_coord_cam"], (meta["handJoints3D"] * flip)[HO3D_TO_DEXYCB], atol=1e-12)
                root, _ = cv2.Rodrigues(np.diag(flip) @ cv2.Rodrigues(meta["handPose"][:3].astype(np.float64))[0])
                want = np.concatenate([root.ravel(), meta["handPose"][3:] - mean])
                np.testing.assert_allclose(ann["mano_param"]["pose"], want, atol=1e-9)
                assert ann["mano_param"]["shape"] == meta["handBeta"].tolist()
                assert "joints_img" not in ann and "hand_type" not in ann
            else:
                np.testing.assert_allclose(ann["root_joint_cam"], meta["handJoints3D"] * flip, atol=1e-12)
                x1, y1, x2, y2 = meta["handBoundingBox"]
                np.testing.assert_allclose(ann["bbox"], [x1, y1, x2 - x1, y2 - y1], atol=1e-9)
                assert process_bbox(np.array(ann["bbox"], dtype=np.float32), 640, 480, expansion=1.5) is not None
    assert (out / "train").resolve() == (ho3d_small / "train").resolve()


def test_parts_resume_and_settings_guard(dex_export, dexycb_s0, tmp_path):
    out, summary, cfg = dex_export
    files = {p: (out / p).read_bytes() for p in ("annotations/DEX_YCB_s0_train_data.json",
                                                 "annotations/DEX_YCB_s0_test_data.json")}
    split = tmp_path / "parts"
    kw = dict(progress=False, chunk_size=16)
    first = export_dataset("handoccnet", cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", split, part=(0, 2), **kw)
    assert not first.finished and not (split / "annotations").exists()
    second = export_dataset("handoccnet", cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", split, part=(1, 2), **kw)
    assert second.finished and all((split / p).read_bytes() == b for p, b in files.items())
    manifests = sorted((split / ".hoidata-export" / "handoccnet-train-test").glob("chunk-*.json"))
    manifests[1].unlink()  # an interrupted run: one chunk missing
    (split / "annotations" / "DEX_YCB_s0_train_data.json").unlink()
    again = export_dataset("handoccnet", cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", split, **kw)
    assert (again.units_written, again.units_kept) == (1, len(manifests) - 1)
    assert all((split / p).read_bytes() == b for p, b in files.items())
    other = load_build_config("dexycb_grasping", ["dataset.complete_subjects=false"])
    with pytest.raises(DataError, match="other settings"):
        export_dataset("handoccnet", other, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", split, **kw)
    shutil.rmtree(split)


def test_the_export_command(dexycb_s0, ho3d_small, tmp_path, capsys):
    from hoidata.cli import main

    out = tmp_path / "data"
    argv = ["export", "--format", "handoccnet", "--dataset", "dexycb_full", "--root", str(dexycb_s0), "--out", str(out),
            "--splits", "test", "dataset.complete_subjects=false"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "frames exported as handoccnet" in printed and "annotation files written" in printed
    assert sorted(p.name for p in (out / "annotations").iterdir()) == ["DEX_YCB_s0_test_data.json",
                                                                       "DEX_YCB_s0_val_data.json"]
    assert main(["export", "--format", "gsdf", "--dataset", "ho3d", "--root", str(ho3d_small), "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == ("hoidata export: error: 'dataset.name': the gsdf format reads dexycb, "
                                               "not ho3d")
