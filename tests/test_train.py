"""HOISDF model, losses and trainer on CPU with a tiny config: shapes, gradients, overfitting, exact resume,
DDP (gloo, 2 processes), real + synthetic mixing, the field-guided sampler and ground-truth conventions."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

from hoisdf.config import load_train_config
from hoisdf.data import StoreSpec, build_dataset
from hoisdf.data.augment import augment_batch
from hoisdf.model import build_model
from hoisdf.model.sampling import ABSOLUTE, SIGNED, field_guided_points, grid_points, inside_box
from hoisdf.training.losses import HOISDFLoss, hand_targets, mirrored_shape_mano
from hoisdf.training.trainer import Trainer

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=2",
        "model.decoder_layers=2", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16",
        "model.chunk=2048", "train.batch_size=2", "train.workers=0", "train.lr=1e-3", "train.log_every=1",
        "train.shuffle_buffer=4", "train.val_every=0"]
NO_AUGMENT = ["augment.rotation=\"none\"", "augment.center_jitter=0.0", "augment.scale_sigma=0.0",
              "augment.color=false", "augment.blur_max=0.0"]


@pytest.fixture(scope="module")
def mano(mano_dir):
    from hoidata.hand import load_mano

    return load_mano(mano_dir, side="right")


def _batch(store, n=2, training=True, seed=0):
    cfg = load_train_config(None, TINY)
    data = build_dataset([StoreSpec(store)], n, seed=seed, n_hand=cfg.model.hand_queries, n_object=cfg.model.object_queries,
                         training=training)
    return next(iter(data))


@pytest.mark.slow
@pytest.mark.parametrize("regressor", ["mano", "voting", "ik", "mano_only"])
def test_forward_backward_shapes_and_gradients(tiny_store, mano, regressor):
    cfg = load_train_config(None, TINY + [f'model.pose_regressor="{regressor}"'])
    torch.manual_seed(0)
    model = build_model(cfg.model, mano)
    batch = augment_batch(_batch(tiny_store), cfg.augment, torch.Generator().manual_seed(0), train=True)
    B, S, Nh, No = 2, 64, 32, 16
    for points in ("gt", "field"):
        out = model(batch, points=points, noise=0.03)
        shapes = {"heatmap": (B, 1, S // 2, S // 2), "hand_mask_logits": (B, 1, S // 2, S // 2),
                  "hand_sdf": (B, Nh), "obj_sdf": (B, No), "hand_query": (B, Nh, 3), "obj_query": (B, No, 3),
                  "joints": (B, 21, 3), "obj_rotation": (B, 3, 3), "obj_translation": (B, 3),
                  "obj_rot_points": (1, B, No, 3)}
        if regressor != "mano_only":
            shapes.update({"vote_offsets": (2, B, Nh, 20, 3), "vote_logits": (2, B, Nh, 20), "vote_joints": (2, B, 20, 3)})
        if regressor in ("mano", "mano_only"):
            shapes.update({"rotations": (2, B, 16, 3, 3), "mano_verts": (2, B, 778, 3), "verts": (B, 778, 3)})
        for name, shape in shapes.items():
            assert tuple(out[name].shape) == shape, name
        R = out["obj_rotation"]
        assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(B, 3, 3), atol=1e-4)
    model.zero_grad()
    total, terms = HOISDFLoss(cfg.loss, mano, cls_dist=cfg.model.cls_dist)(out, batch)
    total.backward()
    assert all(torch.isfinite(v) for v in terms.values())
    groups = ["backbone.decoder", "backbone.backbone.layer1", "features.sdf_in", "features.token_in",
              "fields.hand_sdf", "fields.obj_sdf", "pose.hand_encoder", "pose.obj_encoder", "pose.obj_head"]
    groups += [f"pose.regressor.{head}" for head in {
        "mano": ["hand_decoder", "mano_head", "vote_head"], "mano_only": ["hand_decoder", "mano_head"],
        "voting": ["vote_head"], "ik": ["hand_decoder", "shape_head", "vote_head"]}[regressor]]
    grads = {g: 0.0 for g in groups}
    for name, p in model.named_parameters():
        for g in groups:
            if name.startswith(g) and p.grad is not None:
                grads[g] += float(p.grad.abs().sum())
    assert all(v > 0 for v in grads.values()), grads
    assert model.widths.hand_beta.grad is not None and model.widths.hand_beta.grad.abs() > 0  # the density is learned
    widths = [layer.out_features for layer in model.features.token_in.layers if isinstance(layer, torch.nn.Linear)]
    assert widths == [48, 64 - 33]  # model.token_hidden, then d_model minus the point code


@pytest.mark.slow
def test_ablation_switches_run(tiny_store, mano):
    batch = augment_batch(_batch(tiny_store), load_train_config(None, TINY).augment, None, train=False)
    for switch in ['model.sampling="signed"', 'model.sampling="random"', 'model.sampling="gradient"',
                   'model.feature_augmentation="none"', 'model.feature_augmentation="density_concat"',
                   'model.feature_augmentation="distance_concat"', 'model.cross_field="none"',
                   'model.cross_field="image"', 'model.cross_field="target"', 'model.density_sign="code"',
                   'model.object_rotation="axis_angle"', 'model.test_boxes="predicted"', "model.sheared_grid=true",
                   "model.channels_last=true"]:
        cfg = load_train_config(None, TINY + [switch])
        model = build_model(cfg.model, mano).eval()
        with torch.no_grad():
            out = model(batch, points="field")
        assert torch.isfinite(out["joints"]).all() and torch.isfinite(out["obj_translation"]).all(), switch


def test_field_guided_sampler_picks_smallest_abs_sdf_inside_box():
    """Analytic field: a sphere of radius 8 cm around a centre 40 cm in front of the camera."""
    K = torch.tensor([[[200.0, 0, 64], [0, 200.0, 64], [0, 0, 1]]])
    center = torch.tensor([[0.02, -0.01, 0.4]])
    scale, radius = 3.1, 0.08
    box = torch.tensor([[40.0, 30.0, 100.0, 90.0]])

    def sdf_fn(points_cam):
        return ((points_cam - torch.tensor([0.0, 0.0, 0.4])).norm(dim=-1) - radius) * scale

    grid = grid_points(24)
    points, sdf = field_guided_points(grid, center, scale, K, box, sdf_fn, 50, ABSOLUTE, chunk=1000)
    cam = grid[None] / scale + center[:, None]
    inside = inside_box(cam, K, box)[0]
    all_sdf = sdf_fn(cam)[0]
    expected = torch.sort(all_sdf[inside].abs()).values[:50]
    assert torch.allclose(torch.sort(sdf[0].abs()).values, expected)
    assert inside_box(points / scale + center[:, None], K, box).all()
    # "signed" takes the deepest inside points; a box with fewer grid points than asked still gives n points
    _, signed = field_guided_points(grid, center, scale, K, box, sdf_fn, 50, SIGNED, chunk=1000)
    assert torch.allclose(torch.sort(signed[0]).values, torch.sort(all_sdf[inside]).values[:50])
    tiny_box = torch.tensor([[63.0, 63.0, 66.0, 66.0]])
    few, _ = field_guided_points(grid, center, scale, K, tiny_box, sdf_fn, 50, ABSOLUTE, chunk=1000)
    assert few.shape == (1, 50, 3)
    n_inside = int(inside_box(cam, K, tiny_box).sum())
    assert 0 < n_inside < 50 and int(inside_box(few / scale + center[:, None], K, tiny_box).sum()) == n_inside


@pytest.mark.slow
def test_ground_truth_hand_matches_stored_joints_incl_mirrored(tiny_store, mano):
    """hand_targets (right model, mirrored-shape twin for mirrored records) reproduces the records' joints."""
    data = build_dataset([StoreSpec(tiny_store)], 16, training=False, n_hand=8, n_object=8)
    batch = next(iter(data))
    assert batch["mirrored"].any() and (~batch["mirrored"]).any()
    gt = hand_targets(mano, mirrored_shape_mano(mano), batch)
    stored = batch["joints_3d"] - batch["hand_root"][:, None]
    assert (gt["joints"] - stored).norm(dim=-1).max() < 1e-4


