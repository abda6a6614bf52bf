"""The readers on toy data in the real DexYCB and HO-3D layouts: counts, labels vs pixels, bad input."""

from __future__ import annotations

import pickle
import shutil
from dataclasses import replace

import cv2
import igl
import numpy as np
import pytest
import torch

from hoidata.datasets.dexycb import SETTINGS, DexYCBReader
from hoidata.datasets.dexycb_frames import FRAME_KEYS
from hoidata.datasets.dexycb_layout import read_labels
from hoidata.datasets.ho3d import HO3DReader
from hoidata.errors import DataError
from hoidata.geometry.crop import project
from hoidata.hand import load_mano
from hoidata.objects import load_object_mesh, object_mesh_path, repair_mesh
from hoidata.toy.dexycb import (
    INVALID_FRAME,
    ToyDexYCBSize,
    ToyJob,
    ToyWorkerSpec,
    sequence_side,
    write_calibration,
    write_toy_dexycb,
)
from hoidata.toy.ho3d import (
    DEPTH_SCALE,
    ToyHO3DSize,
    pack_depth,
    unpack_depth,
    write_toy_ho3d,
)
from hoidata.toy.make import write_assets

DEX_SIZE = ToyDexYCBSize(subjects=(0, 2), sequences=5, serials=(0, 7), frames=8)
HO3D_SIZE = ToyHO3DSize(train_sequences=2, eval_sequences=1, frames=4)


@pytest.fixture(scope="session")
def dex_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("dexycb")
    mano_dir, models_dir = write_assets(root)
    write_toy_dexycb(root, mano_dir, models_dir, DEX_SIZE, workers=2, progress=False)
    return root


@pytest.fixture(scope="session")
def ho3d_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("ho3d")
    mano_dir, models_dir = write_assets(root)
    write_toy_ho3d(root, mano_dir, models_dir, HO3D_SIZE, progress=False)
    return root


def _read(root, split, setting="dexycb_full", **kw):
    reader = DexYCBReader(root, root / "mano", split, replace(SETTINGS[setting], complete_subjects=False), **kw)
    return list(reader.frames()), reader


def _implied_count(split, stride, sides):
    """Frames the toy layout implies for an s0 split before quality filters."""
    subjects = {"train": [0, 2], "val": [0], "test": [2]}[split]
    seqs = [i for i in range(DEX_SIZE.sequences) if (i % 5 != 4) == (split == "train")]
    frames = [f for f in range(0, DEX_SIZE.frames, stride)]
    total = 0
    for _ in subjects:
        for i in seqs:
            if sequence_side(i) in sides:
                invalid = INVALID_FRAME in frames and i % 3 == 2
                total += len(DEX_SIZE.serials) * (len(frames) - invalid)
    return total


@pytest.mark.slow
@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_dexycb_split_counts_match_the_layout(dex_root, split):
    full, _ = _read(dex_root, split, "dexycb_full")
    assert len(full) == _implied_count(split, 1, ("right", "left")) > 0
    assert all(f.mirror == (f.side == "left") for f in full)
    subset, reader = _read(dex_root, split, "dexycb")
    far = [s for s in reader.skipped if s.reason.startswith("hand-object distance")]
    assert len(subset) + len(far) == _implied_count(split, 5, ("right",))
    assert len(subset) > 0 and all(f.side == "right" and not f.mirror for f in subset)
    assert all(int(f.source["frame"]) % 5 == 0 for f in subset)


@pytest.mark.slow
def test_a_sequence_written_again_elsewhere_is_byte_identical(dex_root, tmp_path):
    # the tree was written by a pool of 2 processes; here one sequence of each hand again, in this process: the
    # colour images too (pyrender's draw and light order once followed memory addresses, 1 level at a few pixels)
    calib = write_calibration(tmp_path, DEX_SIZE, np.random.default_rng(0))
    worker = ToyWorkerSpec(dex_root / "mano", dex_root / "models").open()
    try:
        for number, (pos, subject, sequence) in enumerate([(0, DEX_SIZE.subjects[0], 0), (1, DEX_SIZE.subjects[1], 1)]):
            worker.run(ToyJob(number, tmp_path, pos, subject, sequence, DEX_SIZE, calib, 0))
    finally:
        worker.close()
    again = sorted(p for p in tmp_path.rglob("*") if p.is_file() and "calibration" not in p.parts)
    assert len([p for p in again if p.suffix == ".jpg"]) == 2 * len(DEX_SIZE.serials) * DEX_SIZE.frames
    for path in again:
        assert path.read_bytes() == (dex_root / path.relative_to(tmp_path)).read_bytes(), path.relative_to(tmp_path)


