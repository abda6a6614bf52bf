"""MANO layer: forward kinematics, conversions, gradients, dtypes, closed mesh and part labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from hoidata.geometry.rotation import axis_angle_to_matrix
from hoidata.hand import (
    DEXYCB_TO_MANO,
    MANO_PARENTS,
    MANO_TO_DEXYCB,
    axis_angle_to_pca,
    flat_to_mean_relative,
    load_mano,
    mean_relative_to_flat,
    pca_to_axis_angle,
)


def random_inputs(n, seed=0, dtype=torch.float64, scale=0.5):
    g = torch.Generator().manual_seed(seed)
    pose = torch.randn(n, 48, generator=g, dtype=dtype) * scale
    betas = torch.randn(n, 10, generator=g, dtype=dtype)
    transl = torch.randn(n, 3, generator=g, dtype=dtype) * 0.2
    return pose, betas, transl


def reference_forward(model, pose, betas, transl):
    """Independent numpy/scipy MANO forward (one sample at a time, explicit loops) for cross-checking."""
    v_t = model.v_template.double().numpy()
    sd, pd = model.shapedirs.double().numpy(), model.posedirs.double().numpy()
    jr, w = model.j_regressor.double().numpy(), model.lbs_weights.double().numpy()
    v_shaped = v_t + sd @ betas
    joints = jr @ v_shaped
    rots = Rotation.from_rotvec(pose.reshape(16, 3)).as_matrix()
    feat = np.concatenate([(r - np.eye(3)).ravel() for r in rots[1:]])
    v_posed = v_shaped + pd @ feat
    world = []
    for j in range(16):
        local = np.eye(4)
        local[:3, :3] = rots[j]
        local[:3, 3] = joints[j] - (joints[MANO_PARENTS[j]] if j else 0)
        world.append(local if j == 0 else world[MANO_PARENTS[j]] @ local)
    verts = np.zeros_like(v_posed)
    for j in range(16):
        g = world[j].copy()
        g[:3, 3] -= g[:3, :3] @ joints[j]
        verts += w[:, j:j + 1] * (v_posed @ g[:3, :3].T + g[:3, 3])
    return verts + transl, np.array([g[:3, 3] for g in world]) + transl


def test_zero_pose_gives_template(mano_right):
    out = mano_right(torch.zeros(2, 48, dtype=torch.float64))
    assert torch.allclose(out.vertices, mano_right.v_template.expand(2, -1, -1), atol=1e-12)
    rest_joints = mano_right.j_regressor @ mano_right.v_template
    assert torch.allclose(out.mano_joints[0], rest_joints, atol=1e-12)


def test_forward_matches_independent_reference(mano_right):
    pose, betas, transl = random_inputs(3)
    out = mano_right(pose, betas, transl)
    for i in range(3):
        verts, joints = reference_forward(mano_right, pose[i].numpy(), betas[i].numpy(), transl[i].numpy())
        np.testing.assert_allclose(out.vertices[i].numpy(), verts, atol=1e-10)
        np.testing.assert_allclose(out.mano_joints[i].numpy(), joints, atol=1e-10)


def test_rodrigues_matches_scipy():
    aa = torch.randn(64, 3, dtype=torch.float64) * 2.0
    aa[0] = 0.0
    aa[1] = 1e-5
    ref = Rotation.from_rotvec(aa.numpy()).as_matrix()
    np.testing.assert_allclose(axis_angle_to_matrix(aa).numpy(), ref, atol=1e-10)


def test_batched_equals_per_sample(mano_right):
    pose, betas, transl = random_inputs(5, seed=1)
    batched = mano_right(pose, betas, transl)
    for i in range(5):
        single = mano_right(pose[i:i + 1], betas[i:i + 1], transl[i:i + 1])
        assert torch.allclose(batched.vertices[i], single.vertices[0], atol=1e-12)
        assert torch.allclose(batched.joints[i], single.joints[0], atol=1e-12)


def test_joints_are_dexycb_order_with_mano_tips(mano_right):
    pose, betas, transl = random_inputs(2, seed=2)
    out = mano_right(pose, betas, transl)
    assert out.joints.shape == (2, 21, 3)
    mano_plus_tips = torch.cat([out.mano_joints, out.vertices[:, [745, 317, 444, 556, 673]]], dim=1)
    assert torch.equal(out.joints, mano_plus_tips[:, MANO_TO_DEXYCB])
    assert torch.equal(out.joints[:, DEXYCB_TO_MANO], mano_plus_tips)
    assert out.joints[0, 4].tolist() == out.vertices[0, 745].tolist()  # thumb tip


def test_ho3d_tip_convention(mano_dir):
    ho3d = load_mano(mano_dir, tips="ho3d", dtype=torch.float64)
    out = ho3d(*random_inputs(1, seed=3))
    assert torch.equal(out.joints[0, [4, 8, 12, 16, 20]], out.vertices[0, [744, 333, 444, 555, 672]])


def test_pca_conversion_is_exact(mano_right):
    comps, mean = mano_right.hands_components, mano_right.hands_mean
    g = torch.Generator().manual_seed(4)
    pose_m = torch.randn(8, 48, generator=g, dtype=torch.float64)
    full = pca_to_axis_angle(pose_m, comps, mean)
    # manopth's internal formula, written out: global, then hands_mean + coeffs . components
    expected = torch.cat([pose_m[:, :3], mean + pose_m[:, 3:] @ comps], dim=1)
    assert torch.allclose(full, expected, atol=1e-12)
    assert torch.allclose(axis_angle_to_pca(full, comps, mean), pose_m, atol=1e-6)
    # numpy path, float32, and fewer components
    np_full = pca_to_axis_angle(pose_m.numpy().astype(np.float32), comps.numpy(), mean.numpy())
    assert np_full.dtype == np.float32
    np.testing.assert_allclose(np_full, full.numpy(), atol=1e-5)
    short = pca_to_axis_angle(pose_m[:, :15], comps, mean)
    assert torch.allclose(short[:, 3:], mean + pose_m[:, 3:15] @ comps[:12], atol=1e-12)


def test_flat_and_mean_relative_round_trip(mano_right):
    pose, _, _ = random_inputs(4, seed=5)
    mean = mano_right.hands_mean
    rel = flat_to_mean_relative(pose, mean)
    assert torch.allclose(rel[:, 3:], pose[:, 3:] - mean)
    assert torch.allclose(mean_relative_to_flat(rel, mean), pose, atol=1e-12)


def test_pca_pose_drives_the_model_like_manopth(mano_right):
    """Feeding the converted pose to the flat layer equals posing with mean + PCA inside the layer."""
    g = torch.Generator().manual_seed(6)
    pose_m = torch.randn(3, 48, generator=g, dtype=torch.float64) * 0.5
    full = pca_to_axis_angle(pose_m, mano_right.hands_components, mano_right.hands_mean)
    out = mano_right(full)
    for i in range(3):
        inner = np.concatenate([pose_m[i, :3].numpy(),
                                (mano_right.hands_mean + pose_m[i, 3:] @ mano_right.hands_components).numpy()])
        verts, _ = reference_forward(mano_right, inner, np.zeros(10), np.zeros(3))
        np.testing.assert_allclose(out.vertices[i].numpy(), verts, atol=1e-6)


def test_gradients_flow(mano_right):
    pose, betas, transl = random_inputs(2, seed=7)
    pose[0] = 0.0  # the rest pose must have finite gradients too
    for t in (pose, betas, transl):
        t.requires_grad_(True)
    out = mano_right(pose, betas, transl)
    (out.vertices.square().sum() + out.joints.sum()).backward()
    for t in (pose, betas, transl):
        assert torch.isfinite(t.grad).all()
        assert t.grad.abs().sum() > 0
    assert pose.grad[0].abs().sum() > 0


def test_float32_matches_float64(mano_dir, mano_right):
    m32 = load_mano(mano_dir, dtype=torch.float32)
    assert m32.v_template.dtype == torch.float32
    pose, betas, transl = random_inputs(3, seed=8)
    out32 = m32(pose.float(), betas.float(), transl.float())
    out64 = mano_right(pose, betas, transl)
    assert out32.vertices.dtype == torch.float32
    assert torch.allclose(out32.vertices.double(), out64.vertices, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(mano_right):
    pose, betas, transl = random_inputs(4, seed=9)
    cpu = mano_right(pose, betas, transl)
    gpu = mano_right.to("cuda")(pose.cuda(), betas.cuda(), transl.cuda())
    mano_right.to("cpu")
    assert torch.allclose(gpu.vertices.cpu(), cpu.vertices, atol=1e-9)


@pytest.mark.parametrize("side", ["right", "left"])
def test_closed_hand_is_watertight_with_positive_volume(side, mano_right, mano_left):
    model = mano_right if side == "right" else mano_left
    assert model.closed_faces.shape == (1538 + 16, 3)
    for pose in (torch.zeros(1, 48, dtype=torch.float64), random_inputs(1, seed=10, scale=0.2)[0]):
        verts = model.close(model(pose).vertices)[0].numpy()
        mesh = trimesh.Trimesh(verts, model.closed_faces, process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent
        assert mesh.volume > 1e-4  # m^3: about 250 cm^3 at rest


def test_part_labels_from_skinning_weights(mano_right):
    parts = mano_right.vertex_parts
    assert parts.shape == (778,) and set(parts.tolist()) == set(range(16))
    assert np.array_equal(parts, mano_right.lbs_weights.numpy().argmax(1))
    # each fingertip vertex belongs to its finger's distal part (MANO order: thumb 15, index 3, ...)
    for tip, part in zip((745, 317, 444, 556, 673), (15, 3, 6, 12, 9)):
        assert parts[tip] == part
    assert mano_right.face_parts.shape == (1538,)
    assert (mano_right.closed_face_parts[1538:] == 0).all()  # the wrist cap is palm/wrist
    assert set(mano_right.face_parts.tolist()) == set(range(16))


def test_bad_forward_inputs_raise_clear_errors(mano_right):
    with pytest.raises(ValueError, match=r"pose: expected a tensor of shape \(B, 48\)"):
        mano_right(torch.zeros(2, 45))
    with pytest.raises(ValueError, match=r"betas: expected a tensor of shape \(2, 10\)"):
        mano_right(torch.zeros(2, 48), torch.zeros(3, 10))
    with pytest.raises(ValueError, match="tips must be"):
        load_mano(mano_right.path, tips="fingers")


def test_change_frame_moves_the_posed_hand_rigidly(mano_right):
    from hoidata.hand import change_frame

    pose, betas, transl = random_inputs(3, seed=11)
    rot = Rotation.random(random_state=12).as_matrix()
    shift = np.array([0.1, -0.2, 0.5])
    wrist = mano_right.rest_joints(betas)[:, 0].numpy()
    new_pose, new_transl = change_frame(pose.numpy(), transl.numpy(), wrist, rot, shift)
    before = mano_right(pose, betas, transl).vertices.numpy()
    after = mano_right(torch.as_tensor(new_pose), betas, torch.as_tensor(new_transl)).vertices.numpy()
    np.testing.assert_allclose(after, before @ rot.T + shift, atol=1e-10)
    assert np.array_equal(new_pose[:, 3:], pose.numpy()[:, 3:])