def test_mirrored_shape_mano_is_the_mirrored_unfixed_left_model(mano_dir, mano):
    from hoidata.geometry.mirror import mirror_axis_angle, mirror_points
    from hoidata.hand import load_mano

    left = load_mano(mano_dir, side="left", fix_left_shapedirs=False)
    g = torch.Generator().manual_seed(3)
    pose, betas = torch.randn(3, 48, generator=g) * 0.3, torch.randn(3, 10, generator=g)
    want = left(pose, betas)
    mirrored_pose = torch.as_tensor(mirror_axis_angle(pose.numpy())).float()
    got = mirrored_shape_mano(mano)(mirrored_pose, betas)
    assert (got.vertices - torch.as_tensor(mirror_points(want.vertices.numpy()))).abs().max() < 1e-5
    assert (got.joints - torch.as_tensor(mirror_points(want.joints.numpy()))).abs().max() < 1e-5
    plain = mano(mirrored_pose, betas).vertices  # the plain right model is not it
    assert (plain - torch.as_tensor(mirror_points(want.vertices.numpy()))).abs().max() > 1e-3


def _trainer(store, run_dir, mano, extra=(), stores=None):
    cfg = load_train_config(None, TINY + list(extra))
    torch.manual_seed(0)
    return Trainer(cfg, stores or [StoreSpec(store)], mano, run_dir, torch.device("cpu"))


