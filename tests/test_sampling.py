"""Query-point sampling: the fixed-shape path selects the same points as the compact one; the ablation
variants choose their training points as the supplementary describes; "gradient" uses the full field gradient."""

from __future__ import annotations

import pytest
import torch

from hoisdf.config import load_train_config
from hoisdf.data import StoreSpec, build_dataset
from hoisdf.data.augment import augment_batch
from hoisdf.model import build_model
from hoisdf.model.encoding import pixel_aligned_features
from hoisdf.model.sampling import (
    STRATEGIES,
    field_guided_points,
    grid_points,
    inside_box,
    inside_rows,
    random_grid_points,
)

SCALE = 3.1
TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=2",
        "model.decoder_layers=2", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16",
        "model.chunk=700"]


def _scene():
    """Two samples with their own intrinsics, centres and boxes; the second box holds fewer than 50 grid points."""
    K = torch.tensor([[[200.0, 0, 64], [0, 200.0, 64], [0, 0, 1]], [[230.0, 0, 60], [0, 220.0, 70], [0, 0, 1]]])
    center = torch.tensor([[0.02, -0.01, 0.4], [-0.03, 0.02, 0.5]])
    box = torch.tensor([[40.0, 30.0, 100.0, 90.0], [53.0, 65.0, 67.0, 79.0]])
    sphere = torch.tensor([[0.0, 0.0, 0.4], [-0.02, 0.02, 0.52]])

    def sdf_fn(points_cam):  # a 2 cm ball per sample, clamped as the model clamps (many exact ties at +-0.15)
        return ((points_cam - sphere[:, None]).norm(dim=-1) - 0.02).mul(SCALE).clamp(-0.15, 0.15)

    return K, center, box, sdf_fn


@pytest.mark.parametrize("strategy", ["absolute", "signed", "random", "gradient"])
def test_fixed_shape_selects_the_same_points_as_the_compact_path(strategy):
    K, center, box, sdf_fn = _scene()
    grid = grid_points(20)
    runs = {}
    for fixed in (False, True):
        gen = torch.Generator().manual_seed(3)
        runs[fixed] = field_guided_points(grid, center, SCALE, K, box, sdf_fn, 50, STRATEGIES[strategy], chunk=997,
                                          generator=gen, fixed_shape=fixed)
    assert torch.equal(runs[False][0], runs[True][0]) and torch.equal(runs[False][1], runs[True][1])
    cam = grid[None] / SCALE + center[:, None]
    inside = inside_box(cam, K, box)
    n_small = int(inside[1].sum())
    assert 0 < n_small < 50  # the second sample is filled with outside points, the same ones on both paths
    if strategy != "gradient":  # (the gradient step may move points out of the box)
        picked = inside_box(runs[True][0] / SCALE + center[:, None], K, box)
        assert bool(picked[0].all()) and int(picked[1].sum()) == n_small


def test_ties_go_to_the_lower_grid_index():
    """|SDF| clamped to 0.15 everywhere: the first 5 inside points in grid order are taken, on both paths."""
    K, center, box, _ = _scene()
    grid = grid_points(12)
    flat = lambda p: torch.full(p.shape[:2], 0.15)
    expected_idx = torch.nonzero(inside_box(grid[None] / SCALE + center[:1, None], K[:1], box[:1])[0])[:5, 0]
    for fixed in (False, True):
        points, _ = field_guided_points(grid, center[:1], SCALE, K[:1], box[:1], flat, 5, fixed_shape=fixed)
        assert torch.equal(points[0], grid[expected_idx])


@pytest.fixture(scope="module")
def tiny(tiny_store, mano_dir):
    from hoidata.hand import load_mano

    mano = load_mano(mano_dir, side="right")
    cfg = load_train_config(None, TINY)
    data = build_dataset([StoreSpec(tiny_store)], 2, seed=0, n_hand=32, n_object=16, training=True)
    batch = augment_batch(next(iter(data)), cfg.augment, torch.Generator().manual_seed(0), train=True)
    return mano, batch


def _model(mano, *extra):
    torch.manual_seed(0)
    return build_model(load_train_config(None, TINY + list(extra)).model, mano)