@pytest.mark.slow
def test_dexycb_invalid_annotations_are_skipped_with_reasons(dex_root):
    _, reader = _read(dex_root, "train", "dexycb_full")
    reasons = {s.reason for s in reader.skipped}
    assert reasons == {"hand annotation missing (joint_3d is -1)"}
    assert all(s.path.endswith(f"labels_{INVALID_FRAME:06d}.npz") for s in reader.skipped)


@pytest.mark.slow
def test_dexycb_other_setups_select_by_subject_and_camera(dex_root):
    s2 = {split: {f.source["serial"] for f in DexYCBReader(dex_root, dex_root / "mano", split,
                                                           SETTINGS["dexycb_full"].__class__(setup="s2", sides=("right", "left"),
                                                                                             frame_stride=1, proximity_mm=None,
                                                                                             complete_subjects=False)).frames()}
          for split in ("train", "test")}
    assert s2 == {"train": {"836212060125"}, "test": {"932122062010"}}


def _mano_joints(frame, mano):
    out = mano(torch.as_tensor(frame.mano_pose)[None], torch.as_tensor(frame.mano_betas)[None],
               torch.as_tensor(frame.mano_transl)[None])
    return out.joints[0].numpy(), out.vertices[0].numpy()


@pytest.mark.slow
def test_dexycb_labels_are_consistent(dex_root):
    frames, reader = _read(dex_root, "train", "dexycb_full")
    assert {f.side for f in frames} == {"right", "left"}
    for frame in frames[::7]:
        np.testing.assert_allclose(project(frame.joints_3d, frame.K), frame.joints_2d, atol=0.5)
        joints, _ = _mano_joints(frame, reader.mano(frame.side))  # left: MANO_LEFT without the fix
        np.testing.assert_allclose(joints, frame.joints_3d, atol=1e-5)  # PCA pose -> axis-angle is exact


@pytest.mark.slow
def test_ho3d_labels_are_consistent(ho3d_root):
    reader = HO3DReader(ho3d_root, ho3d_root / "mano", "train")
    frames = list(reader.frames())
    assert len(frames) == HO3D_SIZE.train_sequences * HO3D_SIZE.frames
    mano = load_mano(ho3d_root / "mano", tips="ho3d", dtype=torch.float64)
    gl = np.diag([1.0, -1.0, -1.0])
    for frame in frames:
        meta = pickle.loads(open(frame.source["meta"], "rb").read())
        # HO-3D's own projection: flip to OpenCV, apply K
        uvw = (meta["handJoints3D"] @ gl.T) @ meta["camMat"].T
        np.testing.assert_allclose(uvw[:, :2] / uvw[:, 2:], frame.joints_2d[np.argsort([0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20])], atol=0.5)
        assert (meta["handJoints3D"][:, 2] < 0).all()  # OpenGL: the scene lies at negative z
        joints, _ = _mano_joints(frame, mano)
        np.testing.assert_allclose(joints, frame.joints_3d, atol=1e-5)
        assert frame.tip_convention == "ho3d"


@pytest.mark.slow
def test_ho3d_evaluation_split_has_reduced_ground_truth(ho3d_root):
    frames = list(HO3DReader(ho3d_root, ho3d_root / "mano", "evaluation").frames())
    assert len(frames) == HO3D_SIZE.frames
    for f in frames:
        assert f.mano_pose is None and f.joints_3d is None and f.hand_box.shape == (4,)
        assert f.root_3d[2] > 0  # converted to OpenCV: in front of the camera
        u, v = project(f.root_3d, f.K)
        x1, y1, x2, y2 = f.hand_box
        assert x1 <= u <= x2 and y1 <= v <= y2


def _dilate(mask, px):
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)) > 0


def _model_silhouette(frame, root, shape):
    mesh = load_object_mesh(object_mesh_path(root / "models", frame.object_name))
    pts = np.asarray(mesh.vertices) @ frame.object_pose[:3, :3].T + frame.object_pose[:3, 3]
    uv = project(pts, frame.K)
    sil = np.zeros(shape, np.uint8)
    for tri in np.round(uv[np.asarray(mesh.faces)] * 16).astype(np.int32):  # one by one: fillPoly is even-odd
        cv2.fillConvexPoly(sil, tri, 1, shift=4)
    return sil > 0