@pytest.mark.slow
def test_overfitting_two_samples_lowers_every_loss_term(tiny_store, mano, tmp_path):
    # with the paper's weights the betas term (0.1) is traded for the vertex term (1e4) early in training,
    # so it rises for a while; a larger shape weight makes every term's own gradient path visible. The
    # rotation term first rises while the global rotation is fitted (from the flat-hand start), then falls.
    trainer = _trainer(tiny_store, tmp_path, mano, NO_AUGMENT + ["model.dropout=0.0", "model.sdf_dropout=0.0",
                                                                 "loss.mano_shape=100.0"])
    batch = _batch(tiny_store, training=True)
    model = trainer.model

    def losses():
        model.eval()
        with torch.no_grad():
            b = augment_batch(batch, trainer.config.augment, None, train=False)
            _, terms = trainer.loss(model(b, points="gt", noise=0.0), b)
        model.train()
        return {k: float(v) for k, v in terms.items()}

    before = losses()
    for _ in range(120):
        trainer.train_step(batch, "gt", 0.0)
    after = losses()
    worse = {k: (before[k], after[k]) for k in before if not after[k] < before[k]}
    assert not worse, worse


@pytest.mark.slow
def test_resume_two_plus_two_steps_equals_four(tiny_store, mano, tmp_path):
    extra = ["train.point_sampling_epoch=0", "train.field_prob=0.5"]  # exercise both sampling paths' RNG
    full = _trainer(tiny_store, tmp_path / "full", mano, extra + ["train.max_steps=4"])
    full.fit(progress_bar=False)
    first = _trainer(tiny_store, tmp_path / "split", mano, extra + ["train.max_steps=2"])
    first.fit(progress_bar=False)
    payload = torch.load(tmp_path / "split" / "checkpoints" / "last.pt", weights_only=True)
    assert payload["progress"]["global_step"] == 2
    second = _trainer(tiny_store, tmp_path / "split", mano, extra + ["train.max_steps=4"])
    rng = second.load(payload)
    second.fit(rng, progress_bar=False)
    a, b = full.model.state_dict(), second.model.state_dict()
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a), [k for k in a if not torch.equal(a[k], b[k])][:5]
    curve = (tmp_path / "full" / "metrics.csv").read_text().splitlines()
    assert curve[0] == "split,epoch,step,name,value" and any(line.startswith("train,0,4,total,") for line in curve)


@pytest.mark.slow
def test_mixed_real_and_synthetic_training_reads_the_requested_ratio(tiny_store, mano, tmp_path):
    from hoidata.records.records import RecordSettings
    from hoidata.render_synthetic import render_synthetic
    from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d
    from hoidata.toy.make import write_assets

    mano_dir, models_dir = write_assets(tmp_path)
    write_toy_ho3d(tmp_path, mano_dir, models_dir, ToyHO3DSize(train_sequences=1, eval_sequences=0, frames=2),
                   progress=False)
    render_synthetic(tmp_path, tmp_path / "synth", 4, mano_dir, models_dir, seed=0, workers=1,
                     record=RecordSettings(crop_size=128, sdf_samples_hand=128, sdf_samples_object=64),
                     records_per_shard=4, progress=False)
    stores = [StoreSpec(tiny_store, 1.0), StoreSpec(tmp_path / "synth", 0.6)]
    trainer = _trainer(tiny_store, tmp_path / "run", mano, ["train.record_keys=true", "train.max_steps=40",
                                                            "train.batch_size=4", "train.epoch_samples=1000"], stores)
    trainer.fit(progress_bar=False)
    keys = (tmp_path / "run" / "keys-rank0.txt").read_text().split()
    synthetic = np.mean([k.startswith("synthetic") for k in keys])
    assert len(keys) == 160 and abs(synthetic - 0.6 / 1.6) < 0.15, synthetic


