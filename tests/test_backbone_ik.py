"""ResNet U-Net backbone (shapes, freezing, weight loading, gradients) and the MANO inverse kinematics."""

from __future__ import annotations

import math

import pytest
import torch
import torchvision
from torch import nn

from hoidata.geometry.rotation import axis_angle_to_matrix, matrix_to_axis_angle
from hoidata.errors import DataError
from hoisdf.model.backbone import BIG, DECODERS, SMALL, ResNetUNet, frozen_bn_parameters
from hoisdf.model.ik import kabsch_rotation, minimal_rotation, solve_ik

# ---------------------------------------------------------------------------------------------- backbone


@pytest.mark.parametrize("decoder, channels", [("small", [32, 16, 32, 64, 128]),
                                               pytest.param("big", [32, 64, 128, 256, 512], marks=pytest.mark.slow)])
def test_r18_shapes(decoder, channels):
    torch.manual_seed(0)
    net = ResNetUNet(depth=18, decoder=DECODERS[decoder])
    assert net.channels == channels
    pyramid, maps = net(torch.rand(2, 3, 64, 64))
    assert [tuple(f.shape) for f in pyramid] == [(2, c, 64 // s, 64 // s) for c, s in zip(channels, (2, 4, 8, 16, 32))]
    assert maps.shape == (2, 3, 32, 32)
    assert torch.isfinite(maps).all()


@pytest.mark.parametrize("decoder, total, first_fuse_in", [("small", 992, 96),
                                                          pytest.param("big", 3968, 192, marks=pytest.mark.slow)])
def test_r50_channels(decoder, total, first_fuse_in):
    net = ResNetUNet(depth=50, decoder=DECODERS[decoder]).eval()
    assert sum(net.channels) == net.feature_dim == total
    assert net.decoder.up2.fuse[0].in_channels == first_fuse_in
    if decoder == "small":  # one forward pass (the big decoder is slow on CPU)
        with torch.no_grad():
            pyramid, maps = net(torch.rand(1, 3, 64, 64))
        assert [f.shape[1] for f in pyramid] == net.channels == [32, 64, 128, 256, 512]
        assert maps.shape == (1, 3, 32, 32)
    else:
        assert net.channels == [128, 256, 512, 1024, 2048]


def test_heads_are_separate_stacks():
    net = ResNetUNet(depth=18, decoder=BIG)
    convs = [m for m in net.heatmap_head.modules() if isinstance(m, nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size) for c in convs] == [(32, 32, (1, 1)), (32, 16, (1, 1)),
                                                                                (16, 1, (1, 1))]
    assert not isinstance(list(net.heatmap_head.modules())[-1], (nn.ReLU, nn.BatchNorm2d))  # logits, no activation
    assert net.hand_mask_head[0][0].weight.data_ptr() != net.obj_mask_head[0][0].weight.data_ptr()


def test_decoder_init():
    net = ResNetUNet(depth=18, decoder=SMALL)
    w = torch.cat([m.weight.flatten() for m in net.decoder.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))])
    assert 0.5e-3 < w.std().item() < 2e-3
    assert all(m.bias.abs().max() == 0 for m in net.decoder.modules() if isinstance(m, nn.Conv2d))


def test_freeze_bn_affine():
    net = ResNetUNet(depth=18, freeze_bn_affine=True)
    frozen = {n for n, p in net.backbone.named_parameters() if not p.requires_grad}
    expected = {f"{n}.{k}" for n, m in net.backbone.named_modules()
                if isinstance(m, nn.BatchNorm2d) and "downsample" not in n for k in ("weight", "bias")}
    assert frozen == expected and len(expected) > 0
    assert net.backbone.layer2[0].downsample[1].weight.requires_grad
    assert all(p.requires_grad for p in net.decoder.parameters())
    assert len(frozen_bn_parameters(net.backbone)) == len(expected)
    # running statistics still update in train mode
    before = net.backbone.bn1.running_mean.clone()
    net.train()(torch.rand(2, 3, 32, 32))
    assert not torch.equal(before, net.backbone.bn1.running_mean)
    assert all(p.requires_grad for p in ResNetUNet(depth=18, freeze_bn_affine=False).parameters())


def test_normalize_input():
    torch.manual_seed(0)
    a = ResNetUNet(depth=18, normalize_input=True).eval()
    b = ResNetUNet(depth=18, normalize_input=False).eval()
    b.load_state_dict(a.state_dict())
    img = torch.rand(1, 3, 64, 64)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    with torch.no_grad():
        torch.testing.assert_close(a(img)[1], b((img - mean) / std)[1])
        assert not torch.allclose(a(img)[0][4], b(img)[0][4])


