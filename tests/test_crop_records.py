"""Crops, intrinsics, heatmaps, mask bits and left-hand mirroring of frames."""

from __future__ import annotations

import cv2
import numpy as np

from hoidata import schema
from hoidata.datasets.frame import Frame
from hoidata.geometry import crop
from hoidata.geometry.crop import project
from hoidata.records.records import mirror_frame, pack_masks, summed_heatmap


def test_crop_intrinsics_follow_the_warped_pixels():
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    pts = np.array([[0.02, -0.01, 0.5], [-0.03, 0.02, 0.55], [0.0, 0.0, 0.6]])
    uv = project(pts, K)
    box = crop.square_crop_box(uv[:2], uv[2:], context=2.0)
    to_crop = crop.crop_affine(box, 128)
    image = np.zeros((480, 640), np.uint8)
    for u, v in np.round(uv).astype(int):
        image[v - 1:v + 2, u - 1:u + 2] = 255  # 3x3 dots centred on the projections
    warped = crop.warp_image(image, to_crop, 128, nearest=True)
    for p in project(pts, to_crop @ K):
        ys, xs = np.nonzero(warped[int(p[1]) - 4:int(p[1]) + 5, int(p[0]) - 4:int(p[0]) + 5])
        assert len(xs) and abs(xs.mean() + int(p[0]) - 4 - p[0]) < 1.0 and abs(ys.mean() + int(p[1]) - 4 - p[1]) < 1.0


def test_crop_box_covers_expanded_boxes_and_outside_is_black():
    hand = np.array([[100.0, 100.0], [140.0, 160.0]])
    obj = np.array([[150.0, 120.0], [200.0, 150.0]])
    # boxes x1.5: hand [90, 85, 150, 175], object [137.5, 112.5, 212.5, 157.5]; union 122.5 x 90
    np.testing.assert_allclose(crop.square_crop_box(hand, obj, context=1.0), [90.0, 68.75, 122.5])
    np.testing.assert_allclose(crop.square_crop_box(hand, obj, context=2.0), [28.75, 7.5, 245.0])
    img = np.full((480, 640, 3), 200, np.uint8)
    out = crop.warp_image(img, crop.crop_affine(np.array([-100.0, -100.0, 200.0]), 64), 64)
    assert (out[:20, :20] == 0).all() and (out[-10:, -10:] == 200).all()


def test_resize_affine_maps_centres_to_centres():
    a = crop.resize_affine(512, 256)
    np.testing.assert_allclose(crop.apply_affine(a, np.array([[-0.5, -0.5], [511.5, 511.5]])), [[-0.5, -0.5], [255.5, 255.5]])


def test_heatmap_peaks_at_joints():
    joints = np.array([[10.0, 20.0], [40.5, 30.0]])
    hm = summed_heatmap(joints, 64, 1.25)
    assert hm.dtype == np.uint8 and hm[20, 10] == 255 and hm[0, 63] == 0
    assert hm[30, 40] == hm[30, 41] > 200  # a joint between two pixels lights both equally


def test_mask_bits():
    labels = np.array([[0, 1], [2, 1]])
    amodal = np.array([[[0, 1], [1, 1]], [[1, 0], [1, 1]]], bool)
    seg = pack_masks(labels, amodal)
    assert seg[0, 1] == schema.SEG_HAND_VISIBLE | schema.SEG_HAND_AMODAL
    assert seg[1, 0] == schema.SEG_OBJECT_VISIBLE | schema.SEG_HAND_AMODAL | schema.SEG_OBJECT_AMODAL
    assert seg[0, 0] == schema.SEG_OBJECT_AMODAL


