"""Left <-> right mirroring: involution, and the mirrored left hand equals the right hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from hoidata.geometry.mirror import (
    mirror_axis_angle,
    mirror_mesh,
    mirror_points,
    mirror_rotation,
    mirror_transform,
)
from hoidata.hand import load_mano


def test_mirroring_twice_is_identity_numpy_and_torch():
    rng = np.random.default_rng(0)
    pts, pose = rng.normal(size=(10, 3)), rng.normal(size=(4, 48))
    rot = Rotation.random(5, random_state=1).as_matrix()
    tf = np.tile(np.eye(4), (5, 1, 1))
    tf[:, :3, :3], tf[:, :3, 3] = rot, rng.normal(size=(5, 3))
    for x, f in ((pts, mirror_points), (pose, mirror_axis_angle), (rot, mirror_rotation), (tf, mirror_transform)):
        np.testing.assert_array_equal(f(f(x)), x)
        assert not np.allclose(f(x), x)
        t = torch.as_tensor(x)
        assert torch.equal(f(f(t)), t)
        np.testing.assert_array_equal(f(t).numpy(), f(x))


def test_mirrored_mesh_stays_outward_wound_numpy_and_torch():
    import trimesh

    box = trimesh.creation.box(extents=(0.04, 0.07, 0.1))
    box.apply_translation((0.03, -0.01, 0.02))
    verts, faces = np.asarray(box.vertices), np.asarray(box.faces)
    mv, mf = mirror_mesh(verts, faces)
    np.testing.assert_array_equal(mv, mirror_points(verts))
    assert trimesh.Trimesh(mv, mf, process=False).volume == pytest.approx(box.volume)  # positive: outward
    assert mf.flags.c_contiguous
    twice = mirror_mesh(mv, mf)
    np.testing.assert_array_equal(twice[0], verts)
    np.testing.assert_array_equal(twice[1], faces)
    tv, tf = mirror_mesh(torch.as_tensor(verts), torch.as_tensor(faces))
    np.testing.assert_array_equal(tv.numpy(), mv)
    np.testing.assert_array_equal(tf.numpy(), mf)


def test_axis_angle_mirror_agrees_with_rotation_mirror():
    aa = np.random.default_rng(2).normal(size=(20, 3))
    via_matrix = mirror_rotation(Rotation.from_rotvec(aa).as_matrix())
    np.testing.assert_allclose(Rotation.from_rotvec(mirror_axis_angle(aa)).as_matrix(), via_matrix, atol=1e-12)


def test_mirrored_rotation_acts_on_mirrored_points():
    rng = np.random.default_rng(3)
    rot, pts = Rotation.random(random_state=4).as_matrix(), rng.normal(size=(7, 3))
    np.testing.assert_allclose(mirror_points(pts @ rot.T), mirror_points(pts) @ mirror_rotation(rot).T, atol=1e-12)


def test_axis_angle_needs_triplets():
    with pytest.raises(ValueError, match="multiple of 3"):
        mirror_axis_angle(np.zeros(47))


def _inputs(seed):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(3, 48, generator=g, dtype=torch.float64) * 0.5,
            torch.randn(3, 10, generator=g, dtype=torch.float64) * 2.0,
            torch.randn(3, 3, generator=g, dtype=torch.float64) * 0.2)


def test_mirrored_left_hand_matches_right_hand(mano_right, mano_left):
    pose, betas, transl = _inputs(5)
    right = mano_right(pose, betas, transl)
    left = mano_left(mirror_axis_angle(pose), betas, mirror_points(transl))
    assert torch.allclose(mirror_points(left.vertices), right.vertices, atol=1e-10)
    # manopth takes the left middle tip from vertex 445 instead of 444: every other joint matches
    others = [i for i in range(21) if i != 12]
    assert torch.allclose(mirror_points(left.joints[:, others]), right.joints[:, others], atol=1e-10)
    assert torch.equal(left.joints[:, 12], left.vertices[:, 445])


def test_left_shapedirs_fix_is_needed_and_applied(mano_dir, mano_right):
    unfixed = load_mano(mano_dir, side="left", fix_left_shapedirs=False, dtype=torch.float64)
    pose, betas, transl = _inputs(6)
    right = mano_right(pose, betas, transl).vertices
    wrong = mirror_points(unfixed(mirror_axis_angle(pose), betas, mirror_points(transl)).vertices)
    assert (wrong - right).norm(dim=-1).max() > 1e-3  # the file's bug: visibly different shapes


def test_left_pca_basis_is_the_mirrored_right_basis(mano_right, mano_left):
    g = torch.Generator().manual_seed(7)
    coeffs = torch.randn(4, 45, generator=g, dtype=torch.float64)
    right = mano_right.hands_mean + coeffs @ mano_right.hands_components
    left = mano_left.hands_mean + coeffs @ mano_left.hands_components
    assert torch.allclose(mirror_axis_angle(left), right, atol=1e-12)