def test_imagenet_missing_raises(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    with pytest.raises(FileNotFoundError) as info:
        ResNetUNet(depth=18, weights="imagenet")
    assert str(tmp_path / "checkpoints" / "resnet18-f37072fd.pth") in str(info.value)


def test_imagenet_from_hub_cache(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    ref = torchvision.models.resnet18(weights=None)
    (tmp_path / "checkpoints").mkdir()
    torch.save(ref.state_dict(), tmp_path / "checkpoints" / "resnet18-f37072fd.pth")
    net = ResNetUNet(depth=18, weights="imagenet")
    torch.testing.assert_close(net.backbone.layer3[1].conv2.weight, ref.layer3[1].conv2.weight, rtol=0, atol=0)


def test_load_state_dict_file(tmp_path):
    torch.manual_seed(1)
    ref = torchvision.models.resnet18(weights=None)
    with torch.no_grad():
        ref.bn1.running_mean.uniform_()
    path = tmp_path / "r18.pth"
    torch.save(ref.state_dict(), path)
    net = ResNetUNet(depth=18, weights=str(path))
    theirs = ref.state_dict()
    for k, v in net.backbone.state_dict().items():
        assert torch.equal(v, theirs[k]), k
    assert not net.backbone.bn1.weight.requires_grad  # freezing applies after loading too
    with pytest.raises(DataError, match="missing.pth: backbone weights file not found"):
        ResNetUNet(depth=18, weights=str(tmp_path / "missing.pth"))
    torch.save({"conv1.weight": ref.conv1.weight}, tmp_path / "partial.pth")
    with pytest.raises(DataError, match="partial.pth: not ResNet-18 weights"):
        ResNetUNet(depth=18, weights=str(tmp_path / "partial.pth"))


@pytest.mark.slow
def test_gradients_reach_decoder_and_backbone():
    torch.manual_seed(0)
    net = ResNetUNet(depth=18, decoder=SMALL)
    pyramid, maps = net(torch.rand(2, 3, 64, 64))
    loss = sum(f.square().mean() for f in pyramid) + maps.square().mean()
    loss.backward()
    for module in (net.backbone.conv1, net.backbone.layer1[0].conv1, net.backbone.layer4[1].conv2,
                   net.decoder.up2.fuse[0], net.decoder.top[0], net.heatmap_head[-1][0], net.obj_mask_head[0][0]):
        assert module.weight.grad is not None and module.weight.grad.abs().sum() > 0
    assert net.backbone.bn1.weight.grad is None


@pytest.mark.slow
def test_channels_last_computes_the_same_numbers_as_nchw():
    """The NHWC layout changes memory order only: same state dict keys and values, same outputs and gradients."""
    torch.manual_seed(0)
    nhwc, nchw = ResNetUNet(depth=18, channels_last=True), ResNetUNet(depth=18)
    nchw.load_state_dict(nhwc.state_dict())
    assert nhwc.backbone.conv1.weight.is_contiguous(memory_format=torch.channels_last)
    assert nchw.backbone.conv1.weight.is_contiguous()
    img = torch.rand(2, 3, 64, 64)
    outs = []
    for net in (nhwc, nchw):
        pyramid, maps = net(img)
        (sum(f.square().mean() for f in pyramid) + maps.square().mean()).backward()
        outs.append((pyramid, maps, net.backbone.layer2[0].conv1.weight.grad))
    (p1, m1, g1), (p2, m2, g2) = outs
    assert p1[0].is_contiguous(memory_format=torch.channels_last) and p2[0].is_contiguous()
    for a, b in zip([*p1, m1, g1], [*p2, m2, g2]):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)  # float summation order differs


def test_bad_input_shape():
    net = ResNetUNet(depth=18)
    with pytest.raises(ValueError):
        net(torch.rand(1, 3, 60, 60))
    with pytest.raises(ValueError):
        ResNetUNet(depth=101)

# ---------------------------------------------------------------------------------------------- IK math


def _random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    aa = q[:, 1:] / q[:, 1:].norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=gen, dtype=torch.float64) * math.pi
    return axis_angle_to_matrix(aa)