@pytest.mark.slow
@pytest.mark.parametrize("project_grid", [False, True])
def test_model_fixed_shape_and_compact_paths_pick_the_same_query_points(tiny, project_grid):
    """The real network's fields (in float64, so that per-row matmul rounding cannot reorder near-ties)."""
    mano, batch = tiny
    model = _model(mano).double().eval()
    model.features.project_grid = project_grid
    x = {k: v.double() if torch.is_tensor(v) and v.is_floating_point() else v for k, v in batch.items()}
    with torch.no_grad():
        pyramid, maps = model.backbone(x["img"])
        picks = {}
        for fixed in (False, True):
            model.sampler.fixed_shape = fixed
            picks[fixed] = model._query_points(x, pyramid, x["K"], x["hand_root"], x["obj_center"],
                                               model.boxes(x, maps), "field", 0.0, None)
    for a, b in zip(picks[False], picks[True]):
        assert torch.equal(a, b)


@pytest.mark.slow
def test_signed_variant_trains_on_points_inside_the_meshes(tiny):
    mano, batch = tiny
    model = _model(mano, 'model.sampling="signed"').train()
    rows = torch.cat([batch["hand_points"], batch["hand_near_points"]], 1)
    sdf = torch.cat([batch["hand_sdf"], batch["hand_near_sdf"]], 1)
    hand, _ = model._training_points(batch, batch["K"], batch["hand_root"], batch["obj_center"],
                                     (batch["hand_box"], batch["object_box"]), torch.Generator().manual_seed(0))
    for b in range(2):
        match = torch.cdist(hand[b] / model.scale, rows[b]).argmin(dim=1)
        assert torch.allclose(rows[b][match], hand[b] / model.scale, atol=1e-6)
        assert bool((sdf[b][match] < 0).all())  # every training point is a row inside the hand
    # the plain variant trains on the near-surface rows (|SDF| < 5 cm), not only inside ones
    plain, _ = _model(mano)._training_points(batch, batch["K"], batch["hand_root"], batch["obj_center"],
                                             (batch["hand_box"], batch["object_box"]), None)
    assert torch.equal(plain, batch["hand_near_points"] * model.scale)


def test_inside_rows_falls_back_to_the_deepest_row():
    points = torch.arange(12.0).view(1, 4, 3)
    picked = inside_rows(points, torch.tensor([[0.3, 0.1, 0.2, 0.5]]), 3, torch.Generator().manual_seed(0))
    assert torch.equal(picked, points[:, [1, 1, 1]])


@pytest.mark.slow
def test_random_variant_trains_on_random_grid_points_inside_the_box(tiny):
    mano, batch = tiny
    model = _model(mano, 'model.sampling="random"').train()
    boxes = (batch["hand_box"], batch["object_box"])
    hand, obj = model._training_points(batch, batch["K"], batch["hand_root"], batch["obj_center"], boxes,
                                       torch.Generator().manual_seed(0))
    assert hand.shape == (2, 32, 3) and obj.shape == (2, 16, 3)
    cam = hand / model.scale + batch["hand_root"][:, None]
    assert bool(inside_box(cam, batch["K"], batch["hand_box"]).all())
    lattice = model.grid
    dist = torch.cdist(hand.flatten(0, 1), lattice, compute_mode="donot_use_mm_for_euclid_dist")
    assert dist.min(dim=1).values.max() < 1e-6
    again = random_grid_points(model.grid, batch["hand_root"], model.scale, batch["K"], batch["hand_box"], 32,
                               torch.Generator().manual_seed(1))
    assert not torch.equal(again, hand)  # a new draw


