"""Device and dtype hygiene without a GPU (issue 25, item 10).

No GPU has run this code, so the CPU stands in: the model, its optimizer state and the inputs live on the CPU while
the default device is ``meta``. A tensor the code makes without the input's device (``torch.zeros(n)`` instead of
``torch.zeros(n, device=x.device)``) then lands on meta and the step fails here, as it would mix devices on a
user's GPU. The same steps under a float64 default dtype catch tensors made without the input's dtype: every
output must stay float32. Tensors that are meant for the CPU (the augmentation's and the query jitter's draws from
a CPU generator, a mask filled from Python) say ``device="cpu"`` explicitly.
"""

from __future__ import annotations

import pytest
import torch

from hoisdf.config import load_train_config
from hoisdf.data import StoreSpec, build_dataset
from hoisdf.evaluation.inference import predict_batch
from hoisdf.training.losses import mirrored_shape_mano
from hoisdf.training.trainer import Trainer

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=2",
        "model.decoder_layers=2", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16",
        "model.chunk=2048", "train.batch_size=2", "train.workers=0", "train.val_every=0"]
VARIANTS = {"default": [], "ik": ['model.pose_regressor="ik"'], "voting": ['model.pose_regressor="voting"'],
            "predicted boxes": ['model.test_boxes="predicted"', 'model.sampling="gradient"',
                                'model.cross_field="target"']}


@pytest.fixture(scope="module")
def mano(mano_dir):
    from hoidata.hand import load_mano

    return load_mano(mano_dir, side="right")


def _setup(store, mano, run_dir, extra):
    cfg = load_train_config(None, TINY + extra)
    torch.manual_seed(0)
    trainer = Trainer(cfg, [StoreSpec(store)], mano, run_dir, torch.device("cpu"))
    batch = next(iter(build_dataset([StoreSpec(store)], 2, seed=0, n_hand=cfg.model.hand_queries,
                                    n_object=cfg.model.object_queries, training=True)))
    eval_batch = next(iter(build_dataset([StoreSpec(store)], 2, n_hand=1, n_object=1, training=False)))
    # one ordinary step first: torch's own Adam makes its step counters on the default device at the first step
    trainer.train_step(batch, "field", 0.03)
    return cfg, trainer, batch, eval_batch


def _steps(cfg, trainer, batch, eval_batch, mano):
    logged = [trainer.train_step(batch, points, 0.03) for points in ("field", "gt")]
    trainer.model.eval()
    (_, out), arrays = predict_batch(trainer.model, mano, mirrored_shape_mano(mano), eval_batch, cfg)
    trainer.model.train()
    return logged, out, arrays


def test_the_meta_default_device_catches_a_tensor_made_without_a_device():
    """The check itself: CPU inputs, and one tensor made without a device, fail under it."""
    x = torch.ones(3, device="cpu")
    with torch.device("meta"), pytest.raises((RuntimeError, NotImplementedError)):
        float((x + torch.zeros(3)).sum())
    with torch.device("meta"):
        assert float((x + torch.zeros(3, device=x.device)).sum()) == 3.0


@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_training_step_and_eval_batch_make_every_tensor_on_the_inputs_device(variant, tiny_store, mano, tmp_path):
    cfg, trainer, batch, eval_batch = _setup(tiny_store, mano, tmp_path, VARIANTS[variant])
    with torch.device("meta"):
        logged, out, arrays = _steps(cfg, trainer, batch, eval_batch, mano)
    assert all(torch.isfinite(torch.tensor(list(step.values()))).all() for step in logged)
    tensors = {k: v for k, v in out.items() if torch.is_tensor(v)}
    assert {v.device.type for v in tensors.values()} == {"cpu"}, {k: v.device for k, v in tensors.items()}
    assert all(p.device.type == "cpu" for p in trainer.model.parameters())


@pytest.mark.slow
def test_training_step_and_eval_batch_keep_the_inputs_dtype(tiny_store, mano, tmp_path):
    cfg, trainer, batch, eval_batch = _setup(tiny_store, mano, tmp_path, [])
    torch.set_default_dtype(torch.float64)
    try:
        logged, out, arrays = _steps(cfg, trainer, batch, eval_batch, mano)
    finally:
        torch.set_default_dtype(torch.float32)
    wrong = {k: v.dtype for k, v in out.items() if torch.is_tensor(v) and v.is_floating_point()
             and v.dtype != torch.float32}
    assert not wrong and all(p.dtype == torch.float32 for p in trainer.model.parameters()), wrong