@pytest.mark.slow
def test_ddp_two_processes_gloo_see_disjoint_samples(tiny_store_two_shards, mano_dir, tmp_path):
    store = tiny_store_two_shards
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--standalone",
           "-m", "hoisdf.train", "--shards", str(store), "--mano", str(mano_dir), "--out", str(run), "--device", "cpu",
           "--no-progress", *TINY, "train.record_keys=true", "train.epochs=1", "train.epoch_samples=16"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    rank0 = (run / "keys-rank0.txt").read_text().split()
    rank1 = (run / "keys-rank1.txt").read_text().split()
    assert len(rank0) == len(rank1) == 8  # 16 samples per epoch over 2 ranks, batch 2
    assert not set(rank0) & set(rank1)
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "config.json").is_file()


@pytest.mark.slow
def test_cli_refuses_to_overwrite_a_run(tiny_store, mano_dir, tmp_path):
    from hoisdf.train import main

    args = ["--shards", str(tiny_store), "--mano", str(mano_dir), "--out", str(tmp_path / "run"), "--no-progress",
            *TINY, "train.max_steps=1"]
    assert main(args) == 0
    assert main(args) == 2  # the run exists: needs --resume
    assert main(["--resume", *args[:-1], "train.max_steps=2"]) == 0
    payload = torch.load(tmp_path / "run" / "checkpoints" / "last.pt", weights_only=True)
    assert payload["progress"]["global_step"] == 2


def test_replace_keeps_config_roundtrip():
    from hoisdf.config import config_from_dict

    cfg = load_train_config("toy", ["train.batch_size=3"])
    assert config_from_dict(cfg.as_dict()) == cfg and replace(cfg.train, batch_size=3) == cfg.train


@pytest.mark.slow
def test_projected_grid_features_equal_direct_sampling(tiny_store, mano):
    """The big decoder's inference grid path applies sdf_in's first layer before sampling: the same SDF."""
    cfg = load_train_config(None, TINY)
    torch.manual_seed(0)
    model = build_model(cfg.model, mano).eval()
    batch = augment_batch(_batch(tiny_store), cfg.augment, None, train=False)
    with torch.no_grad():
        pyramid, _ = model.backbone(batch["img"])
        points = batch["hand_root"][:, None] + torch.randn(2, 500, 3, generator=torch.Generator().manual_seed(1)) * 0.1
        from hoisdf.model.encoding import project_pyramid

        direct = model._sdf_fn(model.fields.hand_sdf, pyramid, batch["K"], batch["hand_root"])(points)
        projected = project_pyramid(pyramid, model.features.sdf_in.layers[0])
        fast = model._grid_sdf_fn(model.fields.hand_sdf, projected, batch["K"], batch["hand_root"])(points)
    assert torch.allclose(direct, fast, atol=1e-5) and direct.abs().max() > 0


def test_bad_settings_and_files_give_clear_errors(tmp_path, mano_dir, capsys):
    from hoidata.errors import DataError
    from hoidata.records.settings import load_build_config
    from hoisdf.train import main
    from hoisdf.training.checkpoint import load_checkpoint

    with pytest.raises(DataError, match="model.widht"):
        load_train_config(None, ["model.widht=3"])
    with pytest.raises(DataError, match="augment.input_size"):
        load_train_config(None, ["model.image_size=128", "augment.input_size=256"])
    with pytest.raises(ValueError, match="model.sampling"):
        build_model(load_train_config(None, TINY + ['model.sampling="nearest"']).model, None)
    # values are checked against the settings' types, naming the key
    for item, message in (('model.channels_last="yes"', "true or false"), ("train.bf16=1", "true or false"),
                          ("train.batch_size=2.5", "an integer"), ("model.token_hidden=256", "must be a list"),
                          ('model.token_hidden=[64, "wide"]', "every item must be an integer"),
                          ("train.lr=\"fast\"", "a number")):
        with pytest.raises(DataError, match=message) as info:
            load_train_config(None, [item])
        assert item.split("=")[0] in str(info.value)
    assert load_train_config(None, ["train.lr=1"]).train.lr == 1  # an integer is a number
    with pytest.raises(ValueError, match="model.token_hidden"):
        build_model(load_train_config(None, TINY + ["model.token_hidden=[32, 0]"]).model, None)
    with pytest.raises(DataError, match="record.sigmas.*2 values"):
        load_build_config("toy", ["record.sigmas=[0.01]"])
    bad = tmp_path / "run" / "checkpoints" / "last.pt"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="last.pt"):
        load_checkpoint(tmp_path / "run")
    assert main(["--shards", str(tmp_path / "nowhere"), "--mano", str(mano_dir), "--out", str(tmp_path / "r2"),
                 *TINY]) == 2
    assert "nowhere" in capsys.readouterr().err
