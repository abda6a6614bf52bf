"""Upstream's initialisation and targets as settings (issue 31, items 4 and 5): the SDF decoders' training init in
every model, ``model.rot6d = "raw"``, ``model.beta_floor = "project"`` and ``augment.heatmap_target = "upstream"``.
The whole training step against upstream's own is tests/test_train_step_upstream.py."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from hoidata.hand import load_mano
from hoisdf.config import ModelSettings, load_train_config
from hoisdf.data.augment import AugmentSettings, heatmap_target, render_heatmap
from hoisdf.model import build as B
from hoisdf.model import build_model

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
        "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16"]


def _tiny(*overrides) -> ModelSettings:
    return load_train_config(None, TINY + list(overrides)).model


def _batch() -> dict:
    K = torch.tensor([[[60.0, 0.0, 31.5], [0.0, 60.0, 31.5], [0.0, 0.0, 1.0]]])
    return {"img": torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0)), "K": K,
            "hand_root": torch.tensor([[0.0, 0.0, 0.5]]), "obj_center": torch.tensor([[0.02, 0.0, 0.5]]),
            "hand_box": torch.tensor([[0.0, 0.0, 63.0, 63.0]]), "object_box": torch.tensor([[0.0, 0.0, 63.0, 63.0]])}


def test_the_new_choices_are_the_builders_tables():
    assert set(ModelSettings.CHOICES["rot6d"]) == set(B.RAW_6D)
    assert set(ModelSettings.CHOICES["beta_floor"]) == set(B.PROJECT_BETA)
    with pytest.raises(ValueError, match="model.rot6d"):
        load_train_config(None, TINY + ['model.rot6d="quaternion"'])
    with pytest.raises(ValueError, match="heatmap_target"):
        AugmentSettings(heatmap_target="summed")


def test_build_model_gives_the_sdf_decoders_upstreams_init():
    """Upstream's ``apply(init_weights)``: zero biases, N(0, 0.01) output layer. Before it was wired, the decoders
    kept PyTorch's default init (biases up to +-1/sqrt(fan_in), output weights ~0.04)."""
    torch.manual_seed(0)
    model = build_model(_tiny(), None)
    for decoder in (model.fields.hand_sdf, model.fields.obj_sdf):
        assert all(float(layer.bias.detach().abs().max()) == 0.0 for layer in decoder.hidden_layers)
        assert float(decoder.out_layer.bias.detach().abs().max()) == 0.0
        assert 0.008 < float(decoder.out_layer.weight.detach().std()) < 0.012


def test_other_modules_keep_the_weights_their_seed_gave_them(monkeypatch):
    """The decoder init is drawn last: wiring it changed no other initial weight of a seed (the build without it
    is the build before it was wired); the new settings draw nothing."""
    torch.manual_seed(3)
    wired = build_model(_tiny(), None).state_dict()
    torch.manual_seed(3)
    other = build_model(_tiny('model.rot6d="raw"', 'model.beta_floor="project"', 'model.field_density="ranking"'),
                        None).state_dict()
    monkeypatch.setattr(B, "init_sdf_decoder_weights", lambda decoder: None)
    torch.manual_seed(3)
    before = build_model(_tiny(), None).state_dict()
    assert wired.keys() == other.keys() == before.keys()
    assert all(torch.equal(wired[k], other[k]) for k in wired)
    changed = {k for k in wired if not torch.equal(wired[k], before[k])}
    assert changed == {f"fields.{d}_sdf.{p}" for d in ("hand", "obj") for p in
                       ("hidden_layers.0.bias", "hidden_layers.1.bias", "hidden_layers.2.bias", "hidden_layers.3.bias",
                        "out_layer.weight", "out_layer.bias")}


@pytest.mark.slow
def test_raw_6d_is_the_offset_head_with_the_identity_in_its_bias(mano_dir):
    mano = load_mano(mano_dir, side="right")
    torch.manual_seed(1)
    offset = build_model(_tiny(), mano).eval()
    raw = build_model(_tiny('model.rot6d="raw"'), mano).eval()
    state = offset.state_dict()
    raw.load_state_dict(state)
    with torch.no_grad():
        a = offset(_batch())
        b = raw(_batch())
        assert not torch.allclose(a["rotations"], b["rotations"], atol=1e-3)  # the same weights: another code
        last = raw.pose.regressor.mano_head.pose.layers[-1].bias
        last += torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])
        b = raw(_batch())
    assert torch.allclose(a["rotations"], b["rotations"], atol=1e-6)
    assert torch.allclose(a["mano_verts"], b["mano_verts"], atol=1e-6)
    assert float(raw.pose.regressor.mano_head.identity_6d.abs().max()) == 0.0 and "identity_6d" not in raw.state_dict()


