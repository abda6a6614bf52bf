"""hoisdf.data on a store written from hand-made records (tests/test_store.py's ``build_store``: 7 records, 32 px
crops, 3 shards): the loader's batches hold exactly the store's values, in the fast tier. test_data.py checks the
same and more (mixing, workers, epochs) on stores built from the toy datasets, in the slow tier."""

from __future__ import annotations

import numpy as np
import torch

from hoidata import schema, store
from hoisdf.data import StoreSpec, build_dataset
from test_store import CROP, build_store

N_HAND, N_OBJECT, NEAR = 8, 4, 0.05


def test_batches_hold_the_stores_values(tmp_path):
    build_store(tmp_path)
    records = {r[store.KEY]: r for r in store.iter_records(tmp_path)}
    batches = list(build_dataset([StoreSpec(tmp_path, 1.0)], 3, n_hand=N_HAND, n_object=N_OBJECT, training=False))
    assert [len(b["key"]) for b in batches] == [3, 3, 1]  # one pass in stored order, the partial batch kept
    assert [k for b in batches for k in b["key"]] == list(records)
    for batch in batches:
        assert batch["img"].shape[1:] == (3, CROP, CROP) and batch["img"].dtype == torch.uint8
        for i, key in enumerate(batch["key"]):
            rec = records[key]
            meta = rec[schema.META]
            xyz, sdf_hand, sdf_obj, _ = schema.dequantize_sdf(rec[schema.SDF])
            n_h, n_o, n_u = meta["sdf_counts"]
            uniform = set(range(n_h + n_o, n_h + n_o + n_u))
            for name, dist, own in (("hand", sdf_hand, range(0, n_h)), ("obj", sdf_obj, range(n_h, n_h + n_o))):
                rows = batch[f"{name}_rows"][i].numpy()
                assert set(rows.tolist()) <= set(own) | uniform, name  # its own set or the uniform set
                np.testing.assert_array_equal(batch[f"{name}_points"][i].numpy(), xyz[rows])
                np.testing.assert_array_equal(batch[f"{name}_sdf"][i].numpy(), dist[rows])
            assert len(set(batch["hand_rows"][i].tolist())) == N_HAND  # without replacement: the pool is larger
            np.testing.assert_array_equal(batch["img"][i].permute(1, 2, 0).numpy(), rec[schema.IMG])
            np.testing.assert_array_equal(batch["seg_bits"][i].numpy(), rec[schema.SEG])
            np.testing.assert_allclose(batch["joints_3d"][i].numpy(), meta["joints_3d"], rtol=1e-6)
            np.testing.assert_allclose(batch["object_pose"][i].numpy(), meta["object_pose"], rtol=1e-6)
            assert batch["object_id"][i] == meta["object_id"] and not batch["is_synthetic"][i]


def test_training_batches_draw_near_rows_and_repeat_with_the_seed(tmp_path):
    build_store(tmp_path)
    records = {r[store.KEY]: r for r in store.iter_records(tmp_path)}

    def first(seed):
        dataset = build_dataset([StoreSpec(tmp_path, 1.0)], 4, seed=seed, n_hand=N_HAND, n_object=N_OBJECT, near=NEAR)
        dataset.set_epoch(0)
        return next(iter(dataset))

    batch = first(0)
    assert len(batch["key"]) == 4 and set(batch["key"]) <= set(records)
    for i, key in enumerate(batch["key"]):
        xyz, sdf_hand, _, _ = schema.dequantize_sdf(records[key][schema.SDF])
        rows = batch["hand_near_rows"][i].numpy()
        np.testing.assert_array_equal(batch["hand_near_points"][i].numpy(), xyz[rows])
        np.testing.assert_array_equal(batch["hand_near_sdf"][i].numpy(), sdf_hand[rows])
    again, other = first(0), first(1)
    assert again["key"] == batch["key"] and torch.equal(again["hand_rows"], batch["hand_rows"])
    assert other["key"] != batch["key"] or not torch.equal(other["hand_rows"], batch["hand_rows"])
