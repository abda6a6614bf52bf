"""The dtype path under bf16 autocast (CPU autocast; CUDA follows the same code): geometry stays fp32.

Projection, sampling coordinates, the inference grid, the SDF ranking and every head's output are full
precision; convolutions, feature MLPs and transformers may run in bf16 (``hoisdf.model.precision``).
"""

from __future__ import annotations

import pytest
import torch

from hoisdf.config import load_train_config
from hoisdf.data import StoreSpec, build_dataset
from hoisdf.data.augment import augment_batch
from hoisdf.model import build_model
from hoisdf.model.encoding import pixel_to_grid, project_points, sample_pyramid
from hoisdf.model.precision import autocast, trace_dtypes

CPU_BF16 = {"device_type": "cpu", "dtype": torch.bfloat16}
TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=2",
        "model.decoder_layers=2", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16",
        "model.chunk=2048"]


def test_projection_is_fp32_under_autocast_where_bf16_would_move_the_pixel():
    """The issue's case: a point projecting to (187.78, 90.61) in a 256 crop; bf16 would give (188.0, 90.5)."""
    K = torch.tensor([[[480.0, 0.0, 128.0], [0.0, 480.0, 128.0], [0.0, 0.0, 1.0]]])
    uv = torch.tensor([187.78, 90.61])
    z = 0.55
    point = torch.cat([(uv - 128.0) / 480.0 * z, torch.tensor([z])])[None, None]
    exact = project_points(point, K)
    with torch.autocast(**CPU_BF16):
        under = project_points(point, K)
        naive = torch.einsum("bij,bnj->bni", K, point)  # what autocast does to an unguarded projection
    assert under.dtype == torch.float32 and torch.equal(under, exact)
    assert torch.allclose(exact[0, 0], uv, atol=1e-3)
    assert naive.dtype == torch.bfloat16 and (naive[..., :2] / naive[..., 2:]).float().sub(uv).abs().max() > 0.05


def test_bf16_maps_are_sampled_at_fp32_coordinates():
    torch.manual_seed(0)
    fmap = torch.randn(1, 4, 16, 16).to(torch.bfloat16)
    uv = torch.tensor([[[3.37, 11.81], [12.02, 0.49]]])
    grid = pixel_to_grid(uv, 16)
    expected = torch.nn.functional.grid_sample(fmap.float(), grid[:, None], mode="bilinear", padding_mode="border",
                                               align_corners=False)[:, :, 0].transpose(1, 2)
    with torch.autocast(**CPU_BF16):
        got = sample_pyramid([fmap], grid)
    assert got.dtype == torch.float32 and torch.allclose(got, expected, atol=1e-6)
    rounded = torch.nn.functional.grid_sample(fmap, grid[:, None].to(torch.bfloat16), align_corners=False,
                                              padding_mode="border")[:, :, 0].transpose(1, 2)
    assert (rounded.float() - expected).abs().max() > 1e-3  # bf16 coordinates would sample elsewhere


@pytest.fixture(scope="module")
def model_and_batch(tiny_store, mano_dir):
    from hoidata.hand import load_mano

    cfg = load_train_config(None, TINY)
    torch.manual_seed(0)
    model = build_model(cfg.model, load_mano(mano_dir, side="right")).eval()
    data = build_dataset([StoreSpec(tiny_store)], 2, n_hand=32, n_object=16, training=False)
    batch = augment_batch(next(iter(data)), cfg.augment, None, train=False)
    return model, {k: v for k, v in batch.items() if not k.endswith(("_points", "_sdf", "_rows"))}


@pytest.mark.slow
def test_model_under_cpu_autocast_keeps_geometry_fp32(model_and_batch):
    model, batch = model_and_batch
    with torch.no_grad(), autocast("cpu", "bf16"), trace_dtypes(model) as seen:
        out = model(batch, points="field")
    # learned transforms ran in bf16 ...
    for stage in ("backbone", "sdf_in", "token_in"):
        assert seen[f"stage:{stage}"] == "bfloat16", (stage, seen)
    # ... the SDF decoder outputs (ranked), every head's output and every returned geometry are fp32
    for key in ("stage:hand_sdf", "stage:obj_sdf", "stage:vote_head", "stage:mano_head", "stage:obj_head",
                "output:hand_query", "output:hand_query_sdf", "output:obj_translation", "output:obj_rotation",
                "output:joints", "output:verts", "output:vote_offsets", "output:rotations"):
        assert seen[key] == "float32", (key, seen)
    # the query points are exact fp32 lattice points (a bf16 grid would round them off the lattice)
    lattice = model.grid
    points = out["hand_query"][0] * model.scale
    dist = torch.cdist(points, lattice, compute_mode="donot_use_mm_for_euclid_dist")
    assert dist.min(dim=1).values.max() < 1e-6


@pytest.mark.slow
def test_fp32_and_bf16_evaluation_differ_only_in_the_learned_layers(model_and_batch):
    model, batch = model_and_batch
    with torch.no_grad():
        ref = model(batch, points="field")
        with autocast("cpu", "bf16"):
            low = model(batch, points="field")
    assert ref["joints"].dtype == low["joints"].dtype == torch.float32
    assert (ref["joints"] - low["joints"]).abs().max() < 5e-3  # metres: bf16 features, fp32 geometry


def test_precision_setting_is_checked():
    with pytest.raises(ValueError, match="precision must be one of"):
        autocast("cpu", "fp16")


@pytest.mark.slow
def test_evaluate_precision_switch_is_recorded_in_metrics(tiny_store, mano_dir, tmp_path):
    import json

    from hoidata.hand import load_mano
    from hoisdf.evaluate import evaluate
    from hoisdf.training.checkpoint import save_checkpoint

    cfg = load_train_config(None, TINY)
    torch.manual_seed(0)
    model = build_model(cfg.model, load_mano(mano_dir, side="right"))
    save_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt",
                    {"model": model.state_dict(), "config": cfg.as_dict(), "progress": {}})
    for precision, learned in (("fp32", "float32"), ("bf16", "bfloat16")):
        evaluate(tmp_path / "run", [tiny_store], mano_dir, tmp_path / precision, batch_size=4, limit=4,
                 plausibility=0, progress=False, workers=0, precision=precision)
        record = json.loads((tmp_path / precision / "metrics.json").read_text())["precision"]
        assert record["mode"] == precision
        assert record["dtypes"]["stage:backbone"] == learned and record["dtypes"]["output:joints"] == "float32"
