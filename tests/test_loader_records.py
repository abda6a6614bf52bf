"""hoisdf.data on a store written from hand-made records (tests/test_store.py's ``build_store``: 7 records, 32 px
crops, 3 shards), in the fast tier: the loader's batches hold exactly the store's values, and augmentation keeps the
geometry consistent. test_data.py and test_augment.py check the same and more (mixing, workers, epochs, pixels) on
stores built from the toy datasets, in the slow tier."""

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


def test_augmented_batches_keep_joints_on_their_projections(tmp_path):
    """augment_batch on a batch of the hand-written store given a camera and joints that agree (the records'
    values are random): the new intrinsics still project the moved joints onto the moved 2D joints. The same
    checks on real toy records are tests/test_augment.py's (slow tier)."""
    from hoisdf.data.augment import AugmentSettings, augment_batch
    from hoisdf.model.encoding import project_points

    build_store(tmp_path)
    batch = next(iter(build_dataset([StoreSpec(tmp_path, 1.0)], 4, n_hand=N_HAND, n_object=N_OBJECT, training=False)))
    K = torch.tensor([[40.0, 0.0, 15.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]]).expand(4, 3, 3).clone()
    joints = torch.randn(4, 21, 3, generator=torch.Generator().manual_seed(0)) * 0.03 + torch.tensor([0.0, 0.0, 0.5])
    batch.update(K=K, joints_3d=joints, joints_2d=project_points(joints, K), hand_root=joints[:, 0].clone())
    settings = AugmentSettings(input_size=64, rotation="uniform", scale_sigma=0.3, color=False, blur_max=0.0)
    out = augment_batch(batch, settings, torch.Generator().manual_seed(3), train=True)
    assert out["img"].shape == (4, 3, 64, 64) and out["seg"].shape == (4, 4, 32, 32)
    angles = torch.atan2(out["rotation"][:, 1, 0], out["rotation"][:, 0, 0]).abs()
    assert angles.max() > 0.5 and out["crop_scale"].std() > 0.01  # the augmentation is really on
    assert (project_points(out["joints_3d"], out["K"]) - out["joints_2d"]).abs().max() < 1e-3
    rot = out["rotation"]
    assert torch.allclose(rot @ rot.transpose(1, 2), torch.eye(3).expand_as(rot), atol=1e-6)
    torch.testing.assert_close(out["joints_3d"], joints @ rot.transpose(1, 2), atol=1e-6, rtol=0)
    torch.testing.assert_close(out["hand_root"], out["joints_3d"][:, 0], atol=1e-6, rtol=0)
    assert torch.allclose(out["K"][:, 0, 0] / K[:, 0, 0], out["crop_scale"])
