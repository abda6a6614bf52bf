"""model.pixel_convention: "upstream" samples the pyramid as the released code does (amathislab/HOISDF
main/model.py: ``grid_sample(..., padding_mode="border", align_corners=True)`` at ``(uv - 127.5) / 127.5``);
the grid is ranked by the unclamped SDF, as the released ``sdf_infer`` does."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from hoisdf.config import ModelSettings, load_train_config
from hoisdf.model import build_model
from hoisdf.model.encoding import CENTERS, PIXEL_CONVENTIONS, UPSTREAM, pixel_aligned_features, pixel_to_grid
from hoisdf.model.heads import masks_to_boxes
from hoisdf.model.sampling import inside_box

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=2",
        "model.decoder_layers=2", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16"]


def _reference_features(pyramid, points_cam, K, size):
    """The released code's lines, written out: projection, normalizer = (S-1)/2, align_corners=True."""
    uv = torch.bmm(points_cam, K.transpose(1, 2))
    uv = uv[..., :2] / uv[..., 2:]
    normalizer = torch.tensor([size - 1, size - 1]) / 2
    grids = ((uv - normalizer) / normalizer).unsqueeze(1)
    out = [F.grid_sample(f, grids, padding_mode="border", align_corners=True) for f in pyramid]
    return torch.cat(out, dim=1).squeeze(2).permute(0, 2, 1)


def test_upstream_convention_samples_where_the_released_code_samples():
    g = torch.Generator().manual_seed(0)
    pyramid = [torch.randn(2, c, s, s, generator=g) for c, s in ((3, 128), (4, 64), (5, 32), (6, 16), (7, 8))]
    K = torch.tensor([[480.0, 0, 130.5], [0, 480.0, 125.0], [0, 0, 1]]).expand(2, 3, 3)
    points = torch.randn(2, 50, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 0.6])
    ours = pixel_aligned_features(pyramid, points, K, 256, convention=UPSTREAM)
    ref = _reference_features(pyramid, points, K, 256)
    assert (ours - ref).abs().max() < 1e-6
    centers = pixel_aligned_features(pyramid, points, K, 256)
    assert (centers - ref).abs().max() > 1e-2  # the two conventions really sample elsewhere


def test_conventions_agree_at_the_centre_and_differ_at_the_border():
    uv = torch.tensor([[[127.5, 127.5], [0.0, 255.0]]])
    up, ce = pixel_to_grid(uv, 256, UPSTREAM), pixel_to_grid(uv, 256)
    assert torch.equal(up[0, 0], torch.zeros(2)) and torch.allclose(ce[0, 0], torch.zeros(2))
    assert torch.equal(up[0, 1], torch.tensor([-1.0, 1.0]))  # pixel 0 / 255 are the outer corner samples
    assert PIXEL_CONVENTIONS == {"centers": CENTERS, "upstream": UPSTREAM} and torch.equal(ce, CENTERS.to_grid(uv, 256))


def test_mask_boxes_follow_the_convention():
    mask = torch.zeros(1, 8, 8)
    mask[0, 2:5, 1:4] = 1.0  # rows 2-4, columns 1-3 of an 8 px map of a 64 px input
    assert masks_to_boxes(mask, 0.5, 64).tolist() == [[7.5, 15.5, 31.5, 39.5]]
    s = 63 / 7  # upstream: mask pixel i sits at input pixel i * (S-1)/(w-1)
    expected = torch.tensor([[0.5 * s, 1.5 * s, 3.5 * s, 4.5 * s]])
    assert torch.allclose(masks_to_boxes(mask, 0.5, 64, UPSTREAM), expected)


def test_project_default_stays_pixel_centres():
    assert ModelSettings().pixel_convention == "centers"
    with pytest.raises(ValueError, match="pixel_convention"):
        build_model(load_train_config(None, TINY + ['model.pixel_convention="corners"']).model, None)


@pytest.mark.parametrize("project_grid", [pytest.param(False, marks=pytest.mark.slow), True])
def test_grid_ranked_by_the_unclamped_sdf(mano_dir, project_grid):
    """Every in-box grid point has |SDF| beyond the clamp: the picks are still the n smallest unclamped |SDF|
    (clamped values would all tie at 0.15 and the picks would be the first n in grid order)."""
    from hoidata.hand import load_mano

    torch.manual_seed(0)
    cfg = load_train_config(None, TINY + ['model.pixel_convention="upstream"', "model.sheared_grid=true"])
    model = build_model(cfg.model, load_mano(mano_dir, side="right")).eval()
    model.features.project_grid = project_grid
    with torch.no_grad():
        for dec in (model.fields.hand_sdf, model.fields.obj_sdf):
            dec.out_layer.bias.fill_(0.6)  # tanh output ~0.5 everywhere: far beyond the 0.15 clamp
    K = torch.tensor([[[90.0, 0, 32], [0, 90.0, 32], [0, 0, 1]]])
    root, center = torch.tensor([[0.0, 0.0, 0.5]]), torch.tensor([[0.03, 0.0, 0.5]])
    box = torch.tensor([[10.0, 12.0, 50.0, 52.0]])
    img = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        pyramid, _ = model.backbone(img)
        hand, _ = model._query_points({}, pyramid, K, root, center, (box, box), "field", 0.0, None)
        inside = inside_box(model.grid[None] / model.scale + root[:, None], K, box)[0]
        cand = model.grid[inside]
        raw = model._sdf_fn(model.fields.hand_sdf, pyramid, K, root, clamp=False)(cand[None] / model.scale + root[:, None])[0]
    assert raw.abs().min() > 0.15
    expected = cand[torch.sort(raw.abs(), stable=True).indices[:model.sampler.hand_queries]]
    assert torch.allclose(hand[0], expected, atol=1e-6) and not torch.equal(hand[0], cand[:model.sampler.hand_queries])