def test_mirrored_frame_matches_the_flipped_image():
    K = np.array([[600.0, 0, 300.0], [0, 600, 240], [0, 0, 1]])
    joints = np.random.default_rng(0).normal([0, 0, 0.5], 0.03, size=(21, 3))
    pose = np.eye(4)
    pose[:3, 3] = [0.01, 0.02, 0.5]
    frame = Frame("dexycb", "train", "f", None, (640, 480), K, "left", joints[0], "025_mug", 14, pose,
                  np.zeros(48), np.zeros(10), np.zeros(3), joints, project(joints, K), mirror=True)
    m = mirror_frame(frame)
    np.testing.assert_allclose(project(m.joints_3d, m.K), m.joints_2d, atol=1e-9)
    np.testing.assert_allclose(m.joints_2d[:, 0], 639 - frame.joints_2d[:, 0])  # where image[:, ::-1] puts them
    assert m.side == "right" and m.mirror
    img = np.zeros((480, 640), np.uint8)
    u, v = np.round(frame.joints_2d[0]).astype(int)
    img[v, u] = 1
    flipped = cv2.flip(img, 1)
    mu, mv = np.round(m.joints_2d[0]).astype(int)
    assert flipped[mv, mu] == 1


def test_mirrored_frame_poses_the_mirror_image_of_the_object():
    """A mirrored frame's object (masks, SDF, box) is the mirror image of the scene's object, as the flipped image
    shows it: the x-mirrored model under [M R M | M t], wound outward. The plain model under that pose is not."""
    import trimesh

    from hoidata.geometry.mirror import mirror_points
    from hoidata.records.records import ObjectAsset, posed_object

    box = trimesh.creation.box(extents=(0.04, 0.07, 0.1))
    box.apply_translation((0.03, -0.01, 0.02))  # not symmetric in x
    obj = ObjectAsset("box", np.asarray(box.vertices), np.asarray(box.faces), True, np.asarray(box.vertices)[:8])
    K = np.array([[600.0, 0, 300.0], [0, 600, 240], [0, 0, 1]])
    joints = np.random.default_rng(0).normal([0, 0, 0.5], 0.03, size=(21, 3))
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.array([0.3, -0.8, 0.5]))[0]
    pose[:3, 3] = [0.01, 0.02, 0.5]
    frame = Frame("dexycb", "train", "f", None, (640, 480), K, "left", joints[0], "box", 14, pose,
                  np.zeros(48), np.zeros(10), np.zeros(3), joints, project(joints, K), mirror=True)
    scene = obj.vertices @ pose[:3, :3].T + pose[:3, 3]
    verts, faces, box21 = posed_object(mirror_frame(frame), obj)
    np.testing.assert_allclose(verts, mirror_points(scene), atol=1e-12)
    np.testing.assert_allclose(box21, mirror_points(obj.box21 @ pose[:3, :3].T + pose[:3, 3]), atol=1e-12)
    assert trimesh.Trimesh(verts, faces, process=False).volume > 0
    plain = obj.vertices @ mirror_frame(frame).object_pose[:3, :3].T + mirror_frame(frame).object_pose[:3, 3]
    assert np.abs(plain - mirror_points(scene)).max() > 0.01


def test_dataset_mask_iou_equals_one_warp_per_mask(tmp_path):
    """Both dataset masks travel as bits of one map through one nearest warp (and one flip for a mirrored frame):
    the same IoU as warping each mask on its own."""
    from dataclasses import replace

    from hoidata.records.records import dataset_mask_iou

    rng = np.random.default_rng(0)
    height, width, size = 48, 64, 20
    frame_labels = rng.integers(0, 3, (height, width))
    frame = Frame(dataset="toy", split="train", frame_id="f", image_path=tmp_path / "f.jpg", image_size=(width, height),
                  K=np.eye(3), side="right", root_3d=np.zeros(3), object_name="025_mug", object_id=14,
                  object_pose=np.eye(4), labels=frame_labels)
    to_mask = np.array([[0.37, 0.05, -3.2], [-0.04, 0.41, 1.7], [0.0, 0.0, 1.0]])
    ours = rng.integers(0, 3, (size, size))
    for mirror in (False, True):
        theirs = frame_labels[:, ::-1] if mirror else frame_labels
        want = []
        for label in (1, 2):
            warped = crop.warp_image((theirs == label).astype(np.uint8), to_mask, size, nearest=True) > 0
            union = np.count_nonzero((ours == label) | warped)
            want.append(np.count_nonzero((ours == label) & warped) / union)
        np.testing.assert_array_equal(dataset_mask_iou(replace(frame, mirror=mirror), ours, to_mask), want)
    assert (dataset_mask_iou(replace(frame, labels=None), ours, to_mask) == -1).all()  # no dataset masks
