"""HOT3D-Clips' fields on hand-made values: RLE masks (both edges of the 1-based start), cameras, crop cameras,
members of a clip tar (hand shapes missing, a tar cut short)."""

from __future__ import annotations

import io
import json
import tarfile

import numpy as np
import pytest

from hoidata.datasets.hot3d import hand_reason, nearest_object
from hoidata.datasets.hot3d_format import (
    FISHEYE624,
    HAND_SHAPES,
    crop_camera,
    list_members,
    read_betas,
    rle_decode,
    rle_encode,
    stream_camera,
)
from hoidata.errors import DataError


@pytest.fixture(params=["slices", "cumulative sum"])
def rle_path(request, monkeypatch):
    """rle_decode's two ways (a slice per run; one cumulative sum for masks of many runs), each test run on both."""
    import hoidata.datasets.hot3d_format as fmt

    monkeypatch.setattr(fmt, "RLE_LOOP_RUNS", 10**9 if request.param == "slices" else 0)
    return request.param


def test_rle_starts_are_one_based_at_both_edges(rle_path):
    first = rle_decode({"height": 2, "width": 3, "rle": [1, 2]})  # the first two pixels
    np.testing.assert_array_equal(first, [[1, 1, 0], [0, 0, 0]])
    last = rle_decode({"height": 2, "width": 3, "rle": [6, 1]})  # the very last pixel
    np.testing.assert_array_equal(last, [[0, 0, 0], [0, 0, 1]])
    both = rle_decode({"height": 2, "width": 3, "rle": [2, 2, 6, 1]})
    np.testing.assert_array_equal(both, [[0, 1, 1], [0, 0, 1]])
    assert rle_encode(both)["rle"] == [2, 2, 6, 1]
    assert rle_encode(np.ones((2, 3), bool))["rle"] == [1, 6]
    assert rle_encode(np.zeros((2, 3), bool))["rle"] == [] and not rle_decode(rle_encode(np.zeros((2, 3)))).any()


def test_rle_round_trip_on_random_masks(rle_path):
    rng = np.random.default_rng(0)
    for _ in range(20):
        mask = rng.random((rng.integers(1, 30), rng.integers(1, 30))) < rng.random()
        np.testing.assert_array_equal(rle_decode(rle_encode(mask)), mask)


@pytest.mark.parametrize("rle,problem", [([0, 1], "1-based"), ([6, 2], "outside"), ([1], "odd"), ([2, -1], "outside")])
def test_bad_rle_names_the_field(rle, problem, rle_path):
    with pytest.raises(DataError, match=f"'m.rle'.*{problem}"):
        rle_decode({"height": 2, "width": 3, "rle": rle}, "clip.tar", "m")


def _camera(params, model=FISHEYE624, q=(1.0, 0.0, 0.0, 0.0)):
    return {"calibration": {"label": "camera-rgb", "image_width": 64, "image_height": 48, "projection_model_type": model,
                            "projection_params": params},
            "T_world_from_camera": {"quaternion_wxyz": list(q), "translation_xyz": [1.0, 2.0, 3.0]}}


def test_stream_camera_reads_aria_and_quest_params_and_refuses_others():
    aria = stream_camera(_camera([100.0, 31.5, 23.5] + [0.0] * 12), "c.tar", "000000.cameras.json: 214-1")
    assert aria.is_rgb and aria.camera.fx == aria.camera.fy == 100.0 and aria.world_from_camera[2, 3] == 3.0
    quest = stream_camera(_camera([100.0, 101.0, 31.5, 23.5] + [0.0] * 12), "c.tar", "x")
    assert quest.camera.fy == 101.0
    with pytest.raises(DataError, match="projection_model_type.*FISHEYE624"):
        stream_camera(_camera([1.0] * 15, model="PinholePlane"), "c.tar", "x")
    with pytest.raises(DataError, match="projection_params.*15 or 16"):
        stream_camera(_camera([1.0] * 14), "c.tar", "x")
    with pytest.raises(DataError, match="quaternion_wxyz.*unit"):
        stream_camera(_camera([1.0] * 15, q=(2.0, 0.0, 0.0, 0.0)), "c.tar", "x")
    with pytest.raises(DataError, match="'x.T_world_from_camera': missing"):
        stream_camera({"calibration": {}}, "c.tar", "x")
    with pytest.raises(DataError, match="'x.calibration.image_width': expected a whole number, got a string"):
        stream_camera({**_camera([1.0] * 15), "calibration": {**_camera([1.0] * 15)["calibration"],
                                                              "image_width": "64"}}, "c.tar", "x")


def test_crop_camera_fov_is_radians():
    pose = {"quaternion_wxyz": [1.0, 0.0, 0.0, 0.0], "translation_xyz": [0.0, 0.0, 0.0]}
    K, world_from_crop = crop_camera({"crop_camera_fov": 1.0, "T_world_from_crop_camera": pose}, 128, "c", "x")
    assert K[0, 0] == pytest.approx(64 / np.tan(0.5)) and K[0, 2] == 63.5
    with pytest.raises(DataError, match="radians"):
        crop_camera({"crop_camera_fov": 60.0, "T_world_from_crop_camera": pose}, 128, "c", "x")  # degrees


def _tar(path, members: dict) -> None:
    with tarfile.open(path, "w") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))


