"""Tests of the model building blocks: encodings, pixel-aligned sampling, SDF decoder, transformer, rotations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.spatial.transform import Rotation

from hoidata.geometry.rotation import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    matrix_to_rot6d,
    quaternion_to_matrix,
    rot6d_to_matrix,
)
from hoisdf.model.encoding import (
    fourier_encode,
    pixel_aligned_features,
    pixel_to_grid,
    project_points,
    sample_pyramid,
)
from hoisdf.model.layers import MLP
from hoisdf.model.sdf_decoder import SDFDecoder, init_sdf_decoder_weights
from hoisdf.model.transformer import (
    QueryDecoder,
    TokenEncoder,
    init_transformer_weights,
    mano_query_mask,
    memory_mask,
)

# ----------------------------------------------------------------------------------------------- layers


def test_mlp_structure_and_relu_last():
    torch.manual_seed(0)
    head = MLP(8, [16, 16], 3)
    feat = MLP(8, [16], 4, relu_last=True)
    assert [m.out_features for m in head.layers if isinstance(m, torch.nn.Linear)] == [16, 16, 3]
    x = torch.randn(2, 5, 8)
    assert head(x).shape == (2, 5, 3)
    assert (head(x) < 0).any()  # linear last layer
    assert (feat(x) >= 0).all() and feat(x).shape == (2, 5, 4)


# --------------------------------------------------------------------------------------------- encoding


def test_fourier_layout_hand_computed():
    x = torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64)
    code = fourier_encode(x, n_freq=2)
    a, b, c = 0.1, -0.2, 0.3
    expected = [math.sin(a), math.sin(b), math.sin(c), math.cos(a), math.cos(b), math.cos(c),
                math.sin(2 * a), math.sin(2 * b), math.sin(2 * c), math.cos(2 * a), math.cos(2 * b), math.cos(2 * c)]
    assert torch.allclose(code[0], torch.tensor(expected, dtype=torch.float64))
    assert fourier_encode(torch.randn(2, 7, 3)).shape == (2, 7, 30)
    # highest default frequency is 16 (no pi factor)
    assert torch.allclose(fourier_encode(x)[0, 24:27], torch.sin(16 * x[0]))


def test_project_points_and_behind_camera():
    K = torch.tensor([[[100.0, 0, 50], [0, 200, 60], [0, 0, 1]]])
    pts = torch.tensor([[[0.1, -0.2, 2.0], [0.0, 0.0, -1.0], [0.1, 0.1, 0.0]]])
    uv = project_points(pts, K)
    assert torch.allclose(uv[0, 0], torch.tensor([55.0, 40.0]))
    assert torch.isfinite(uv).all()


def _ramp(size: int) -> torch.Tensor:
    """(1, 2, S, S) map with channel 0 = 10 v + u and channel 1 = u - 3 v + 100 (linear in the pixel centre)."""
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                          indexing="ij")
    return torch.stack([10 * v + u, u - 3 * v + 100])[None]


def test_sample_at_pixel_centres_and_half_pixel():
    S = 8
    fmap = _ramp(S)
    uv = torch.tensor([[[0.0, 0.0], [3.0, 5.0], [7.0, 7.0], [2.5, 5.0], [2.5, 4.5]]], dtype=torch.float64)
    out = sample_pyramid([fmap], pixel_to_grid(uv, S))
    assert out.shape == (1, 5, 2)
    expected0 = torch.tensor([0.0, 53.0, 77.0, 52.5, (42 + 43 + 52 + 53) / 4], dtype=torch.float64)
    assert torch.allclose(out[0, :, 0], expected0, atol=1e-9)
    # pixel-centre samples are exact copies of the stored values, for a non-linear map as well
    rnd = torch.randn(1, 3, S, S, dtype=torch.float64)
    iu, iv = torch.tensor([1, 6, 4]), torch.tensor([2, 0, 7])
    uv_int = torch.stack([iu, iv], -1)[None].to(torch.float64)
    got = sample_pyramid([rnd], pixel_to_grid(uv_int, S))[0]
    assert torch.allclose(got, rnd[0, :, iv, iu].T, atol=1e-12)


def test_pyramid_levels_are_consistent():
    """Average-pooled copies of a linear ramp, sampled at the same image location, give the same value."""
    S = 8
    fine = _ramp(S)
    levels = [fine, F.avg_pool2d(fine, 2), F.avg_pool2d(fine, 4)]
    # interior locations (inside the outermost pixel centres of the coarsest, 2x2 level: [1.5, 5.5])
    uv = torch.tensor([[[1.5, 1.5], [2.0, 3.0], [4.25, 5.5], [3.7, 2.2]]], dtype=torch.float64)
    out = sample_pyramid(levels, pixel_to_grid(uv, S))
    assert out.shape == (1, 4, 6)
    u, v = uv[0, :, 0], uv[0, :, 1]
    truth = torch.stack([10 * v + u, u - 3 * v + 100], -1)
    for level in range(3):  # concatenated in list order
        assert torch.allclose(out[0, :, 2 * level:2 * level + 2], truth, atol=1e-9)


def test_no_gradient_to_points_but_to_features():
    S = 16
    feats = [torch.randn(2, 4, S, S, requires_grad=True), torch.randn(2, 3, S // 2, S // 2, requires_grad=True)]
    K = torch.tensor([[200.0, 0, 8], [0, 200, 8], [0, 0, 1]]).expand(2, 3, 3)
    pts = (torch.randn(2, 10, 3) * 0.02 + torch.tensor([0, 0, 0.5])).requires_grad_(True)
    out = pixel_aligned_features(feats, pts, K, S)
    assert out.shape == (2, 10, 7)
    out.sum().backward()
    assert pts.grad is None
    assert feats[0].grad is not None and feats[0].grad.abs().sum() > 0
    grid = torch.zeros(2, 5, 2, requires_grad=True)
    sample_pyramid(feats, grid).sum().backward()
    assert grid.grad is None


# ------------------------------------------------------------------------------------------ SDF decoder


def _decoder_inputs(B: int = 2, N: int = 9, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(B, N, 3, generator=g) * 2 - 1
    return torch.randn(B, N, 256, generator=g), fourier_encode(xyz), xyz


def test_sdf_decoder_shapes_range_and_skip_width():
    torch.manual_seed(0)
    dec = SDFDecoder()
    assert dec.in_dim == 289
    lin = [layer for layer in dec.hidden_layers]
    assert [layer.in_features for layer in lin] == [289, 512, 512, 512]
    assert [layer.out_features for layer in lin] == [512, 223, 512, 512]
    assert all(hasattr(layer, "parametrizations") for layer in lin)
    n_params = sum(p.numel() for p in dec.parameters())
    expected = (289 * 512 + 2 * 512) + (512 * 223 + 2 * 223) + 2 * (512 * 512 + 2 * 512) + (512 + 1)
    assert n_params == expected
    dec.eval()
    out = dec(*_decoder_inputs())
    assert out.shape == (2, 9)
    assert (out.abs() < 1).all()
    with torch.no_grad():  # a huge output bias saturates the tanh but stays inside (-1, 1)
        dec.out_layer.bias.fill_(5.0)
    out = dec(*_decoder_inputs())
    assert (out > 0.99).all() and (out < 1).all()


def test_sdf_decoder_skip_carries_the_input():
    """With the first two layers zeroed, the output still depends on the input via the re-concatenation."""
    torch.manual_seed(0)
    dec = SDFDecoder(weight_norm=False).eval()
    with torch.no_grad():
        for layer in dec.hidden_layers[:2]:
            layer.weight.zero_()
            layer.bias.zero_()
    a = dec(*_decoder_inputs(seed=1))
    b = dec(*_decoder_inputs(seed=2))
    assert not torch.allclose(a, b)


def test_sdf_decoder_dropout_and_per_point_independence():
    torch.manual_seed(0)
    dec = SDFDecoder()
    feat, pe, xyz = _decoder_inputs(N=40)
    dec.train()
    assert not torch.allclose(dec(feat, pe, xyz), dec(feat, pe, xyz))
    dec.eval()
    full = dec(feat, pe, xyz)
    assert torch.equal(full, dec(feat, pe, xyz))
    # chunking / other points do not matter
    assert torch.allclose(dec(feat[:, :7], pe[:, :7], xyz[:, :7]), full[:, :7], atol=1e-6)
    feat2 = feat.clone()
    feat2[:, 1:] = torch.randn_like(feat2[:, 1:])
    assert torch.allclose(dec(feat2, pe, xyz)[:, 0], full[:, 0], atol=1e-6)


def test_sdf_decoder_upstream_init():
    torch.manual_seed(0)
    dec = SDFDecoder()
    w_before = dec.hidden_layers[0].weight.clone()
    init_sdf_decoder_weights(dec)
    assert torch.equal(dec.hidden_layers[0].weight, w_before)
    assert all((layer.bias == 0).all() for layer in dec.hidden_layers)
    assert (dec.out_layer.bias == 0).all() and dec.out_layer.weight.std() < 0.02


# ------------------------------------------------------------------------------------------ transformer

D, HEADS, FF = 32, 4, 64


def test_encoder_shapes_and_shared_inter_norm():
    torch.manual_seed(0)
    enc = TokenEncoder(3, D, HEADS, FF, 0.1).eval()
    with torch.no_grad():  # at init a LayerNorm of a LayerNorm output is ~identity: make the shared norm visible
        enc.inter_norm.weight.fill_(2.0)
    tokens = torch.randn(2, 11, D)
    inter, memory = enc(tokens)
    assert inter.shape == (3, 2, 11, D) and memory.shape == (2, 11, D)
    assert torch.allclose(inter[-1], enc.inter_norm(memory))
    assert not torch.allclose(inter[-1], memory)
    enc.train()
    assert not torch.allclose(enc(tokens)[1], enc(tokens)[1])  # dropout active


def test_decoder_shapes():
    torch.manual_seed(0)
    dec = QueryDecoder(4, 17, D, HEADS, FF, 0.1).eval()
    out = dec(torch.randn(3, 20, D), tgt_mask=mano_query_mask(), memory_mask=memory_mask(17, 20, 15))
    assert out.shape == (4, 3, 17, D)
    assert torch.isfinite(out).all()


def test_mano_query_mask_pattern():
    mask = mano_query_mask()
    assert mask.shape == (17, 17) and mask.dtype == torch.bool
    groups = [[0], [1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12], [13, 14, 15], [16]]
    expected = torch.ones(17, 17, dtype=torch.bool)
    for g in groups:
        for i in g:
            for j in g:
                expected[i, j] = False
    assert torch.equal(mask, expected)
    assert (~mask).sum() == 1 + 5 * 9 + 1


def test_memory_mask_blocks_hidden_tokens():
    torch.manual_seed(0)
    mm = memory_mask(17, 12, 8)
    assert mm.shape == (17, 12) and not mm[:, :8].any() and mm[:, 8:].all()
    dec = QueryDecoder(2, 17, D, HEADS, FF, 0.1).eval()
    memory = torch.randn(2, 12, D)
    ref = dec(memory, tgt_mask=mano_query_mask(), memory_mask=mm)
    hidden = memory.clone()
    hidden[:, 10] += 5 * torch.randn(D)
    assert torch.allclose(dec(hidden, tgt_mask=mano_query_mask(), memory_mask=mm), ref, atol=1e-6)
    visible = memory.clone()
    visible[:, 3] += 5 * torch.randn(D)
    assert not torch.allclose(dec(visible, tgt_mask=mano_query_mask(), memory_mask=mm), ref, atol=1e-3)
    # without the mask the hidden token matters
    assert not torch.allclose(dec(hidden, memory_mask=None), dec(memory, memory_mask=None), atol=1e-3)


def test_query_mask_isolates_groups():
    """Perturbing the positional embedding of query 1 changes only its triple {1, 2, 3}.

    tgt starts at zero, so the first self-attention mixes only (constant) values; from the second layer on the
    queries carry their own state, so without the mask query 1's change leaks into the other queries.
    """
    torch.manual_seed(0)
    dec = QueryDecoder(2, 17, D, HEADS, FF, 0.1).eval()
    memory = torch.randn(2, 10, D)
    mask = mano_query_mask()
    ref_masked, ref_free = dec(memory, tgt_mask=mask), dec(memory)
    with torch.no_grad():
        dec.query_embed.weight[1] += torch.randn(D)
    out_masked, out_free = dec(memory, tgt_mask=mask), dec(memory)
    others = [q for q in range(17) if q not in (1, 2, 3)]
    assert torch.allclose(out_masked[:, :, others], ref_masked[:, :, others], atol=1e-6)
    for q in (1, 2, 3):
        assert not torch.allclose(out_masked[-1, :, q], ref_masked[-1, :, q], atol=1e-4)
    assert not torch.allclose(out_free[-1, :, others], ref_free[-1, :, others], atol=1e-4)


def test_init_transformer_weights():
    torch.manual_seed(0)
    dec = QueryDecoder(2, 17, D, HEADS, FF, 0.1)
    emb = dec.query_embed.weight.clone()
    init_transformer_weights(dec)
    layer = dec.layers[0]
    assert torch.equal(dec.query_embed.weight, emb)
    assert abs(layer.ffn.linear1.weight.std().item() - 0.01) < 0.002
    assert (layer.ffn.linear1.bias == 0).all() and (layer.ffn.linear2.bias == 0).all()
    bound = math.sqrt(6 / (D + D))  # xavier on the attention output projection, not N(0, 0.01)
    assert layer.self_attn.out_proj.weight.abs().max() <= bound and layer.self_attn.out_proj.weight.std() > 0.05


# ------------------------------------------------------------------------------------------- rotations


def _test_axis_angles() -> torch.Tensor:
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(64, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, 40),
                             [0.0, 1e-9, 1e-6, 1e-4, 1e-3, 0.01, np.pi - 1e-2, np.pi - 1e-4, np.pi - 1e-6, np.pi,
                              np.pi, np.pi - 1e-8, 2.0, 3.0, 0.5, 1.0, 1e-3, 1e-7, 3.1, 3.14, 3.141, 3.1415,
                              0.3, 0.2]])
    return torch.from_numpy(axes * angles[:, None])


def test_axis_angle_to_matrix_matches_scipy():
    aa = _test_axis_angles()
    R = axis_angle_to_matrix(aa)
    ref = torch.from_numpy(Rotation.from_rotvec(aa.numpy()).as_matrix())
    assert torch.allclose(R, ref, atol=1e-12)
    assert torch.allclose(axis_angle_to_matrix(torch.zeros(3)), torch.eye(3, dtype=torch.float32))


def test_axis_angle_round_trip_all_angles():
    aa = _test_axis_angles()
    back = matrix_to_axis_angle(axis_angle_to_matrix(aa))
    assert torch.isfinite(back).all()
    angle = aa.norm(dim=-1)
    regular = angle < np.pi - 1e-3
    assert torch.allclose(back[regular], aa[regular], atol=1e-9)
    # near pi only the rotation is defined: aa and -aa (both of angle ~pi) are equivalent
    assert torch.allclose(back.norm(dim=-1), angle, atol=1e-6)
    near_pi = ~regular
    sign_ok = torch.minimum((back - aa).norm(dim=-1), (back + aa).norm(dim=-1))
    assert (sign_ok[near_pi] < 1e-5).all()
    assert torch.allclose(axis_angle_to_matrix(back), axis_angle_to_matrix(aa), atol=1e-9)
    # float32: no NaN, same rotation
    back32 = matrix_to_axis_angle(axis_angle_to_matrix(aa.float()))
    assert torch.isfinite(back32).all()
    assert torch.allclose(axis_angle_to_matrix(back32), axis_angle_to_matrix(aa.float()), atol=1e-5)


def test_quaternion_matches_scipy_and_round_trips():
    R = torch.from_numpy(Rotation.random(50, random_state=1).as_matrix())
    q = matrix_to_quaternion(R)
    ref = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_quat())[:, [3, 0, 1, 2]]  # (w, x, y, z)
    ref = torch.where(ref[:, :1] < 0, -ref, ref)
    assert torch.allclose(q, ref, atol=1e-12)
    assert torch.allclose(quaternion_to_matrix(q), R, atol=1e-12)


def test_rotation_gradients_finite_and_correct():
    R = torch.from_numpy(Rotation.random(3, random_state=2).as_matrix()).requires_grad_(True)
    assert torch.autograd.gradcheck(matrix_to_axis_angle, (R,))
    aa = (torch.randn(4, 3, dtype=torch.float64) * 0.7).requires_grad_(True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (aa,))
    small = torch.tensor([[1e-5, -2e-5, 0.5e-5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (small,))
    for f, x in ((axis_angle_to_matrix, torch.zeros(2, 3)), (matrix_to_axis_angle, torch.eye(3).expand(2, 3, 3))):
        x = x.clone().requires_grad_(True)
        f(x).sum().backward()
        assert torch.isfinite(x.grad).all()


def test_rot6d_round_trip_and_orthonormalisation():
    R = torch.from_numpy(Rotation.random(20, random_state=3).as_matrix())
    six = matrix_to_rot6d(R)
    assert six.shape == (20, 6)
    assert torch.allclose(rot6d_to_matrix(six), R, atol=1e-12)
    x = torch.randn(5, 7, 6, dtype=torch.float64) * 3
    M = rot6d_to_matrix(x)
    eye = torch.eye(3, dtype=torch.float64).expand_as(M)
    assert torch.allclose(M.transpose(-1, -2) @ M, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(M), torch.ones(5, 7, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(M[..., 0], F.normalize(x[..., :3], dim=-1))  # first column along a1
    assert ((M[..., 1] * x[..., 3:]).sum(-1) > 0).all()  # second column in the (a1, a2) half-plane of a2


@pytest.mark.parametrize("shape", [(3,), (2, 4, 3)])
def test_rotation_batch_shapes(shape):
    aa = torch.randn(*shape)
    R = axis_angle_to_matrix(aa)
    assert R.shape == (*shape[:-1], 3, 3)
    assert matrix_to_axis_angle(R).shape == shape
    assert rot6d_to_matrix(matrix_to_rot6d(R)).shape == R.shape
