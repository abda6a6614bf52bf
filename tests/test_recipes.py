"""Training recipes: the defaults are upstream's released code; ``train.recipe=paper_text`` is the paper's text."""

from __future__ import annotations

import pytest
import torch

from hoidata.errors import DataError
from hoisdf.config import RECIPES, TrainSettings, config_from_dict, load_train_config


def test_defaults_are_the_released_recipe():
    t = load_train_config(None).train
    assert (t.recipe, t.optimizer, t.weight_decay, t.lr, t.lr_drop, t.lr_gamma, t.epochs, t.batch_size,
            t.point_sampling_epoch) == ("released", "adamw", 0.01, 1e-4, 9, 0.7, 70, 22, 40)
    assert all(getattr(TrainSettings(), k) == v for k, v in RECIPES["released"].items())


@pytest.mark.parametrize("pipeline", [None, "dexycb", "dexycb_full", "ho3d", "ho3d_render"])
def test_paper_text_recipe_sets_adam_batch_32_and_the_5_epoch_steps(pipeline):
    t = load_train_config(pipeline, ['train.recipe="paper_text"']).train
    assert (t.optimizer, t.weight_decay, t.batch_size, t.lr_drop, t.lr_gamma, t.epochs) == ("adam", 0.0, 32, 5, 0.7, 40)
    assert t.point_sampling_epoch < t.epochs


def test_explicit_values_win_over_the_recipe_and_checkpoints_keep_them():
    cfg = load_train_config(None, ['train.recipe="paper_text"', "train.batch_size=8", 'train.optimizer="adamw"'])
    assert (cfg.train.batch_size, cfg.train.optimizer, cfg.train.lr_drop) == (8, "adamw", 5)
    again = config_from_dict(cfg.as_dict())
    assert again.train == cfg.train
    old = cfg.as_dict()
    for key in ("recipe", "optimizer"):  # a checkpoint written before these settings existed
        del old["train"][key]
    assert config_from_dict(old).train.optimizer == "adamw"


@pytest.mark.parametrize("override, field", [('train.recipe="paper"', "train.recipe"),
                                             ('train.optimizer="sgd"', "train.optimizer")])
def test_unknown_recipe_or_optimizer_names_the_setting(override, field):
    with pytest.raises(DataError, match=field.replace(".", r"\.")):
        load_train_config(None, [override])


@pytest.mark.slow
def test_trainer_builds_the_recipe_optimizer(tiny_store, mano_dir, tmp_path):
    from hoidata.hand import load_mano
    from hoisdf.data import StoreSpec
    from hoisdf.training.trainer import Trainer

    tiny = ["model.depth=18", "model.image_size=64", "model.grid_resolution=12", "model.n_hand=16",
            "model.n_object=8", "model.hand_layers=1", "model.decoder_layers=1", "train.workers=0"]
    mano = load_mano(mano_dir, side="right")
    for recipe, cls, decay in (("released", torch.optim.AdamW, 0.01), ("paper_text", torch.optim.Adam, 0.0)):
        cfg = load_train_config(None, tiny + [f'train.recipe="{recipe}"', "train.batch_size=2"])
        trainer = Trainer(cfg, [StoreSpec(tiny_store)], mano, tmp_path / recipe, torch.device("cpu"))
        assert type(trainer.optimizer) is cls and trainer.optimizer.defaults["weight_decay"] == decay


def test_ho3d_render_uses_the_small_decoder_and_inverse_kinematics():
    m = load_train_config("ho3d_render").model
    assert (m.decoder, m.pose_regressor, m.depth) == ("small", "ik", 50)
    assert load_train_config("ho3d").model.decoder == "big"
