"""The fixed-shape inference path compiles as one graph (torch.compile fullgraph=True) and matches eager.

The test compiles with the ``aot_eager`` backend (AOTAutograd tracing and decompositions, no code generation)
to stay fast on 2 CPU cores; ``python -m bench.bench_train --compile`` compiles with inductor and prints the largest
difference to eager beside the timings.
"""

from __future__ import annotations

import pytest
import torch

from hoisdf.config import load_train_config
from hoisdf.data import StoreSpec, build_dataset
from hoisdf.data.augment import augment_batch
from hoisdf.model import build_model

pytestmark = pytest.mark.slow  # torch.compile

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
        "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=12",
        "model.chunk=1000"]


@pytest.fixture(scope="module")
def setup(tiny_store, mano_dir):
    from hoidata.hand import load_mano

    mano = load_mano(mano_dir, side="right")
    cfg = load_train_config(None, TINY)
    data = build_dataset([StoreSpec(tiny_store)], 2, n_hand=32, n_object=16, training=False)
    batch = augment_batch(next(iter(data)), cfg.augment, None, train=False)
    batch = {k: v for k, v in batch.items() if torch.is_tensor(v) and not k.endswith(("_points", "_sdf", "_rows"))}
    return mano, batch


def _model(mano, fixed: bool):
    torch.manual_seed(0)
    cfg = load_train_config(None, TINY + [f"model.fixed_shape={str(fixed).lower()}"])
    model = build_model(cfg.model, mano).eval()
    model.mano.to("cpu")
    return model


def test_compiled_fullgraph_outputs_equal_eager(setup):
    """fullgraph=True raises on any graph break: the fixed-shape model is a single graph."""
    mano, batch = setup
    model = _model(mano, True)
    torch._dynamo.reset()
    with torch.no_grad():
        eager = model(batch, points="field")
        compiled = torch.compile(model, fullgraph=True, backend="aot_eager")(batch, points="field")
    for key in ("hand_query", "obj_query", "joints", "verts", "obj_rotation", "obj_translation", "vote_joints"):
        assert torch.allclose(compiled[key], eager[key], atol=1e-5, rtol=1e-5), key


def test_the_compact_path_cannot_compile_as_one_graph(setup):
    """Its candidate count is data dependent (``int(inside.sum(1).max())``): that is what fixed_shape removes."""
    mano, batch = setup
    torch._dynamo.reset()
    with torch.no_grad(), pytest.raises(Exception, match="(?i)graph break|data.dependent|Unsupported|item"):
        torch.compile(_model(mano, False), fullgraph=True, backend="eager")(batch, points="field")
