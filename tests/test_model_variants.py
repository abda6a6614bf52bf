"""Golden numbers of every model variant (each setting of the paper's ablations and of upstream's conventions), so
that a restructuring of the model's parts is proved to change no number.

A tiny model per variant, seeded, in float64 (so that no kernel's rounding can reorder the grid ranking's near
ties), on a fixed synthetic batch: its field-guided forward in evaluation mode and its ground-truth guided forward
in training mode. ``tests/golden/model_variants/README.md`` says how the numbers were made; run this file as a script
to write them again (only when a change is meant to change them)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from hoisdf.config import load_train_config
from hoisdf.model import build_model

GOLDEN = Path(__file__).parent / "golden" / "model_variants" / "outputs.json"
TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
        "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.grid_resolution=12", "model.chunk=500"]
QUERIES = ["model.hand_queries=24", "model.object_queries=12"]
UPSTREAM = ['model.pixel_convention="upstream"', 'model.density_sign="code"', 'model.object_rotation="axis_angle"',
            "model.sheared_grid=true", 'model.rot6d="raw"', 'model.beta_floor="project"',
            'model.field_density="ranking"', "model.normalize_input=false"]
VARIANTS = {
    "paper": [],
    "upstream": UPSTREAM,
    "upstream_ik": UPSTREAM + ['model.pose_regressor="ik"'],
    "signed": ['model.sampling="signed"'],
    "random": ['model.sampling="random"'],
    "gradient": ['model.sampling="gradient"'],
    "no_augmentation": ['model.feature_augmentation="none"', 'model.cross_field="none"'],
    "density_concat": ['model.feature_augmentation="density_concat"'],
    "distance_concat": ['model.feature_augmentation="distance_concat"'],
    "cross_image": ['model.cross_field="image"'],
    "cross_target": ['model.cross_field="target"'],
    "mano_only": ['model.pose_regressor="mano_only"'],
    "voting": ['model.pose_regressor="voting"'],
    "ik": ['model.pose_regressor="ik"'],
    "predicted_boxes": ['model.test_boxes="predicted"', "model.mask_threshold=0.45"],
    "predicted_boxes_upstream": UPSTREAM + ['model.test_boxes="predicted"', "model.mask_threshold=0.45"],
    "fixed_shape": ["model.fixed_shape=true"],
    "big_decoder": ['model.decoder="big"'],
}
# float64 throughout but MANO (float32 skinning), whose rounding differs between torch's CPU kernels and moves the
# field-guided query points' values: under ATEN_CPU_CAPABILITY=default (AVX2 and AVX-512 agree bit for bit) 275 of
# the 768 numbers move by more than 1e-7 of their size (the sum of |x|), the most 3.4e-5 (mano_only's object query
# SDF). A number must stay within SIZE_TOL of its size: 6x that spread, far below what a moved part or a lost
# convention changes (the two closest variants differ by 2.8e-3 of a size; test_the_variants_differ)
SIZE_TOL = 2e-4


def batch() -> dict:
    """Two samples: their own intrinsics, centres, boxes, near-surface rows and SDF rows (float64)."""
    g = torch.Generator().manual_seed(11)
    rand = lambda *shape: torch.rand(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    K = torch.tensor([[[70.0, 0, 31.5], [0, 72.0, 31.5], [0, 0, 1]], [[80.0, 0, 30.0], [0, 78.0, 33.0], [0, 0, 1]]],
                     dtype=torch.float64)
    rows = lambda n: (rand(2, n, 3) - 0.5) * 0.12  # noqa: E731 - metres around the hand root
    out = {"img": rand(2, 3, 64, 64), "K": K,
           "hand_root": torch.tensor([[0.0, 0.01, 0.45], [0.02, -0.01, 0.5]], dtype=torch.float64),
           "obj_center": torch.tensor([[0.03, 0.02, 0.47], [-0.02, 0.0, 0.52]], dtype=torch.float64),
           "hand_box": torch.tensor([[10.0, 8.0, 50.0, 52.0], [14.0, 20.0, 40.0, 44.0]], dtype=torch.float64),
           "object_box": torch.tensor([[20.0, 18.0, 58.0, 54.0], [4.0, 6.0, 30.0, 36.0]], dtype=torch.float64)}
    for who in ("hand", "obj"):
        out[f"{who}_points"], out[f"{who}_sdf"] = rows(40), (rand(2, 40) - 0.4) * 0.05
        out[f"{who}_near_points"], out[f"{who}_near_sdf"] = rows(30), (rand(2, 30) - 0.5) * 0.05
    return out


def outputs(name: str, mano) -> dict[str, list[float]]:
    """Output name (with the mode) -> [sum, sum of |x|] of the variant's two forwards."""
    torch.manual_seed(0)
    model = build_model(load_train_config(None, TINY + QUERIES + VARIANTS[name]).model, mano).double()
    x = batch()
    found = {}
    with torch.no_grad():
        model.eval()
        for key, value in model(x, points="field").items():
            found[f"field:{key}"] = value
        model.train()
        torch.manual_seed(1)
        for key, value in model(x, points="gt", noise=0.05, generator=torch.Generator().manual_seed(2)).items():
            found[f"gt:{key}"] = value
    return {k: [float(v.double().sum()), float(v.double().abs().sum())] for k, v in sorted(found.items())}


@pytest.fixture(scope="module")
def golden() -> dict:
    return json.loads(GOLDEN.read_text())


@pytest.mark.slow  # a model built and run twice per variant: seconds each
@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_every_variant_computes_its_golden_numbers(name, golden, mano_dir):
    from hoidata.hand import load_mano

    got, want = outputs(name, load_mano(mano_dir, side="right")), golden["variants"][name]
    assert sorted(got) == sorted(want)
    for key, (total, size) in want.items():
        assert got[key] == pytest.approx([total, size], rel=0, abs=SIZE_TOL * size + 1e-12), (name, key)


def test_the_variants_differ():
    """The guard can fail: the variants' numbers differ (each setting changes something), except the fixed-shape
    path, which picks the same points as the compact one (``tests/test_sampling.py``) and so gives the same numbers."""
    data = json.loads(GOLDEN.read_text())["variants"]
    assert set(data) == set(VARIANTS)
    signatures = {name: tuple(v for key in sorted(values) for v in values[key]) for name, values in data.items()}
    assert signatures.pop("fixed_shape") == signatures["paper"]
    assert len(set(signatures.values())) == len(signatures)


if __name__ == "__main__":  # the recipe of tests/golden/model_variants/outputs.json
    import tempfile

    from hoidata.hand import load_mano
    from hoidata.toy.hand import write_toy_mano

    with tempfile.TemporaryDirectory() as tmp:
        write_toy_mano(Path(tmp))
        right = load_mano(tmp, side="right")
        data = {"variants": {name: outputs(name, right) for name in sorted(VARIANTS)}}
    GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    GOLDEN.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}", file=sys.stderr)