def test_features_carry_the_gradient_to_the_points_only_when_asked():
    torch.manual_seed(0)
    fmap = [torch.randn(1, 3, 8, 8)]
    K = torch.tensor([[[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]])
    p = torch.tensor([[[0.01, -0.02, 0.4]]], requires_grad=True)
    pixel_aligned_features(fmap, p, K, 32, detach=False).sum().backward()
    assert p.grad is not None and p.grad.abs().sum() > 0
    q = p.detach().clone().requires_grad_(True)
    assert not pixel_aligned_features(fmap, q, K, 32).requires_grad


@pytest.mark.slow
def test_gradient_variant_steps_along_the_full_field_gradient_at_inference_only(tiny):
    mano, batch = tiny
    model = _model(mano, 'model.sampling="gradient"', "model.sdf_dropout=0.0")  # same field in train mode
    args = (batch["K"], batch["hand_root"], batch["obj_center"], (batch["hand_box"], batch["object_box"]), "field",
            0.0, None)
    with torch.no_grad():
        pyramid, _ = model.eval().backbone(batch["img"])
        moved, _ = model._query_points(batch, pyramid, *args)
        model.sampler.fixed_shape = True
        moved_fixed, _ = model._query_points(batch, pyramid, *args)
        model.sampler.fixed_shape = False
        absolute = _model(mano, 'model.sampling="absolute"', "model.sdf_dropout=0.0").eval()  # same weights
        start, _ = absolute._query_points(batch, pyramid, *args)
        model.train()  # trains as "absolute": no step
        trained, _ = model._query_points(batch, pyramid, *args)
    assert torch.equal(trained, start) and torch.allclose(moved, moved_fixed, atol=1e-6)
    fn_full = model._sdf_fn(model.fields.hand_sdf, pyramid, batch["K"], batch["hand_root"], detach=False)
    fn_code = model._sdf_fn(model.fields.hand_sdf, pyramid, batch["K"], batch["hand_root"])
    model.eval()
    grads = {}
    for name, fn in (("full", fn_full), ("code", fn_code)):
        p = start.clone().requires_grad_(True)
        sdf = fn(p / model.scale + batch["hand_root"][:, None])
        grads[name] = torch.autograd.grad(sdf.sum(), p)[0]
        if name == "full":
            unit = grads[name] / grads[name].norm(dim=-1, keepdim=True).clamp_min(1e-8)
            expected = start - sdf.detach()[..., None] * unit
    assert torch.allclose(moved, expected, atol=1e-5)
    assert not torch.allclose(grads["full"], grads["code"], atol=1e-6)  # the image features contribute


# Golden facts of the reference's lattice: upstream amathislab/HOISDF @666e5b7, main/model.py::Model.sdf_infer,
# lines 257-273 (voxel_origin ... samples[:, 2] = ...), executed verbatim with cfg.bins_n = 64 under torch 2.14
# on the CPU: a few rows of the (262144, 3) float32 array (index: x, y, z). (Its sha256 was b598ca1a...; the test
# compares values, which a CPU's kernels may change in the last bits, not bytes: docs/development.md.)
UPSTREAM_LATTICE_ROWS = {
    0: (-1.0, -1.0, -1.0),
    1: (-0.9999922513961792, -0.9995039701461792, -0.9682539701461792),
    63: (-0.99951171875, -0.96875, 1.0),
    64: (-0.9995039701461792, -0.9682539701461792, -1.0),
    4095: (-0.96826171875, 1.03125, 1.0),
    100000: (-0.22495037317276, -0.15873008966445923, 0.015873074531555176),
    200003: (0.5501224994659424, 0.684027910232544, -0.9047619104385376),
    262143: (1.03173828125, 1.03125, 1.0),
}
LATTICE_TOLERANCE = 1e-6  # scaled units, as the upstream parity's query points (tests/test_import_upstream.py)


def test_sheared_grid_equals_the_reference_lattice_value_by_value():
    grid = grid_points(64, sheared=True)
    assert grid.dtype == torch.float32 and grid.shape == (64 ** 3, 3)
    for i, row in UPSTREAM_LATTICE_ROWS.items():
        assert (grid[i].double() - torch.tensor(row, dtype=torch.float64)).abs().max() <= LATTICE_TOLERANCE, i
    # every point: the reference's index arithmetic (true division of i = 64^2 a + 64 b + c) in float64
    i, n = torch.arange(64 ** 3, dtype=torch.float64), 64
    exact = torch.stack([(i / n / n) % n, (i / n) % n, i % n], dim=1) * (2.0 / (n - 1)) - 1.0
    assert (grid.double() - exact).abs().max() <= LATTICE_TOLERANCE
    # the whole lattice lies within the reference's cube (x, y up to 1.0317), none of it at 40 m
    assert grid.min().item() == -1.0 and abs(grid.max().item() - 1.03173828125) <= LATTICE_TOLERANCE


def test_regular_grid_is_the_integer_lattice():
    grid = grid_points(5)
    assert torch.equal(grid[:5, 2], torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0]))
    assert torch.equal(grid[5], torch.tensor([-1.0, -0.5, -1.0]))
    assert torch.equal(grid[25], torch.tensor([-0.5, -1.0, -1.0]))
    assert torch.unique(grid[:, 1]).numel() == 5
