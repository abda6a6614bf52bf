"""hoisdf.data: batch layout, SDF rows vs the store, weighted mixing, epoch seeding, workers, near points."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from hoidata import schema, store
from hoidata.records.records import RecordSettings
from hoidata.build_sdf import build_store
from hoidata.records.settings import load_build_config
from hoidata.render_synthetic import render_synthetic
from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d
from hoidata.toy.make import write_assets
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.augment import AugmentSettings, augment_batch, float_image, unpack_masks
from hoisdf.data.loader import _key_seed, sample_sdf

pytestmark = pytest.mark.slow  # loads batches from a store built from the tiny toy DexYCB

CROP, N_HAND, N_OBJECT, NEAR = 128, 32, 16, 0.05
UPSTREAM_CROP_ENTRIES = {"upstream_crop", "grid_hand_box", "grid_object_box", "object_anchor"}  # loader.crop_entries
# one shard per store on purpose: the two-worker test needs fewer shards than workers
REAL = ["dataset.splits=[\"train\"]", f"record.crop_size={CROP}", "record.sdf_samples_hand=256", "record.sdf_samples_object=128",
        "store.records_per_shard=16"]


@pytest.fixture(scope="module")
def stores(tiny_dexycb, tmp_path_factory):
    """(real store: 16 toy DexYCB records, synthetic store: 6 records), one shard each."""
    root = tmp_path_factory.mktemp("data_stores")
    build_store(load_build_config("toy", REAL), tiny_dexycb, tiny_dexycb / "mano", tiny_dexycb / "models",
                root / "real", workers=1, part=(0, 1), progress=False)
    mano_dir, models_dir = write_assets(root)
    write_toy_ho3d(root, mano_dir, models_dir, ToyHO3DSize(train_sequences=2, eval_sequences=0, frames=2),
                   progress=False)
    render_synthetic(root, root / "synth", 6, mano_dir, models_dir, seed=0, workers=1,
                     record=RecordSettings(crop_size=CROP, sdf_samples_hand=128, sdf_samples_object=64),
                     records_per_shard=6,
                     progress=False)
    return root / "real", root / "synth"


@pytest.fixture(scope="module")
def records(stores):
    """key -> decoded record, for both stores."""
    return {r[store.KEY]: r for path in stores for r in store.iter_records(path)}


def _dataset(stores, batch_size=4, **kw):
    real, synth = stores
    kw = {"n_hand": N_HAND, "n_object": N_OBJECT, "near": NEAR, **kw}
    return build_dataset([StoreSpec(real, 1.0), StoreSpec(synth, 0.6)], batch_size, **kw)


def _keys(dataset, n_batches):
    out = []
    for i, batch in enumerate(dataset):
        if i == n_batches:
            break
        out.append(batch["key"])
    return out


def test_batch_shapes_and_dtypes(stores):
    b, h = 4, CROP // 2
    batch = next(iter(_dataset(stores, batch_size=b)))
    expected = {
        "img": ((b, 3, CROP, CROP), torch.uint8), "seg_bits": ((b, h, h), torch.uint8),
        "hand_points": ((b, N_HAND, 3), torch.float32), "hand_sdf": ((b, N_HAND), torch.float32),
        "obj_points": ((b, N_OBJECT, 3), torch.float32), "obj_sdf": ((b, N_OBJECT), torch.float32),
        "hand_near_points": ((b, N_HAND, 3), torch.float32), "hand_near_sdf": ((b, N_HAND), torch.float32),
        "obj_near_points": ((b, N_OBJECT, 3), torch.float32), "obj_near_sdf": ((b, N_OBJECT), torch.float32),
        "hand_rows": ((b, N_HAND), torch.int64), "obj_rows": ((b, N_OBJECT), torch.int64),
        "hand_near_rows": ((b, N_HAND), torch.int64), "obj_near_rows": ((b, N_OBJECT), torch.int64),
        "K": ((b, 3, 3), torch.float32), "hand_root": ((b, 3), torch.float32),
        "joints_3d": ((b, 21, 3), torch.float32), "joints_2d": ((b, 21, 2), torch.float32),
        "mano_pose": ((b, 48), torch.float32), "mano_betas": ((b, 10), torch.float32),
        "object_pose": ((b, 4, 4), torch.float32), "object_id": ((b,), torch.int64),
        "hand_box": ((b, 4), torch.float32), "object_box": ((b, 4), torch.float32),
        "is_synthetic": ((b,), torch.bool), "mirrored": ((b,), torch.bool),
        "upstream_crop": ((b,), torch.bool), "grid_hand_box": ((b, 4), torch.float32),
        "grid_object_box": ((b, 4), torch.float32), "object_anchor": ((b, 3), torch.float32),
    }
    assert set(batch) == set(expected) | {"key"}
    for name, (shape, dtype) in expected.items():
        assert tuple(batch[name].shape) == shape and batch[name].dtype == dtype, name
    assert isinstance(batch["key"], list) and len(batch["key"]) == b and all(isinstance(k, str) for k in batch["key"])
    assert batch["img"].max() > 0
    assert batch["img"].is_contiguous(memory_format=torch.channels_last)
    assert float_image(batch["img"]).dtype == torch.float32 and float_image(batch["img"]).max() <= 1
    planes = unpack_masks(batch["seg_bits"])
    assert planes[:, 2].sum() >= planes[:, 0].sum() > 0  # amodal hand covers the visible hand


def test_values_match_the_store(stores, records):
    batch = next(iter(_dataset(stores, batch_size=6)))
    uniform_drawn = 0
    for i, key in enumerate(batch["key"]):
        rec = records[key]
        meta = rec[schema.META]
        xyz, sdf_hand, sdf_obj, _ = schema.dequantize_sdf(rec[schema.SDF])
        n_h, n_o, n_u = meta["sdf_counts"]
        uniform = set(range(n_h + n_o, n_h + n_o + n_u))
        for prefix, dist, lo, hi in (("hand", sdf_hand, 0, n_h), ("obj", sdf_obj, n_h, n_h + n_o)):
            for name in (prefix, f"{prefix}_near"):
                rows = batch[f"{name}_rows"][i].numpy()
                assert set(rows.tolist()) <= set(range(lo, hi)) | uniform, name  # its own set or the uniform set
                uniform_drawn += len(set(rows.tolist()) & uniform)
                np.testing.assert_array_equal(batch[f"{name}_points"][i].numpy(), xyz[rows])
                np.testing.assert_array_equal(batch[f"{name}_sdf"][i].numpy(), dist[rows])
        np.testing.assert_array_equal(batch["img"][i].permute(1, 2, 0).numpy(), rec[schema.IMG])
        np.testing.assert_array_equal(batch["seg_bits"][i].numpy(), rec[schema.SEG])
        np.testing.assert_allclose(batch["joints_3d"][i].numpy(), meta["joints_3d"], rtol=1e-6)
        np.testing.assert_allclose(batch["object_pose"][i].numpy(), meta["object_pose"], rtol=1e-6)
        assert batch["object_id"][i] == meta["object_id"]
        assert bool(batch["is_synthetic"][i]) == (meta["dataset"] == "synthetic")
    assert uniform_drawn > 0  # the far-field rows reach training


def test_hand_rows_are_unique_when_the_block_is_large_enough(stores):
    batch = next(iter(_dataset(stores, batch_size=4)))
    for rows in batch["hand_rows"]:
        assert len(set(rows.tolist())) == N_HAND


def test_near_points_are_near(stores):
    for batch in _dataset(stores, batch_size=8, epoch_samples=16):
        assert batch["hand_near_sdf"].abs().max() < NEAR
        assert batch["obj_near_sdf"].abs().max() < NEAR


def test_mixing_follows_the_weights(stores):
    dataset = _dataset(stores, batch_size=10, epoch_samples=300, n_hand=4, n_object=4)
    synthetic = torch.cat([batch["is_synthetic"] for batch in dataset])
    assert len(synthetic) == 300
    assert abs(synthetic.float().mean().item() - 0.6 / 1.6) < 0.07


def test_default_epoch_length_is_the_weighted_store_size(stores):
    dataset = _dataset(stores, batch_size=2)
    assert dataset.epoch_samples == round(16 * 1.0 + 6 * 0.6)
    assert len(list(dataset)) == len(dataset) == dataset.epoch_samples // 2


def test_epoch_seeding(stores):
    def first_keys(seed, epoch):
        dataset = _dataset(stores, batch_size=4, seed=seed, n_hand=4, n_object=4)
        dataset.set_epoch(epoch)
        return _keys(dataset, 3)

    assert first_keys(0, 0) == first_keys(0, 0)
    assert first_keys(0, 1) == first_keys(0, 1)
    assert first_keys(0, 0) != first_keys(0, 1)
    assert first_keys(0, 0) != first_keys(1, 0)


def test_sdf_draw_depends_on_the_epoch(stores):
    def hand_rows(epoch):
        dataset = _dataset(stores, batch_size=4, training=False)
        dataset.set_epoch(epoch)
        batch = next(iter(dataset))
        return batch["key"], batch["hand_rows"]

    keys0, rows0 = hand_rows(0)
    keys1, rows1 = hand_rows(1)
    assert keys0 == keys1  # evaluation order does not depend on the epoch, the SDF draw does
    assert torch.equal(rows0, hand_rows(0)[1]) and not torch.equal(rows0, rows1)


def test_evaluation_reads_every_record_once(stores, records):
    dataset = _dataset(stores, batch_size=5, training=False)
    batches = list(dataset)
    keys = [k for b in batches for k in b["key"]]
    assert sorted(keys) == sorted(records) and len(batches) == 5  # 22 records: 4 full batches + 2
    assert "hand_near_sdf" not in batches[0]


def test_two_workers_with_one_shard_per_store(stores):
    dataset = _dataset(stores, batch_size=4, epoch_samples=40, n_hand=4, n_object=4)
    pickle.dumps(dataset)  # spawn-started workers need a picklable dataset (no lambdas, no open files)
    loader = make_loader(dataset, num_workers=2)
    loader.timeout = 120  # fail instead of hanging if a worker never delivers
    batches = list(loader)
    assert len(batches) == len(loader) == 10  # 40 // (4 * 2) = 5 batches from each worker
    assert all(len(b["key"]) == 4 for b in batches)
    assert len({k for b in batches for k in b["key"]}) > 6  # both workers read, from both stores


def _previous_batch(records, keys, seed, epoch):
    """The batch the loader gave before images and heatmaps stayed uint8 (float32 / 255, CHW), built
    here from the decoded records with that conversion, for the given keys."""
    samples = []
    for key in keys:
        rec, meta = records[key], records[key][schema.META]
        rng = np.random.default_rng([seed, epoch, _key_seed(key)])
        out = sample_sdf(rec[schema.SDF], meta["sdf_counts"], rng, N_HAND, N_OBJECT, NEAR)
        f32 = {name: np.asarray(meta[name], dtype=np.float32) for name in
               ("K", "hand_root", "joints_3d", "joints_2d", "mano_pose", "mano_betas", "object_pose",
                "hand_box", "object_box")}
        out.update(f32, img=np.ascontiguousarray(rec[schema.IMG].transpose(2, 0, 1), dtype=np.float32) / 255.0,
                   seg=((rec[schema.SEG][None] >> np.arange(4, dtype=np.uint8)[:, None, None]) & 1).astype(bool),
                   heatmap=rec[schema.HEATMAP][None].astype(np.float32) / 255.0,
                   object_id=np.int64(meta["object_id"]), mirrored=np.bool_(meta["mirrored"]),
                   is_synthetic=np.bool_(meta["dataset"] == "synthetic"))
        samples.append(out)
    return {name: torch.from_numpy(np.stack([s[name] for s in samples])) for name in samples[0]}


@pytest.mark.parametrize("workers", [0, 1])
def test_batches_equal_the_previous_loader_for_a_fixed_seed(stores, records, workers):
    """Same keys and values as the loader gave before uint8 images and packed masks (float_image and
    unpack_masks restore the previous values exactly; the stored heatmap is no longer sent, augment_batch never
    read it), in the main process and through a worker's shared-memory collation; and augment_batch makes the
    same network inputs from both batches."""
    dataset = _dataset(stores, batch_size=4, seed=5, epoch_samples=8)
    dataset.set_epoch(3)
    batches = list(make_loader(dataset, workers))
    assert len(batches) == 2
    for batch in batches:
        expected = _previous_batch(records, batch["key"], seed=5, epoch=3)
        assert set(batch) == set(expected) - {"seg", "heatmap"} | {"seg_bits", "key", *UPSTREAM_CROP_ENTRIES}
        for name, value in expected.items():
            if name == "heatmap":
                continue
            got = {"img": lambda: float_image(batch["img"]), "seg": lambda: unpack_masks(batch["seg_bits"]).bool()
                   }.get(name, lambda: batch[name])()
            assert got.dtype == value.dtype and torch.equal(got, value), name
        for train in (True, False):
            settings = AugmentSettings(input_size=64, rotation="uniform")
            ours, before = (augment_batch(b, settings, torch.Generator().manual_seed(1), train)
                            for b in (batch, {**expected, "key": batch["key"]}))
            assert set(ours) == set(before) | UPSTREAM_CROP_ENTRIES
            for name, value in before.items():
                assert name == "key" or torch.equal(ours[name], value), name