def test_members_and_hand_shapes(tmp_path):
    shapes = json.dumps({"mano": list(range(10)), "umetrack": {}}).encode()
    _tar(tmp_path / "a.tar", {"000000.info.json": b"{}", "000000.hands.json": b"{", "000001.info.json": b"{}",
                               HAND_SHAPES: shapes})
    clip = list_members(tmp_path / "a.tar")
    assert sorted(clip.frames) == ["000000", "000001"] and not clip.truncated
    np.testing.assert_array_equal(read_betas(clip), np.arange(10))
    assert clip.json("000000", "info.json") == {}
    with pytest.raises(DataError, match="000000.hands.json.*not JSON"):
        clip.json("000000", "hands.json")
    with pytest.raises(DataError, match="000001.hands.json.*member missing"):
        clip.json("000001", "hands.json")
    _tar(tmp_path / "b.tar", {"000000.info.json": b"{}"})
    with pytest.raises(DataError, match=f"b.tar: '{HAND_SHAPES}': member missing"):
        read_betas(list_members(tmp_path / "b.tar"))
    _tar(tmp_path / "c.tar", {"000000.info.json": b"{}", HAND_SHAPES: json.dumps({"mano": [0] * 10}).encode()})
    with pytest.raises(DataError, match="umetrack.*missing"):
        read_betas(list_members(tmp_path / "c.tar"))


def test_a_tar_cut_short_keeps_the_members_before_the_cut(tmp_path):
    _tar(tmp_path / "a.tar", {"000000.info.json": b"{}", "000001.info.json": b"x" * 5000, "000002.info.json": b"{}"})
    data = (tmp_path / "a.tar").read_bytes()
    (tmp_path / "cut.tar").write_bytes(data[:3000])  # inside 000001's bytes
    clip = list_members(tmp_path / "cut.tar")
    assert list(clip.frames) == ["000000"] and "truncated" in clip.truncated
    (tmp_path / "junk.tar").write_bytes(b"not a tar at all" * 100)
    with pytest.raises(DataError, match="junk.tar.*not a readable tar"):
        list_members(tmp_path / "junk.tar")


def test_hand_without_umetrack_pose_gives_no_mano_hand():
    mano = {"thetas": [0.0] * 15, "wrist_xform": [0.0] * 6}
    assert "umetrack_pose" in hand_reason({"mano_pose": mano})
    assert "mano_pose" in hand_reason({"umetrack_pose": {}})
    assert hand_reason({"umetrack_pose": {}, "mano_pose": mano}) is None


def test_nearest_object_and_a_frame_without_objects():
    def inst(bop, x):
        return {"object_bop_id": bop, "T_world_from_object": {"quaternion_wxyz": [1, 0, 0, 0], "translation_xyz": [x, 0, 0]}}

    objects = {"100001": [inst(1, 0.5)], "100002": [inst(2, 0.1)]}
    bop, pose, uid = nearest_object(objects, np.zeros(3), "c.tar", "000000.objects.json")
    assert (bop, uid, pose[0, 3]) == (2, "100002", 0.1)
    with pytest.raises(DataError, match="000000.objects.json.*no annotated object"):
        nearest_object({}, np.zeros(3), "c.tar", "000000.objects.json")


def test_toy_umetrack_profile_has_the_fields_and_shapes_the_official_reader_loads():
    """hand_tracking_toolkit's SampleDecoder builds an UmeTrack model from ``__hand_shapes.json__``'s ``umetrack``:
    nine required tensors (rest positions in millimetres, floats), 22 joints, 17 frames, 21 landmarks."""
    from hoidata.toy.hot3d_umetrack import umetrack_profile

    rest = np.random.default_rng(0).normal(0, 0.05, (21, 3))
    profile = json.loads(json.dumps(umetrack_profile(rest)))
    shapes = {"joint_rotation_axes": (22, 3), "joint_rest_positions": (22, 3), "joint_frame_index": (22,),
              "joint_parent": (22,), "joint_first_child": (22,), "joint_next_sibling": (22,),
              "landmark_rest_positions": (21, 3), "landmark_rest_bone_weights": (21, 2),
              "landmark_rest_bone_indices": (21, 2)}
    assert {k: np.asarray(v).shape for k, v in profile.items()} == shapes
    assert np.asarray(profile["joint_rest_positions"]).dtype.kind == "f"  # the reader scales them in place by 1e-3
    frames = np.asarray(profile["landmark_rest_bone_indices"])
    assert frames.min() >= 0 and frames.max() <= 16
    np.testing.assert_allclose(profile["landmark_rest_positions"][0], (rest[4] - rest[0]) * 1000)  # thumb tip, mm
    np.testing.assert_allclose(profile["landmark_rest_positions"][5], 0.0, atol=1e-12)  # the wrist


def test_toy_clips_beyond_the_default_three():
    """make-toy --layout hot3d --sequences N: the default three clips first, then 3, 4, 5, ... (odd Aria, even Quest
    3), 10 not twice; the reader puts the multiples of 10 in val."""
    from hoidata.datasets.hot3d import VAL_EVERY
    from hoidata.toy.hot3d import DEFAULT_CLIPS, toy_clips

    assert toy_clips(2) == DEFAULT_CLIPS[:2] and toy_clips(3) == DEFAULT_CLIPS
    clips = toy_clips(22)
    numbers = [n for _, n, _ in clips]
    assert numbers[:5] == [1, 2, 10, 3, 4] and len(set(numbers)) == 22 and max(numbers) == 22
    assert [n for n in numbers if n % VAL_EVERY == 0] == [10, 20]
    assert all(folder == f"train_{device.lower()}" and device == ("Aria" if n % 2 else "Quest3")
               for folder, n, device in clips[3:])
    with pytest.raises(ValueError, match="whole number of clips"):
        toy_clips(0)
