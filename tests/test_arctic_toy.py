"""The toy ARCTIC (hoidata make-toy --layout arctic) in the files, keys, shapes and units ARCTIC's own loader
opens (docs/datasets.md, "ARCTIC"), the object templates and ARCTIC's lens and validity rules."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import hoidata.datasets.arctic_format as af
from hoidata.objects.arctic import ARCTIC_OBJECTS, BOTTOM, TOP, TEMPLATE_FILES, load_arctic_object, pose_points
from hoidata.toy.arctic_objects import box_mesh, toy_object, write_toy_template


def test_the_top_part_turns_about_minus_z_then_both_parts_move():
    pts = np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    out = pose_points(pts, np.array([TOP, BOTTOM]), [np.pi / 2], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    assert np.allclose(out[0], [[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0]])  # -z by 90 deg takes -x to +y: the lid lifts


def test_a_toy_template_reads_back_in_metres_with_arctic_part_ids(tmp_path):
    import trimesh

    v, f = box_mesh((-120, -70, -45), (0, 0, 45))
    assert trimesh.Trimesh(v, f, process=False).is_watertight
    folder = tmp_path / "object_vtemplates" / "box"
    diameter = write_toy_template(folder, toy_object(ARCTIC_OBJECTS.index("box")))
    (tmp_path / "object_meta.json").write_text(json.dumps({"box": {"diameter": diameter}}))
    assert all((folder / name).is_file() for name in TEMPLATE_FILES)
    obj = load_arctic_object(tmp_path, "box")
    labels = json.loads((folder / "parts.json").read_text())
    assert obj.part_ids.tolist() == [x + 1 for x in labels] and set(labels) == {0, 1}
    assert obj.sub_vertices.shape == (600, 3) and obj.bbox3d.shape == (16, 3) and obj.kp3d.shape == (32, 3)
    lid = obj.vertices[obj.part_ids == TOP]
    assert lid[:, 1].min() > 0 and obj.vertices[obj.part_ids == BOTTOM][:, 1].max() <= 0  # metres, lid above y = 0
    assert 0.1 < obj.diameter < 0.3 and np.abs(obj.vertices).max() < 0.2


def test_the_egocentric_lens_is_opencv_rational_model():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.4, -0.3, 0.2], [0.4, 0.3, 0.8], (200, 3))
    d = np.array([0.04, -0.015, 0.0008, -0.0006, 0.002, 0.03, -0.008, 0.001])
    K = np.array([[1100.0, 0, 1400], [0, 1100, 1000], [0, 0, 1]])
    ours = af.project(K, af.distort(pts, d))
    assert np.abs(ours - cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, d)[0][:, 0]).max() < 1e-6


def test_validity_needs_the_wrist_and_three_joints_inside_the_box():
    crops = np.tile([[1400.0, 1000.0, 14.0]], (1, 9, 1))  # every view: the whole 2800 x 2000 image
    inside, outside = np.array([1000.0, 900.0]), np.array([-50.0, 900.0])
    hand_ok = np.tile(inside, (1, 9, 21, 1))
    hand_bad = hand_ok.copy()
    hand_bad[:, :, 0] = outside  # the wrist out
    center = np.tile(inside, (1, 9, 1))
    flags = af.validity(crops, hand_ok, hand_bad, center, np.tile([2800.0, 2000.0], (9, 1)))
    assert flags["right_valid"].all() and not flags["left_valid"].any() and flags["is_valid"].all()


@pytest.mark.slow  # writes the toy ARCTIC (3 sequences, grasp synthesis)
def test_make_toy_writes_what_arctic_loader_opens(tmp_path):
    from hoidata.toy.make import make_toy

    root = tmp_path / "arctic"
    made = make_toy(root, "arctic", progress=False)
    assert made["sequences"] == 3
    misc = json.loads((root / "meta" / "misc.json").read_text())
    for subject, entry in misc.items():
        assert np.shape(entry["world2cam"]) == (8, 4, 4) and np.shape(entry["intris_mat"]) == (8, 3, 3)
        assert np.shape(entry["image_size"]) == (9, 2) and isinstance(entry["ioi_offset"], int)
    for name in ARCTIC_OBJECTS:  # ARCTIC's object layer loads every one of its names at start-up
        assert all((root / "meta" / "object_vtemplates" / name / f).is_file() for f in TEMPLATE_FILES)
    meta = json.loads((root / "meta" / "object_meta.json").read_text())
    assert set(meta) == set(ARCTIC_OBJECTS) and all("diameter" in v for v in meta.values())
    splits = json.loads((root / "splits_json" / "protocol_p1.json").read_text())
    for full in splits["train"] + splits["val"] + splits["test"]:
        subject, name = full.split("/")
        mano = np.load(root / "raw_seqs" / subject / f"{name}.mano.npy", allow_pickle=True).item()
        frames = len(mano["right"]["fitting_err"])
        assert frames > 50
        for side in ("right", "left"):
            h = mano[side]
            assert h["rot"].shape == (frames, 3) and h["pose"].shape == (frames, 45) and h["trans"].shape == (frames, 3)
            assert h["shape"].shape == (10,)
        obj = np.load(root / "raw_seqs" / subject / f"{name}.object.npy")
        assert obj.shape == (frames, 7) and 50 < np.abs(obj[:, 6]).min()  # translation in millimetres (~80 mm up)
        ego = np.load(root / "raw_seqs" / subject / f"{name}.egocam.dist.npy", allow_pickle=True).item()
        assert ego["R_k_cam_np"].shape == (frames, 3, 3) and ego["T_k_cam_np"].shape == (frames, 3, 1)
        assert ego["intrinsics"].shape == (3, 3) and ego["dist8"].shape == (8,) and np.abs(ego["dist8"]).min() > 0
        smplx = np.load(root / "raw_seqs" / subject / f"{name}.smplx.npy", allow_pickle=True).item()
        assert smplx["body_pose"].shape == (frames, 63)
        seq = af.read_sequence(root, subject, name)
        assert seq.frames == frames and seq.object_name in ARCTIC_OBJECTS
    with pytest.raises(ValueError, match="50 frames or fewer"):
        make_toy(tmp_path / "short", "arctic", frames=50, progress=False)


@pytest.mark.slow  # the toy, its evaluation files, then check and score end to end
def test_toy_evaluation_has_invalid_hands_and_scores(tmp_path, capsys):
    from hoidata.toy.arctic_eval import write_toy_evaluation
    from hoidata.toy.make import make_toy
    from hoisdf.cli import main
    from hoisdf.scoring.torch_files import read_pt

    root = tmp_path / "arctic"
    make_toy(root, "arctic", progress=False)
    made = write_toy_evaluation(root, tmp_path / "eval", "pose", "p2", split="val")
    gt = tmp_path / "eval" / "gt"
    left = np.concatenate([np.asarray(read_pt(p)) for p in gt.glob("*/targets/targets.left_valid.pt")])
    ego = np.concatenate([np.asarray(read_pt(p)) for p in gt.glob("*/targets/targets.is_valid.pt")])
    assert 0 < left.sum() < len(left) and 0 < ego.sum() < len(ego)  # the left hand leaves; the head looks away
    assert main(["check", "arctic", "--pred", made["zip"], "--gt", str(gt)]) == 0
    assert main(["score", "arctic", "--pred", made["zip"], "--gt", str(gt), "--meta", str(root / "meta"),
                 "--mano", str(root / "mano")]) == 0
    assert "mpjpe/ra/h" in capsys.readouterr().out
