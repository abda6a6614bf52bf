"""hoidata.export's pure parts on hand-made inputs, in the fast tier: gSDF's crop box and box corners, the SDF
files' normalisation and AlignSDF's part labels, HandOccNet's camera entry. tests/test_export_gsdf.py and
tests/test_export_handoccnet.py export toy datasets and read the files back as those loaders do (slow tier)."""

from __future__ import annotations

import numpy as np
import trimesh

from hoidata.export.gsdf import box_corners, gsdf_bbox
from hoidata.export.handoccnet import cam_param
from hoidata.export.sdf_files import BUFFER, closest_faces, hand_labels, normalisation, part_label_table, to_normalised


def test_gsdf_bbox_pads_squares_and_scales_as_process_bbox():
    joints = np.array([[0.0, 0.0], [20.0, 10.0]])
    corners = np.array([[5.0, 5.0], [12.0, 3.0]])
    # box (0, 0)-(20, 10), padded 10 px: x, y = -10, -10, w, h = 40, 30; centre (10, 5); squared to 40, then x1.25
    assert gsdf_bbox(joints, corners) == [-15.0, -20.0, 50.0, 50.0]
    assert gsdf_bbox(joints, np.array([[30.0, 40.0]]))[2:] == [75.0, 75.0]  # a corner widens the box: 40 + 20 px


def test_box_corners_in_trimesh_order():
    lo, hi = np.array([-1.0, 2.0, 0.5]), np.array([3.0, 4.0, 1.5])
    np.testing.assert_array_equal(box_corners(lo, hi), trimesh.bounds.corners(np.stack([lo, hi])))


def test_normalisation_puts_both_meshes_inside_the_unit_sphere_with_the_margin():
    rng = np.random.default_rng(0)
    hand = rng.normal(scale=0.03, size=(778, 3)) + [0.0, 0.0, 0.6]
    obj = rng.normal(scale=0.05, size=(500, 3)) + [0.05, 0.02, 0.65]
    offset, scale = normalisation(hand, obj)
    assert offset.dtype == scale.dtype == np.float32 and offset.shape == (3,) and scale.shape == (1,)
    both = np.concatenate([hand, obj])
    np.testing.assert_allclose(-offset, (both.min(0) + both.max(0)) / 2, rtol=1e-6)  # the union box's middle
    xyz, sdf = to_normalised(both, np.full(len(both), 0.01), offset, scale)
    assert abs(np.linalg.norm(xyz, axis=1).max() - 1 / BUFFER) < 1e-6  # the farthest vertex, less the margin
    np.testing.assert_allclose(sdf, 0.01 * scale[0], rtol=1e-6)  # distances scale with the points
    np.testing.assert_allclose(xyz / scale[0] - offset, both, atol=1e-6)  # and come back to float32 precision


def test_part_labels_follow_alignsdf_finger_order():
    table = part_label_table()
    assert table.shape == (16, 4) and not table[0].any()  # the wrist/palm part: label 0
    # MANO parts 13-15 are the thumb (AlignSDF finger 0), proximal first; 1-3 the index finger (finger 1)
    np.testing.assert_array_equal(table[13:16, :2], [[1, 3], [1, 2], [1, 1]])
    np.testing.assert_array_equal(table[1:4, :2], [[2, 6], [2, 5], [2, 4]])
    assert sorted(table[1:, 1].tolist()) == list(range(1, 16))  # each fine label once
    assert sorted(set(table[1:, 0].tolist())) == [1, 2, 3, 4, 5]


def test_hand_labels_take_the_closest_faces_part_and_flag_the_wrist_cap():
    face_parts = np.array([0, 13, 1, 15, 0])  # five faces of a closed hand; the last one caps the wrist
    labels = hand_labels(np.array([1, 2, 4, 0]), face_parts, n_open_faces=4)
    np.testing.assert_array_equal(labels[:, :2], part_label_table()[[13, 1, 0, 0], :2])
    np.testing.assert_array_equal(labels[:, 3], [0, 0, 1, 0])


def test_closest_faces_of_a_square_of_two_triangles():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    points = np.array([[0.9, 0.1, 0.3], [0.1, 0.9, -0.2], [2.0, -1.0, 0.0]])
    np.testing.assert_array_equal(closest_faces(points, vertices, faces), [0, 1, 0])
    assert closest_faces(np.zeros((0, 3)), vertices, faces).shape == (0,)


def test_handoccnet_camera_entry():
    K = np.array([[600.0, 0, 320.5], [0, 610.0, 240.25], [0, 0, 1]])
    assert cam_param(K) == {"focal": [600.0, 610.0], "princpt": [320.5, 240.25]}