@pytest.mark.slow
@pytest.mark.parametrize("floor", ["clamp", "project"])
def test_beta_below_its_floor(floor, mano_dir):
    """Upstream projects the width itself (``beta.data.copy_(max(beta.data, 2e-3))``), so it keeps a gradient;
    ``clamp`` floors it in the forward only, where the gradient of a width below the floor is zero."""
    torch.manual_seed(2)
    settings = _tiny(f'model.beta_floor="{floor}"', 'model.pose_regressor="voting"', "model.beta_min=0.05")
    model = build_model(settings, load_mano(mano_dir, side="right")).train()
    with torch.no_grad():
        model.widths.hand_beta.fill_(0.04)  # below the floor, not so small that the density saturates
    out = model(_batch())
    out["vote_joints"].square().sum().backward()
    if floor == "project":
        assert float(model.widths.hand_beta.detach()) == pytest.approx(0.05) and float(model.widths.hand_beta.grad) != 0.0
    else:
        assert float(model.widths.hand_beta.detach()) == pytest.approx(0.04) and float(model.widths.hand_beta.grad) == 0.0


def test_upstream_heatmap_target_sums_on_the_integer_grid():
    """Upstream renders ``uv / 256 * 128`` on the integer grid and sums the Gaussians (x255 in the loss); the project's
    own target maps pixel centres (0.25 heatmap px away) and clips the sum at 1."""
    uv = torch.tensor([[[40.0, 60.0], [40.0, 60.0], [200.0, 10.0]]])  # two joints on one pixel
    up = heatmap_target(uv, 256, 128, 1.25, "upstream")
    mine = heatmap_target(uv, 256, 128, 1.25, "clipped")
    assert float(up[0, 0, 30, 20]) == pytest.approx(2.0) and float(up[0, 0, 5, 100]) == pytest.approx(1.0)
    assert float(mine.max()) == pytest.approx(1.0)
    assert torch.allclose(mine, render_heatmap(uv * 0.5 - 0.25, 128, 1.25))
    assert torch.allclose(up, render_heatmap(uv * 0.5, 128, 1.25, clip=False))
    grid = torch.arange(128.0)
    x, y = 100.0, 5.0
    expected = torch.exp(-((grid[None, :] - x) / 1.25) ** 2 / 2 - ((grid[:, None] - y) / 1.25) ** 2 / 2)
    assert torch.allclose(up[0, 0] - render_heatmap(uv[:, :2] * 0.5, 128, 1.25, clip=False)[0, 0], expected, atol=1e-6)
    assert replace(AugmentSettings(), heatmap_target="upstream").heatmap_target == "upstream"


@pytest.mark.slow
def test_field_tokens_can_take_the_ranking_pass_sdf(mano_dir):
    """``model.field_density = "ranking"``: the field-guided tokens carry the SDF of the ranking pass, dropout mask
    included (upstream's ``sdf_infer`` values); "fresh" decodes the points again with a new mask. In eval mode
    (no dropout) both give the same values."""
    mano = load_mano(mano_dir, side="right")
    for mode in ("fresh", "ranking"):
        torch.manual_seed(4)
        model = build_model(_tiny(f'model.field_density="{mode}"', "model.sdf_dropout=0.5"), mano).train()
        ranked = []
        field_points = model.sampler.field_points

        def spy(*args, **kwargs):
            points, sdf = field_points(*args, **kwargs)
            ranked.append(sdf)
            return points, sdf

        model.sampler.field_points = spy
        with torch.no_grad():
            out = model(_batch(), points="field")
            expected = ranked[0][0].clamp(-model.clamp, model.clamp) / model.scale
            same = torch.allclose(out["hand_query_sdf"], expected, atol=1e-7)
            assert same == (mode == "ranking"), mode
            model.eval()
            ranked.clear()
            out = model(_batch(), points="field")
            assert torch.allclose(out["hand_query_sdf"], ranked[0][0].clamp(-model.clamp, model.clamp) / model.scale,
                                  atol=1e-6)


@pytest.mark.parametrize("target, peak", [("upstream", 2.0), ("clipped", 1.0)])
def test_loader_augmented_batches_take_the_heatmap_target_setting(target, peak):
    """Batches augmented in the loader (augment.upstream) get the heatmap target the settings name: two joints on
    one pixel of upstream's uv / 256 * 128 grid sum to 2 under "upstream" (they were clipped at 1 before the fix)."""
    from hoisdf.data.augment import AugmentSettings, upstream_batch

    joints = torch.full((1, 21, 2), 300.0)  # far outside the 128 px map: contributes nothing
    joints[0, :2] = torch.tensor([100.0, 60.0])  # two joints on the heatmap pixel (50, 30)
    batch = {"img": torch.zeros(1, 3, 256, 256, dtype=torch.uint8), "seg": torch.zeros(1, 4, 128, 128),
             "joints_2d": joints, "object_anchor": torch.zeros(1, 3), "upstream_aug": torch.ones(1, dtype=torch.bool)}
    out = upstream_batch(batch, AugmentSettings(upstream=True, heatmap_target=target))
    assert out["heatmap"].shape == (1, 1, 128, 128)
    assert float(out["heatmap"][0, 0, 30, 50]) == pytest.approx(peak, rel=1e-6)
