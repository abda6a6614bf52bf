"""Augmentation keeps image, intrinsics, joints, masks, SDF samples, object pose and MANO pose consistent."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from hoidata import schema
from hoidata.geometry.rotation import matrix_to_axis_angle
from hoidata.store import KEY, iter_records
from hoisdf.data import StoreSpec, build_dataset
from hoisdf.data.augment import (
    AugmentSettings,
    adjust_hue,
    augment_batch,
    color_jitter,
    float_image,
    gaussian_blur,
    mask_planes,
    rotation_z,
    unpack_masks,
)
from hoisdf.model.encoding import project_points

# strong geometric augmentation; colour and blur off where pixels are compared
GEOMETRY = AugmentSettings(input_size=64, rotation="uniform", scale_sigma=0.3, color=False, blur_max=0.0)
FULL = AugmentSettings(input_size=64, rotation="uniform", scale_sigma=0.3)
TENSOR_KEYS = ("img", "seg", "heatmap", "K", "joints_3d", "joints_2d", "hand_root", "hand_points", "obj_points",
               "mano_pose", "object_pose", "hand_box", "object_box", "obj_center", "rotation", "crop_scale")


@pytest.fixture(scope="module")
def batch(tiny_store):
    """The first batch of 4 holding both a right-hand and a mirrored (left) record."""
    dataset = build_dataset([StoreSpec(tiny_store)], batch_size=4, training=True, n_hand=64, n_object=32)
    for _, candidate in zip(range(8), dataset):
        if 0 < int(candidate["mirrored"].sum()) < 4:
            return candidate
    raise AssertionError("no batch mixes right and mirrored records")


@pytest.fixture(scope="module")
def augmented(batch):
    out = augment_batch(batch, GEOMETRY, torch.Generator().manual_seed(3), train=True)
    angles = torch.atan2(out["rotation"][:, 1, 0], out["rotation"][:, 0, 0]).abs()
    assert angles.max() > 0.5 and out["crop_scale"].std() > 0.01  # the augmentation is really on
    return out


def _bilinear(image: np.ndarray, u: float, v: float) -> np.ndarray:
    """(C, H, W) sampled at continuous pixel (u, v), zeros outside."""
    padded = np.pad(image, ((0, 0), (1, 1), (1, 1)))
    x0, y0 = math.floor(u), math.floor(v)
    fx, fy = u - x0, v - y0
    out = np.zeros(image.shape[0])
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        x, y = x0 + dx + 1, y0 + dy + 1
        if 0 <= x < padded.shape[2] and 0 <= y < padded.shape[1]:
            out += w * padded[:, y, x]
    return out


def _output_to_source(out: dict, i: int) -> np.ndarray:
    """(3, 3) output pixel -> stored pixel of sample i, from K, K' and the rotation alone: K rot^T K'^-1."""
    return (out["K_in"][i] @ out["rotation"][i].T @ torch.linalg.inv(out["K"][i])).double().numpy()


@pytest.mark.slow
def test_joints_project_with_new_intrinsics(batch, augmented):
    assert (project_points(augmented["joints_3d"], augmented["K"]) - augmented["joints_2d"]).abs().max() < 1e-3
    rot = augmented["rotation"]
    assert torch.allclose(rot @ rot.transpose(1, 2), torch.eye(3).expand_as(rot), atol=1e-6)
    assert torch.allclose(augmented["hand_root"], augmented["joints_3d"][:, 0], atol=1e-6)
    assert torch.allclose(augmented["K"][:, 2], torch.tensor([0.0, 0.0, 1.0]).expand(4, 3))
    assert torch.allclose(augmented["K"][:, 0, 0] / batch["K"][:, 0, 0], augmented["crop_scale"])
    # the object pseudo-centre projects onto the object box centre at the hand root's depth
    box = augmented["object_box"]
    centre = project_points(augmented["obj_center"][:, None], augmented["K"])[:, 0]
    assert torch.allclose(centre, 0.5 * (box[:, :2] + box[:, 2:]), atol=1e-3)
    assert torch.allclose(augmented["obj_center"][:, 2], augmented["hand_root"][:, 2])


@pytest.mark.slow
def test_rotated_crop_keeps_the_stored_centre_in_the_middle(batch):
    """Rotation about the optical axis moves the crop centre; the crop follows it (no jitter, scale 1)."""
    settings = AugmentSettings(input_size=64, rotation="uniform", center_jitter=0.0, scale_sigma=0.0)
    out = augment_batch(batch, settings, torch.Generator().manual_seed(4), train=True)
    centre = torch.tensor([63.5, 63.5, 1.0]).expand(4, 3)[..., None]  # the stored 128 px crop's centre
    moved = out["K"] @ out["rotation"] @ torch.linalg.solve(batch["K"], centre)
    torch.testing.assert_close(moved[:, :2, 0], torch.full((4, 2), 31.5), atol=1e-3, rtol=0)
    torch.testing.assert_close(out["crop_scale"], torch.ones(4))


@pytest.mark.slow
def test_boxes_contain_the_moved_box_corners(batch, augmented):
    for name in ("hand_box", "object_box"):
        x1, y1, x2, y2 = batch[name].unbind(1)
        corners = torch.stack([torch.stack([x1, y1], 1), torch.stack([x2, y2], 1)], 1)  # (B, 2, 2)
        rays = torch.linalg.solve(batch["K"], torch.cat([corners, torch.ones(4, 2, 1)], 2).transpose(1, 2))
        moved = project_points((augmented["rotation"] @ rays).transpose(1, 2), augmented["K"])
        new = augmented[name]
        assert (moved >= new[:, None, :2] - 1e-3).all() and (moved <= new[:, None, 2:] + 1e-3).all()


def _distance_check(mesh: trimesh.Trimesh, points: torch.Tensor, sdf: torch.Tensor) -> int:
    """|sdf| of near-surface points equals their distance to ``mesh`` within 1 mm; returns how many were checked."""
    near = sdf.abs() < 0.02
    _, dist, _ = trimesh.proximity.closest_point(mesh, points[near].double().numpy())
    np.testing.assert_allclose(dist, sdf[near].abs().double().numpy(), atol=1e-3)
    return int(near.sum())


@pytest.mark.slow
def test_hand_sdf_samples_follow_the_rotated_mano_mesh(augmented, mano_right):
    checked = 0
    for i in torch.nonzero(~augmented["mirrored"])[:, 0].tolist():
        with torch.no_grad():
            mano = mano_right(augmented["mano_pose"][i:i + 1].double(), augmented["mano_betas"][i:i + 1].double())
        shift = augmented["hand_root"][i].double() - mano.joints[0, 0]
        mesh = trimesh.Trimesh((mano_right.close(mano.vertices)[0] + shift).numpy(), mano_right.closed_faces,
                               process=False)
        root = augmented["hand_root"][i]
        for prefix in ("hand", "hand_near"):
            checked += _distance_check(mesh, augmented[f"{prefix}_points"][i] + root, augmented[f"{prefix}_sdf"][i])
    assert checked >= 20


@pytest.mark.slow
def test_object_sdf_samples_follow_the_new_object_pose(augmented, tiny_dexycb):
    from hoidata.objects import class_name, load_object_mesh, object_mesh_path

    checked = 0
    for i in range(4):
        mesh = load_object_mesh(object_mesh_path(tiny_dexycb / "models", class_name(int(augmented["object_id"][i]))))
        vertices = np.asarray(mesh.vertices, np.float64)
        if augmented["mirrored"][i]:  # a mirrored record's pose places the x-mirrored model
            vertices = vertices * np.array([-1.0, 1.0, 1.0])
        pose = augmented["object_pose"][i].double().numpy()
        posed = trimesh.Trimesh(vertices @ pose[:3, :3].T + pose[:3, 3], mesh.faces, process=False)
        root = augmented["hand_root"][i]
        for prefix in ("obj", "obj_near"):
            checked += _distance_check(posed, augmented[f"{prefix}_points"][i] + root, augmented[f"{prefix}_sdf"][i])
    assert checked >= 20


@pytest.mark.slow
def test_image_and_masks_follow_the_new_intrinsics(batch, augmented):
    out = dict(augmented, K_in=batch["K"])
    size, half = GEOMETRY.input_size, GEOMETRY.input_size // 2
    compared, inside, hand_pixels = 0, [], 0
    for i in range(4):
        to_source = _output_to_source(out, i)
        source_img, source_seg = float_image(batch["img"])[i].double().numpy(), mask_planes(batch)[i].bool().numpy()
        # the image at each joint's pixel is the stored image at the matching source pixel
        for u, v in out["joints_2d"][i].round().long().tolist():
            if 0 <= u < size and 0 <= v < size:
                su, sv, _ = to_source @ np.array([u, v, 1.0])
                np.testing.assert_allclose(out["img"][i, :, v, u].numpy(), _bilinear(source_img, su, sv), atol=1e-4)
                compared += 1
        # joints well inside the visible-hand mask before are inside it after
        old = (0.5 * batch["joints_2d"][i] - 0.25).round().long().clamp(1, half * 2 - 2)
        new = (0.5 * out["joints_2d"][i] - 0.25).round().long().clamp(0, half - 1)
        for (ou, ov), (nu, nv) in zip(old.tolist(), new.tolist()):
            if source_seg[0, ov - 1:ov + 2, ou - 1:ou + 2].all():
                inside.append(bool(out["seg"][i, 0, nv, nu]))
        # dense: every output mask pixel whose source neighbourhood is uniform takes that value
        jh, ih = np.meshgrid(np.arange(half), np.arange(half))
        full = np.stack([2 * jh + 0.5, 2 * ih + 0.5, np.ones_like(jh, dtype=float)], -1) @ to_source.T
        src = np.rint(0.5 * full[..., :2] - 0.25).astype(int)
        ok = ((src >= 1) & (src <= source_seg.shape[-1] - 2)).all(-1)
        padded = np.pad(source_seg, ((0, 0), (1, 1), (1, 1)))
        windows = np.lib.stride_tricks.sliding_window_view(padded, (3, 3), axis=(1, 2))  # [p, v, u]: around (u, v)
        src = src.clip(0, source_seg.shape[-1] - 1)
        for plane in range(4):
            win = windows[plane, src[..., 1], src[..., 0]]
            uniform = ok & (win.all((-1, -2)) | ~win.any((-1, -2)))
            expected = win[..., 1, 1]
            assert (out["seg"][i, plane].numpy()[uniform] == expected[uniform]).all()
            hand_pixels += int((expected & uniform).sum()) if plane == 0 else 0
    assert compared >= 20 and hand_pixels >= 20
    assert len(inside) >= 5 and np.mean(inside) >= 0.9


@pytest.mark.slow
def test_eval_is_the_central_crop(batch, tiny_store):
    out = augment_batch(batch, AugmentSettings(input_size=64), None, train=False)
    torch.testing.assert_close(out["img"], float_image(batch["img"])[:, :, 32:96, 32:96], atol=1e-5, rtol=0)
    assert torch.equal(out["seg"], unpack_masks(batch["seg_bits"])[:, :, 16:48, 16:48])
    # the heatmap rendered from the joints is the one the store holds (which the loader no longer sends)
    stored = {r[KEY]: r[schema.HEATMAP] for r in iter_records(tiny_store)}
    heatmaps = torch.stack([torch.from_numpy(stored[k])[None] for k in batch["key"]])
    torch.testing.assert_close(out["heatmap"], float_image(heatmaps)[:, :, 16:48, 16:48], atol=0.01, rtol=0)
    shift = torch.tensor([[1.0, 0, -32], [0, 1, -32], [0, 0, 1]])
    torch.testing.assert_close(out["K"], shift @ batch["K"])
    torch.testing.assert_close(out["joints_2d"], batch["joints_2d"] - 32)
    torch.testing.assert_close(out["hand_box"], batch["hand_box"] - 32)
    for key in ("joints_3d", "hand_root", "hand_points", "obj_points", "object_pose", "mano_pose"):
        torch.testing.assert_close(out[key], batch[key], atol=1e-6, rtol=0)
    assert torch.equal(out["rotation"], torch.eye(3).expand(4, 3, 3)) and torch.equal(out["crop_scale"], torch.ones(4))


@pytest.mark.slow
def test_untouched_entries_pass_through(batch, augmented):
    for key in ("hand_sdf", "obj_sdf", "hand_near_sdf", "hand_rows", "obj_near_rows", "mano_betas", "object_id",
                "mirrored", "is_synthetic", "key"):
        assert augmented[key] is batch[key]
    assert augmented["seg"].dtype == torch.float32 and set(augmented["seg"].unique().tolist()) <= {0.0, 1.0}
    assert "seg_bits" in batch and "seg_bits" not in augmented  # the packed masks are replaced by their planes
    assert augmented["heatmap"].shape == (4, 1, 32, 32) and augmented["heatmap"].max() <= 1.0


@pytest.mark.slow
def test_same_seed_same_output(batch):
    first, again, other = (augment_batch(batch, FULL, torch.Generator().manual_seed(seed), train=True)
                           for seed in (5, 5, 6))
    for key in TENSOR_KEYS:
        assert torch.equal(first[key], again[key]), key
    assert not torch.allclose(first["img"], other["img"]) and not torch.allclose(first["K"], other["K"])


@pytest.mark.slow
def test_mano_global_rotation_rotates_the_wrist_centred_mesh(batch, augmented, mano_right):
    with torch.no_grad():
        before = mano_right(batch["mano_pose"].double(), batch["mano_betas"].double())
        after = mano_right(augmented["mano_pose"].double(), augmented["mano_betas"].double())
    centred_before = before.vertices - before.joints[:, :1]
    centred_after = after.vertices - after.joints[:, :1]
    expected = centred_before @ augmented["rotation"].double().transpose(1, 2)
    assert (centred_after - expected).abs().max() < 1e-5


def test_rotation_z_turns_x_towards_y():
    rot = rotation_z(torch.tensor([math.pi / 2, 0.3]))
    torch.testing.assert_close(rot[0] @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]))
    torch.testing.assert_close(matrix_to_axis_angle(rot)[1], torch.tensor([0.0, 0, 0.3]))


def test_colour_and_blur_identities_and_effects():
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    identity = torch.tensor([[1.0, 1.0, 1.0, 0.0]] * 2)
    torch.testing.assert_close(color_jitter(img, identity, torch.arange(4)), img)
    torch.testing.assert_close(gaussian_blur(img, torch.zeros(2), 2), img)
    torch.testing.assert_close(adjust_hue(img, torch.ones(2)), img, atol=1e-5, rtol=0)  # a full turn
    grey = torch.tensor([0.299, 0.587, 0.114])
    shifted = adjust_hue(img, torch.tensor([0.1, -0.15]))
    torch.testing.assert_close(torch.einsum("c,bchw->bhw", grey, shifted), torch.einsum("c,bchw->bhw", grey, img))
    assert (shifted - img).abs().max() > 0.05
    desaturated = color_jitter(img, torch.tensor([[1.0, 1.0, 0.0, 0.0]] * 2), torch.arange(4))
    assert (desaturated.std(1)).max() < 1e-6  # saturation 0: grey pixels
    flat = color_jitter(img, torch.tensor([[1.0, 0.0, 1.0, 0.0]] * 2), torch.arange(4))  # contrast 0
    mean_grey = torch.einsum("c,bchw->b", grey, img) / 256
    torch.testing.assert_close(flat, mean_grey[:, None, None, None].expand_as(img))
    brighter = color_jitter(img, torch.tensor([[1.5, 1.0, 1.0, 0.0]] * 2), torch.arange(4))
    torch.testing.assert_close(brighter, (1.5 * img).clamp(max=1.0))
    blurred = gaussian_blur(img, torch.tensor([0.0, 1.0]), 3)
    torch.testing.assert_close(blurred[0], img[0])
    assert blurred[1].std() < 0.7 * img[1].std()
    torch.testing.assert_close(blurred[1].mean(), img[1].mean(), atol=0.02, rtol=0)


@pytest.mark.slow
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(batch):
    cpu = augment_batch(batch, FULL, torch.Generator().manual_seed(7), train=True)
    moved = {k: v.cuda() if torch.is_tensor(v) else v for k, v in batch.items()}
    gpu = augment_batch(moved, FULL, torch.Generator().manual_seed(7), train=True)
    for key in TENSOR_KEYS:
        assert gpu[key].device.type == "cuda"
        torch.testing.assert_close(gpu[key].cpu(), cpu[key], atol=1e-3, rtol=1e-4)