def test_minimal_rotation():
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(100, 3, generator=gen, dtype=torch.float64)
    b = torch.randn(100, 3, generator=gen, dtype=torch.float64)
    b[0] = -2 * a[0]  # opposite
    b[1] = 3 * a[1]  # parallel
    aa = minimal_rotation(a, b)
    rotated = (axis_angle_to_matrix(aa) @ a[..., None])[..., 0]
    torch.testing.assert_close(rotated / rotated.norm(dim=1, keepdim=True), b / b.norm(dim=1, keepdim=True))
    expected_angle = torch.arccos(((a * b).sum(1) / a.norm(dim=1) / b.norm(dim=1)).clamp(-1, 1))
    torch.testing.assert_close(aa.norm(dim=1), expected_angle)
    assert aa[1].abs().max() < 1e-12 and abs(aa[0].norm().item() - math.pi) < 1e-9
    torch.testing.assert_close((aa * a).sum(1), torch.zeros(100, dtype=torch.float64), atol=1e-9, rtol=0)


def test_kabsch_reflection_fix():
    gen = torch.Generator().manual_seed(2)
    rot = _random_rotations(4, gen)
    src = torch.randn(4, 5, 3, generator=gen, dtype=torch.float64)
    dst = src @ rot.transpose(1, 2)
    torch.testing.assert_close(kabsch_rotation(src, dst), rot)
    mirrored = dst * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)  # best orthogonal fit is a reflection
    r = kabsch_rotation(src, mirrored)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(4, 3, 3))

# ---------------------------------------------------------------------------------------------- IK on MANO


def _random_hands(n: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    pose = torch.randn(n, 48, generator=gen, dtype=torch.float64) * 0.3
    rot = _random_rotations(n, gen)
    pose[:, :3] = matrix_to_axis_angle(rot)
    betas = torch.randn(n, 10, generator=gen, dtype=torch.float64) * 0.8
    return pose, betas


def test_ik_reproduces_joints(mano_right):
    pose, betas = _random_hands(16, seed=3)
    transl = torch.randn(16, 3, dtype=torch.float64) * 0.2
    joints = mano_right(pose, betas, transl).joints
    target = joints - joints[:, :1]
    pose_ik = solve_ik(target, betas, mano_right)
    assert pose_ik.shape == (16, 48) and pose_ik.dtype == torch.float64
    out = mano_right(pose_ik, betas).joints
    err = (out - out[:, :1] - target).norm(dim=-1)  # (B, 21) metres
    non_tip = [j for j in range(21) if j % 4 != 0]
    assert err[:, non_tip].max() < 1e-6  # the 16 MANO joints are reproduced exactly
    # tips are skinned vertices; the procedural hand moves them rigidly with the distal bone (real MANO: ~mm)
    assert err.max() < 1e-6
    # the global rotation is recovered exactly (wrist->MCP vectors do not depend on the finger pose)
    torch.testing.assert_close(axis_angle_to_matrix(pose_ik[:, :3]), axis_angle_to_matrix(pose[:, :3]))
    # a wrong bone frame (e.g. dropping the accumulated parent rotation) would break this: shift one joint's pose
    broken = pose_ik.clone()
    broken[:, 3:6] += 0.2
    out_b = mano_right(broken, betas).joints
    assert (out_b - out_b[:, :1] - target).norm(dim=-1).max() > 5e-3


def test_ik_zero_pose_identity(mano_right):
    betas = torch.randn(3, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * 0.5
    joints = mano_right(torch.zeros(3, 48, dtype=torch.float64), betas).joints
    pose_ik = solve_ik(joints - joints[:, :1], betas, mano_right)
    assert pose_ik.abs().max() < 1e-6


def test_ik_batched_equals_single(mano_right):
    pose, betas = _random_hands(5, seed=5)
    joints = mano_right(pose, betas).joints
    joints = joints - joints[:, :1]
    batched = solve_ik(joints, betas, mano_right)
    single = torch.cat([solve_ik(joints[i:i + 1], betas[i:i + 1], mano_right) for i in range(5)])
    torch.testing.assert_close(batched, single, atol=1e-10, rtol=0)


def test_ik_float32_input(mano_right):
    pose, betas = _random_hands(4, seed=6)
    joints = mano_right(pose, betas).joints
    pose_ik = solve_ik((joints - joints[:, :1]).float(), betas.float(), mano_right)
    assert pose_ik.dtype == torch.float32
    out = mano_right(pose_ik.double(), betas).joints
    assert (out - out[:, :1] - (joints - joints[:, :1])).norm(dim=-1).max() < 1e-5