@pytest.mark.slow
def test_dexycb_joints_and_object_agree_with_the_pixels(dex_root):
    """Every projected joint lies under the hand or under what occludes it: the rendered surface at
    the joint's pixel is at or in front of the joint (the object, or the hand itself, hides it)."""
    frames, _ = _read(dex_root, "train", "dexycb_full")
    on_hand = []
    for frame in frames[::11]:
        seg = read_labels(frame.segmentation_path, 2)["seg"]
        depth_path = str(frame.image_path).replace("color_", "aligned_depth_to_color_").replace(".jpg", ".png")
        depth = cv2.imread(depth_path, cv2.IMREAD_ANYDEPTH) / 1000.0
        hand, obj = seg == 255, seg == frame.object_id
        uv = np.round(frame.joints_2d).astype(int)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
        u, v, z = uv[inside, 0], uv[inside, 1], frame.joints_3d[inside, 2]
        assert _dilate(hand | obj, 3)[v, u].mean() >= 0.95, frame.frame_id
        surface = depth[v, u]
        assert ((surface > 0) & (surface <= z + 0.004)).mean() >= 0.9, frame.frame_id  # in front of the joint
        visible = _dilate(hand, 2)[v, u]
        on_hand.append(visible.mean())
        if obj.any():
            covered = _dilate(_model_silhouette(frame, dex_root, seg.shape), 1)[obj].mean()
            assert covered >= 0.99, frame.frame_id
    assert np.mean(on_hand) >= 0.5  # over all views most joints are seen on the hand itself


@pytest.mark.slow
def test_ho3d_segmentation_and_depth_agree_with_the_labels(ho3d_root):
    frame = next(HO3DReader(ho3d_root, ho3d_root / "mano", "train").frames())
    seg = cv2.cvtColor(cv2.imread(str(frame.segmentation_path)), cv2.COLOR_BGR2RGB)
    seg = cv2.resize(seg, (640, 480), interpolation=cv2.INTER_NEAREST)
    hand = seg[..., 0] > 200
    uv = np.round(frame.joints_2d).astype(int)
    assert _dilate(hand | (seg[..., 2] > 200), 6)[uv[:, 1], uv[:, 0]].mean() >= 0.9
    depth = unpack_depth(cv2.imread(str(frame.image_path).replace("/rgb/", "/depth/")))
    root_px = np.round(project(frame.root_3d, frame.K)).astype(int)
    surface = depth[root_px[1], root_px[0]]
    assert 0 < surface <= frame.root_3d[2] + 0.004  # the wrist, or what hides it, is at or in front of the joint
    ramp = np.linspace(0.2, 1.5, 640 * 480).reshape(480, 640)
    np.testing.assert_allclose(unpack_depth(pack_depth(ramp)), ramp, atol=DEPTH_SCALE)


@pytest.mark.slow
def test_no_toy_grasp_penetrates_more_than_2mm(dex_root):
    frames, reader = _read(dex_root, "train", "dexycb_full")
    seen = set()
    for frame in frames:
        key = (frame.source["subject"], frame.source["sequence"], frame.source["frame"])  # every frame, one camera
        if key in seen:
            continue
        seen.add(key)
        _, verts = _mano_joints(frame, reader.mano(frame.side))
        geo, _ = repair_mesh(load_object_mesh(object_mesh_path(dex_root / "models", frame.object_name)))
        local = (verts - frame.object_pose[:3, 3]) @ frame.object_pose[:3, :3]
        wn = igl.winding_number(np.asarray(geo.vertices), np.asarray(geo.faces), local)
        dist = np.sqrt(igl.point_mesh_squared_distance(local, np.asarray(geo.vertices), np.asarray(geo.faces))[0])
        assert (dist[wn > 0.5] <= 0.002).all(), key


@pytest.mark.slow
def test_bad_dexycb_input(dex_root, tmp_path):
    root = tmp_path / "dex"
    shutil.copytree(dex_root, root)
    seq = sorted((root / "20200709-subject-01").iterdir())[0]
    labels = seq / "836212060125" / "labels_000003.npz"
    labels.write_bytes(labels.read_bytes()[:100])
    with pytest.raises(DataError, match=r"labels_000003\.npz"):
        _read(root, "train")
    frames, reader = _read(root, "train", on_error="skip")
    assert any(s.path.endswith("labels_000003.npz") for s in reader.skipped)
    (seq / "meta.yml").unlink()
    with pytest.raises(DataError, match=r"meta\.yml.*file not found"):
        _read(root, "train")
    with pytest.raises(ValueError, match="unknown DexYCB split 'dev'"):
        DexYCBReader(root, root / "mano", "dev")


