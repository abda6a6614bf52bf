"""``hoidata export --format gsdf``: gSDF's DexYCB files and AlignSDF's SDF files, read back as gSDF reads them.

Loaders emulated (zerchen/gSDF): ``datasets/dexycb/dexycb.py`` class ``dexycb`` (``__init__``, ``load_data``: the
split list, the COCO file, every annotation key, the paths rebuilt from ``file_name``) and
``datasets/sdf_dataset.py`` class ``SDFDataset`` (``unpack_sdf`` and the normalisation of ``__getitem__``). The
annotation is checked field by field against ``preprocess/cocoify_dexycb.py`` ``preprocess`` applied to the raw toy
files; SDF values against distances recomputed from the meshes by the brute-force reference.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh
import yaml
from pycocotools.coco import COCO

from hoidata.datasets.dexycb_layout import SUBJECTS
from hoidata.export import export_dataset
from hoidata.export.sdf_files import normalisation
from hoidata.geometry.sdf import brute_force_signed_distance
from hoidata.hand import load_mano
from hoidata.objects import YCB_CLASSES, load_object_mesh, object_mesh_path, repair_mesh
from hoidata.records.settings import load_build_config

pytestmark = pytest.mark.slow  # exports the toy DexYCB s0 split (rendered toy data, SDF files)

KEYS = ("fx", "fy", "cx", "cy", "bbox", "hand_joints_3d", "hand_poses", "hand_shapes", "hand_trans", "obj_transform",
        "obj_corners_3d", "obj_rest_corners_3d", "obj_center_3d", "ycb_id")
SHAPES = {"hand_joints_3d": (21, 3), "hand_poses": (48,), "hand_shapes": (10,), "hand_trans": (3,),
          "obj_transform": (4, 4), "obj_corners_3d": (8, 3), "obj_rest_corners_3d": (8, 3), "obj_center_3d": (3,)}


@pytest.fixture(scope="module")
def gsdf_export(dexycb_s0, tmp_path_factory):
    out = tmp_path_factory.mktemp("gsdf") / "dexycb"
    cfg = load_build_config("dexycb", ["dataset.complete_subjects=false"])
    summary = export_dataset("gsdf", cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", out, progress=False)
    return out, summary


def load_gsdf(cur_dir, data_split):
    """dexycb.__init__ + load_data: the samples gSDF builds from our files."""
    stage_split = "_".join(data_split.split("_")[:-1])
    split = [int(idx) for idx in json.loads((cur_dir / "splits" / f"{data_split}.json").read_text())]
    db = COCO(str(cur_dir / f"dexycb_{stage_split}.json"))
    samples = []
    for aid in split:
        ann = db.anns[aid]
        name = db.loadImgs(ann["image_id"])[0]["file_name"]
        s = {"id": name, "aid": aid, "subject_id": SUBJECTS[int(name.split("_")[0]) - 1],
             "video_id": "_".join(name.split("_")[1:3]), "cam_id": name.split("_")[-2],
             "frame_id": name.split("_")[-1].rjust(6, "0")}
        folder = cur_dir / "data" / s["subject_id"] / s["video_id"] / s["cam_id"]
        s["img_path"], s["seg_path"] = folder / f"color_{s['frame_id']}.jpg", folder / f"labels_{s['frame_id']}.npz"
        for key in KEYS:
            s[key] = np.array(ann[key], dtype=np.float32) if key in SHAPES else ann[key]
        if "train" in stage_split:
            s["sdf_hand_path"] = cur_dir / "data" / "sdf_data" / "sdf_hand" / f"{name}.npz"
            s["sdf_obj_path"] = cur_dir / "data" / "sdf_data" / "sdf_obj" / f"{name}.npz"
            s["sdf_scale"] = np.array(ann["sdf_scale"], dtype=np.float32)
            s["sdf_offset"] = np.array(ann["sdf_offset"], dtype=np.float32)
        samples.append(s)
    return samples


def unpack_sdf(path, subsample, hand, clamp=0.05):
    """SDFDataset.unpack_sdf with filter_dist=True: (samples (subsample, 5), labels (subsample,))."""
    npz = np.load(path)
    pos, neg = torch.from_numpy(npz["pos"]), torch.from_numpy(npz["neg"])
    pos, neg = pos[~torch.isnan(pos[:, 3])], neg[~torch.isnan(neg[:, 3])]
    pos_other, neg_other = torch.from_numpy(npz["pos_other"]), torch.from_numpy(npz["neg_other"])
    lab_pos = torch.from_numpy(npz["lab_pos" if hand else "lab_pos_other"])
    lab_neg = torch.from_numpy(npz["lab_neg" if hand else "lab_neg_other"])
    if hand:
        pos, neg = torch.cat([pos, pos_other], 1), torch.cat([neg, neg_other], 1)
    else:
        pos = torch.cat([pos[:, :3], pos_other, pos[:, 3].unsqueeze(1)], 1)
        neg = torch.cat([neg[:, :3], neg_other, neg[:, 3].unsqueeze(1)], 1)
    keep_p = (torch.abs(pos[:, 3]) < 2.0) & (torch.abs(pos[:, 4]) < 2.0)
    keep_n = (torch.abs(neg[:, 3]) < 2.0) & (torch.abs(neg[:, 4]) < 2.0)
    pos, lab_pos, neg, lab_neg = pos[keep_p], lab_pos[keep_p], neg[keep_n], lab_neg[keep_n]
    half = subsample // 2
    rp, rn = (torch.rand(half) * pos.shape[0]).long(), (torch.rand(half) * neg.shape[0]).long()
    samples = torch.cat([torch.index_select(pos, 0, rp), torch.index_select(neg, 0, rn)], 0)
    labels = torch.cat([torch.index_select(lab_pos, 0, rp)[:, 0], torch.index_select(lab_neg, 0, rn)[:, 0]], 0)
    labels[samples[:, 3] < -clamp] = -1
    labels[samples[:, 3] > clamp] = -1
    if not hand:
        labels[:] = -1
    return samples, labels


def _splits(out, summary):
    names = sorted(p.stem for p in (out / "splits").iterdir())
    assert len(names) == 2 and all(n.endswith(f"_{len(json.loads((out / 'splits' / (n + '.json')).read_text())) // 1000}k")
                                   for n in names)
    return {n.split("_")[0]: n for n in names}


def test_gsdf_reads_every_sample(gsdf_export):
    out, summary = gsdf_export
    assert summary.finished and summary.written > 0 and summary.extra["sdf_sources"] == {"sampled": len(
        json.loads((out / "splits" / (_splits(out, summary)["train"] + ".json")).read_text()))}
    torch.manual_seed(0)
    for split, data_split in _splits(out, summary).items():
        samples = load_gsdf(out, data_split)
        assert samples
        for s in samples:
            assert s["img_path"].is_file() and s["seg_path"].is_file()
            assert all(s[k].shape == shape for k, shape in SHAPES.items()) and len(s["bbox"]) == 4
            if split == "test":
                assert "sdf_hand_path" not in s
                stem = s["id"] + ".obj"
                hand = trimesh.load(out / "data" / "mesh_data" / "mesh_hand" / stem, process=False)
                obj = trimesh.load(out / "data" / "mesh_data" / "mesh_obj" / stem, process=False)
                assert hand.is_watertight and len(obj.faces) > 0
                continue
            assert s["sdf_scale"].shape == (1,) and s["sdf_offset"].shape == (3,)
            for path, hand in ((s["sdf_hand_path"], True), (s["sdf_obj_path"], False)):
                samples_, labels = unpack_sdf(path, 1000, hand)
                assert samples_.shape == (1000, 5) and torch.isfinite(samples_).all()
                xyz = samples_[:, :3] / torch.from_numpy(s["sdf_scale"]) - torch.from_numpy(s["sdf_offset"])
                assert torch.linalg.norm(xyz - torch.from_numpy(s["hand_joints_3d"][0]), dim=1).max() < 1.0
                if hand:
                    assert (labels >= -1).all() and (labels <= 5).all() and (labels >= 0).any()
                else:
                    assert (labels == -1).all()


def _raw(root, name):
    subject, date, time_, serial, frame = name.split("_")
    folder = root / SUBJECTS[int(subject) - 1] / f"{date}_{time_}"
    meta = yaml.safe_load((folder / "meta.yml").read_text())
    lab = np.load(folder / serial / f"labels_{int(frame):06d}.npz")
    intr = yaml.safe_load((root / "calibration" / "intrinsics" / f"{serial}_640x480.yml").read_text())["color"]
    betas = yaml.safe_load((root / "calibration" / f"mano_{meta['mano_calib'][0]}" / "mano.yml").read_text())["betas"]
    return meta, lab, intr, betas


def test_gsdf_fields_follow_its_preprocess(gsdf_export, dexycb_s0):
    """The annotation as cocoify_dexycb.preprocess computes it from the raw files (manopth's th_full_pose, the
    bounding-box-centred object frame of trimesh's bounds, the padded, squared, x1.25 box)."""
    out, summary = gsdf_export
    mano = load_mano(dexycb_s0 / "mano", dtype=torch.float64)
    comps, mean = mano.hands_components.numpy(), mano.hands_mean.numpy()
    for split, data_split in _splits(out, summary).items():
        doc = json.loads((out / f"dexycb_{split}_s0.json").read_text())
        ids = json.loads((out / "splits" / f"{data_split}.json").read_text())
        assert ids == sorted(ids) and all(len(i) == 8 for i in ids)
        assert [int(i) for i in ids] == sorted(a["id"] for a in doc["annotations"])
        names = {im["id"]: im["file_name"] for im in doc["images"]}
        for ann in doc["annotations"]:
            meta, lab, intr, betas = _raw(dexycb_s0, names[ann["id"]])
            assert meta["mano_sides"][0] == "right" and int(names[ann["id"]].split("_")[-1]) % 5 == 0
            assert [ann[k] for k in ("fx", "fy", "cx", "cy")] == [intr[k] for k in ("fx", "fy", "ppx", "ppy")]
            pose_m = lab["pose_m"][0].astype(np.float64)
            np.testing.assert_allclose(ann["hand_poses"], np.concatenate([pose_m[:3], mean + pose_m[3:48] @ comps]), atol=1e-9)
            assert ann["hand_trans"] == lab["pose_m"][0, 48:].tolist() and ann["hand_shapes"] == betas
            assert ann["hand_joints_3d"] == lab["joint_3d"][0].tolist()
            grasp = meta["ycb_grasp_ind"]
            assert ann["ycb_id"] == meta["ycb_ids"][grasp]
            mesh = trimesh.load(dexycb_s0 / "models" / YCB_CLASSES[ann["ycb_id"]] / "textured_simple.obj", process=False)
            offset = (mesh.vertices.min(0) + mesh.vertices.max(0)) / 2
            rest = trimesh.bounds.corners(mesh.bounds) - offset
            R, t = lab["pose_y"][grasp][:3, :3].astype(np.float64), lab["pose_y"][grasp][:, 3:].astype(np.float64)
            new_t = R @ offset.reshape(3, 1) + t
            corners = (R @ rest.T + new_t).T
            np.testing.assert_allclose(ann["obj_transform"], np.r_[np.c_[R, new_t], [[0, 0, 0, 1]]], atol=1e-12)
            np.testing.assert_allclose(ann["obj_center_3d"], new_t[:, 0], atol=1e-12)
            np.testing.assert_allclose(ann["obj_corners_3d"], corners, atol=1e-12)
            np.testing.assert_allclose(ann["obj_rest_corners_3d"], rest, atol=1e-12)
            uv = np.c_[intr["fx"] * corners[:, 0] / corners[:, 2] + intr["ppx"], intr["fy"] * corners[:, 1] / corners[:, 2] + intr["ppy"]]
            pts = np.concatenate([lab["joint_2d"][0], uv])
            tl, br = pts.min(0), pts.max(0)
            x, y, w, h = np.concatenate([tl - 10, br - tl + 20])
            side = max(w, h)
            np.testing.assert_allclose(ann["bbox"], [x + w / 2 - side * 0.625, y + h / 2 - side * 0.625,
                                                     side * 1.25, side * 1.25], atol=1e-9)
            assert ("sdf_scale" in ann) == (split == "train")


def _meshes(root, ann, mano):
    """The frame's closed hand (MANO from the annotation) and repaired object (posed by pose_y), camera frame."""
    with torch.no_grad():
        out = mano(torch.tensor(ann["hand_poses"])[None], torch.tensor(ann["hand_shapes"])[None],
                   torch.tensor(ann["hand_trans"])[None])
        hand = mano.close(out.vertices)[0].numpy()
    repaired, _ = repair_mesh(load_object_mesh(object_mesh_path(root / "models", YCB_CLASSES[ann["ycb_id"]])))
    T = np.array(ann["obj_transform"])
    mesh = trimesh.load(root / "models" / YCB_CLASSES[ann["ycb_id"]] / "textured_simple.obj", process=False)
    centre = (mesh.vertices.min(0) + mesh.vertices.max(0)) / 2
    t = T[:3, 3] - T[:3, :3] @ centre  # back to the model -> camera pose_y
    return hand, mano.closed_faces, np.asarray(repaired.vertices) @ T[:3, :3].T + t, np.asarray(repaired.faces)


def test_gsdf_sdf_values_and_normalisation(gsdf_export, dexycb_s0):
    out, summary = gsdf_export
    mano = load_mano(dexycb_s0 / "mano", dtype=torch.float64)
    doc = json.loads((out / "dexycb_train_s0.json").read_text())
    names = {im["id"]: im["file_name"] for im in doc["images"]}
    rng = np.random.default_rng(0)
    for ann in doc["annotations"][:2]:
        hand, hand_faces, obj, obj_faces = _meshes(dexycb_s0, ann, mano)
        norm = np.load(out / "data" / "sdf_data" / "norm" / f"{names[ann['id']]}.npz")
        assert norm["offset"].dtype == norm["scale"].dtype == np.float32
        assert norm["offset"].shape == (3,) and norm["scale"].shape == (1,)
        assert ann["sdf_scale"] == norm["scale"].tolist() and ann["sdf_offset"] == norm["offset"].tolist()
        verts = np.concatenate([hand, obj])
        centre = (verts.min(0) + verts.max(0)) / 2  # PreprocessMesh: union box centre, 1.03 x farthest vertex
        np.testing.assert_allclose(-norm["offset"], centre, atol=1e-7)
        np.testing.assert_allclose(1 / norm["scale"][0], np.linalg.norm(verts - centre, axis=1).max() * 1.03, rtol=1e-6)
        offset, scale = normalisation(hand, obj)
        assert offset.tobytes() == norm["offset"].tobytes() and scale.tobytes() == norm["scale"].tobytes()
        for branch in ("sdf_hand", "sdf_obj"):
            npz = np.load(out / "data" / "sdf_data" / branch / f"{names[ann['id']]}.npz")
            assert {k: npz[k].dtype for k in npz.files} == {
                "pos": np.float32, "neg": np.float32, "pos_other": np.float32, "neg_other": np.float32,
                "lab_pos": np.int32, "lab_neg": np.int32, "lab_pos_other": np.int32, "lab_neg_other": np.int32}
            assert len(npz["pos"]) + len(npz["neg"]) == 20000 and npz["pos_other"].shape == (len(npz["pos"]), 1)
            assert (npz["pos"][:, 3] > 0).all() and (npz["neg"][:, 3] <= 0).all()  # split by the own distance's sign
            rows = np.concatenate([np.c_[npz["pos"], npz["pos_other"]], np.c_[npz["neg"], npz["neg_other"]]])
            pick = rows[rng.choice(len(rows), 12, replace=False)]
            xyz = pick[:, :3] / norm["scale"] - norm["offset"]  # the loaders' camera-frame point
            metric = pick[:, 3:] / norm["scale"]
            want_h = brute_force_signed_distance(xyz, hand, hand_faces)[0]
            want_o = brute_force_signed_distance(xyz, obj, obj_faces)[0]
            own, other = (want_h, want_o) if branch == "sdf_hand" else (want_o, want_h)
            np.testing.assert_allclose(metric[:, 0], own, atol=2e-6)
            np.testing.assert_allclose(metric[:, 1], other, atol=2e-6)
        labels = np.concatenate([npz["lab_pos_other"], npz["lab_neg_other"]])  # object file: nearest hand part
        assert ((labels[:, 0] == 0) == (labels[:, 1] == 0)).all()
        finger = labels[:, 0] > 0
        assert (labels[finger, 0] == (labels[finger, 1] - 1) // 3 + 1).all() and set(np.unique(labels[:, 3])) <= {0, 1}


def test_gsdf_part_labels_name_alignsdf_parts(gsdf_export, dexycb_s0):
    """Points next to the thumb tip (vertex 745) carry AlignSDF's thumb-distal labels: coarse 1, fine 1."""
    out, _ = gsdf_export
    mano = load_mano(dexycb_s0 / "mano", dtype=torch.float64)
    doc = json.loads((out / "dexycb_train_s0.json").read_text())
    ann, name = doc["annotations"][0], doc["images"][0]["file_name"]
    hand = _meshes(dexycb_s0, ann, mano)[0]
    npz, norm = (np.load(out / "data" / "sdf_data" / b / f"{name}.npz") for b in ("sdf_hand", "norm"))
    xyz = np.concatenate([npz["pos"], npz["neg"]])[:, :3] / norm["scale"] - norm["offset"]
    labels = np.concatenate([npz["lab_pos"], npz["lab_neg"]])
    for vertex, coarse, fine in ((745, 1, 1), (317, 2, 4), (673, 5, 13)):  # thumb, index, little fingertips
        near = np.linalg.norm(xyz - hand[vertex], axis=1) < 0.005
        assert near.sum() >= 5
        assert np.mean((labels[near, 0] == coarse) & (labels[near, 1] == fine)) > 0.8


def test_gsdf_reuses_store_rows(tiny_dexycb, tiny_store, tmp_path):
    from hoidata import schema, store

    cfg = load_build_config("toy", ['dataset.splits=["train"]'])
    out = tmp_path / "dexycb"
    summary = export_dataset("gsdf", cfg, tiny_dexycb, tiny_dexycb / "mano", tiny_dexycb / "models", out,
                             store=tiny_store, progress=False)
    records = {r[schema.META]["key"]: r for r in store.iter_records(tiny_store)}
    right = [k for k, r in records.items() if not r[schema.META]["mirrored"]]
    assert summary.extra["sdf_sources"] == {"store": len(right)} and len(right) > 0
    assert any("right hands only" in s["reason"] for s in summary.skipped)  # the mirrored left hands
    doc = json.loads((out / "dexycb_train_s0.json").read_text())
    names = {im["id"]: im["file_name"] for im in doc["images"]}
    by_index = {int(r[schema.META]["sample_index"]): r for r in records.values() if not r[schema.META]["mirrored"]}
    for ann in doc["annotations"][:3]:
        rec = by_index[ann["id"]]
        xyz, sdf_h, sdf_o, _ = schema.dequantize_sdf(rec[schema.SDF])
        n_h, n_o, n_u = rec[schema.META]["sdf_counts"]
        npz = np.load(out / "data" / "sdf_data" / "sdf_hand" / f"{names[ann['id']]}.npz")
        norm = np.load(out / "data" / "sdf_data" / "norm" / f"{names[ann['id']]}.npz")
        rows = np.concatenate([np.c_[npz["pos"], npz["pos_other"]], np.c_[npz["neg"], npz["neg_other"]]]).astype(np.float64)
        rows[:, :3] = rows[:, :3] / norm["scale"] - norm["offset"] - rec[schema.META]["hand_root"]
        rows[:, 3:] /= norm["scale"]
        want = np.c_[xyz, sdf_h, sdf_o][np.r_[0:n_h, n_h + n_o:n_h + n_o + n_u]]
        order = lambda a: a[np.lexsort(np.round(a[:, :3], 6).T)]  # noqa: E731
        np.testing.assert_allclose(order(rows), order(want.astype(np.float64)), atol=2e-6)


def test_gsdf_files_do_not_depend_on_chunks_or_parts(gsdf_export, dexycb_s0, tmp_path):
    """Per-frame randomness is seeded from the record key: another chunking and a --part job write the same bytes."""
    out, _ = gsdf_export
    cfg = load_build_config("dexycb", ["dataset.complete_subjects=false"])
    other = tmp_path / "part"
    summary = export_dataset("gsdf", cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", other, part=(1, 2),
                             chunk_size=2, progress=False)
    assert not summary.finished
    written = sorted(p.relative_to(other) for p in (other / "data").rglob("*.*") if p.suffix in (".npz", ".obj"))
    assert written
    assert all((other / p).read_bytes() == (out / p).read_bytes() for p in written)


def test_gsdf_exports_a_frame_list_beside_another_split(gsdf_export, dexycb_s0, tmp_path):
    """dataset.frame_list (gSDF's own id lists) exports exactly the listed frames, off the stride too, and an
    export of one split into a folder holding another's export keeps both."""
    import shutil

    out, _ = gsdf_export
    both = tmp_path / "dexycb"
    shutil.copytree(out, both, symlinks=True)  # a folder holding the train and test exports
    ids = json.loads((out / "splits" / (_splits(out, None)["test"] + ".json")).read_text())
    listed = tmp_path / "test_list.json"
    listed.write_text(json.dumps([ids[0], str(int(ids[0]) + 1).rjust(8, "0")]))  # the next frame is off-stride
    cfg = load_build_config("dexycb", ["dataset.complete_subjects=false", 'dataset.splits=["test"]',
                                       f"dataset.frame_list={listed}"])
    summary = export_dataset("gsdf", cfg, dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", both, progress=False)
    assert summary.finished and summary.written == 2
    names = _splits(both, None)
    assert json.loads((both / "splits" / f"{names['test']}.json").read_text()) == json.loads(listed.read_text())
    assert (both / "splits" / f"{names['train']}.json").read_bytes() == (out / "splits" / f"{names['train']}.json").read_bytes()
    assert len(load_gsdf(both, names["test"])) == 2 and load_gsdf(both, names["train"])