@pytest.mark.slow
def test_bad_ho3d_input(ho3d_root, tmp_path):
    root = tmp_path / "ho3d"
    shutil.copytree(ho3d_root, root)
    meta_path = root / "train" / "BB10" / "meta" / "0001.pkl"
    meta = pickle.loads(meta_path.read_bytes())
    del meta["handPose"]
    meta_path.write_bytes(pickle.dumps(meta, protocol=2))
    with pytest.raises(DataError, match=r"0001\.pkl: 'handPose': missing key"):
        list(HO3DReader(root, root / "mano", "train").frames())
    meta["handPose"] = None
    meta_path.write_bytes(pickle.dumps(meta, protocol=2))
    reader = HO3DReader(root, root / "mano", "train")
    assert len(list(reader.frames())) == HO3D_SIZE.train_sequences * HO3D_SIZE.frames - 1
    assert reader.skipped[0].reason == "annotation failed (handPose is None)"
    with pytest.raises(ValueError, match="unknown HO-3D split 'test'"):
        HO3DReader(root, root / "mano", "test")
    (root / "evaluation.txt").unlink()
    with pytest.raises(DataError, match=r"evaluation\.txt.*not found"):
        HO3DReader(root, root / "mano", "evaluation")


@pytest.mark.slow
def test_malformed_values_name_the_file_and_field(dex_root, ho3d_root, tmp_path):
    import yaml

    root = tmp_path / "dex"
    shutil.copytree(dex_root, root)
    meta_path = sorted((root / "20200709-subject-01").iterdir())[0] / "meta.yml"
    meta = yaml.safe_load(meta_path.read_text())
    meta["ycb_grasp_ind"] = "first"
    meta_path.write_text(yaml.safe_dump(meta))
    with pytest.raises(DataError, match=r"meta\.yml: 'ycb_grasp_ind': expected an integer"):
        _read(root, "train")
    _, reader = _read(root, "train", on_error="skip")
    assert any("ycb_grasp_ind" in s.reason for s in reader.skipped)
    (root / "calibration" / "intrinsics" / "932122062010_640x480.yml").unlink()
    _, reader = _read(root, "train", on_error="skip")
    assert any("932122062010_640x480.yml" in s.reason for s in reader.skipped)
    hroot = tmp_path / "ho3d"
    shutil.copytree(ho3d_root, hroot)
    path = hroot / "train" / "BB10" / "meta" / "0000.pkl"
    hmeta = pickle.loads(path.read_bytes())
    hmeta["handPose"] = "garbage"
    path.write_bytes(pickle.dumps(hmeta, protocol=2))
    with pytest.raises(DataError, match=r"0000\.pkl: 'handPose': expected 48 numbers"):
        list(HO3DReader(hroot, hroot / "mano", "train").frames())


@pytest.mark.slow
def test_partial_subjects_are_refused_by_default(dex_root):
    with pytest.raises(DataError, match=r"20200709-subject-01: 5 sequence folders, expected 100"):
        list(DexYCBReader(dex_root, dex_root / "mano", "train").frames())


def test_read_labels_of_some_keys_still_checks_the_file(tmp_path):
    """read_labels(keys=...) (what build-sdf's mask check reads) decodes only those members, but a missing
    member is still refused, and the decoded ones are checked as before."""
    good = {"seg": np.zeros((480, 640), np.uint8), "pose_y": np.zeros((2, 3, 4)), "pose_m": np.zeros((1, 51)),
            "joint_3d": np.zeros((1, 21, 3)), "joint_2d": np.zeros((1, 21, 2))}
    path = tmp_path / "labels_000000.npz"
    np.savez_compressed(path, **good)
    assert set(read_labels(path, 2, keys=("seg",))) == {"seg"} and set(read_labels(path, 2)) == set(good)
    np.savez_compressed(path, **{k: v for k, v in good.items() if k != "joint_2d"})
    with pytest.raises(DataError, match=r"labels_000000\.npz: 'joint_2d': missing key"):
        read_labels(path, 2, keys=("seg",))
    np.savez_compressed(path, **dict(good, seg=np.zeros((48, 64), np.uint8)))
    with pytest.raises(DataError, match=r"'seg': expected shape \(480, 640\)"):
        read_labels(path, 2, keys=("seg",))
    # the members left undecoded (what the frame readers leave: seg) are checked from their .npy headers
    with pytest.raises(DataError, match=r"labels_000000\.npz: 'seg': expected shape \(480, 640\), got \(48, 64\)"):
        read_labels(path, 2, keys=FRAME_KEYS)
    np.savez_compressed(path, **dict(good, seg=np.zeros((480, 640), "U1")))
    with pytest.raises(DataError, match=r"'seg': expected numbers, got dtype <U1"):
        read_labels(path, 2, keys=FRAME_KEYS)
    np.savez(path, **dict(good, pose_y=np.zeros((3, 3, 4))))  # uncompressed members too
    with pytest.raises(DataError, match=r"'pose_y': expected shape \(2, 3, 4\), got \(3, 3, 4\)"):
        read_labels(path, 2, keys=("seg",))
    assert set(read_labels(path, 3, keys=FRAME_KEYS)) == set(FRAME_KEYS)
    assert set(read_labels(path, 2, keys=("seg",), check_rest=False)) == {"seg"}  # the build's second read
