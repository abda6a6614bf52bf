"""Loader throughput: ``make_loader(build_dataset(...))`` against an upstream-style per-file loader.

Usage: python bench/bench_loader.py [--store DIR] [--records 96] [--batch 22] [--batches 12] [--rounds 3]
                                    [--workers 0 1 2]

The baseline reads the same records the way the HOISDF and AlignSDF code bases do: one folder per kind
of file, one file per frame (``rgb/<key>.jpg``, ``seg/<key>.png``, ``heatmap/<key>.png``, ``sdf/<key>.npz``
with the SDF samples as float32 columns, ``meta/<key>.pkl`` with the labels), written here from the store
(the image bytes as they are), and a map-style ``torch.utils.data.Dataset`` that opens and decodes them
per item, converts to float32 in the worker, and ``DataLoader``'s default collation with a shuffling
sampler. It draws the same SDF rows as ours (same seeded generator per key) and returns the same
tensors; the bench checks that on a batch of keys (every key, every value; our uint8 images compared
and heatmaps compared after ``hoisdf.data.augment.float_image``).

Both run interleaved, ``--rounds`` times per worker count (median samples/s reported, with the
spread of the ratio), after one untimed batch each (worker start-up excluded). Without ``--store`` a toy
DexYCB store with 512 px crops is built first (bench_train.toy_store).
"""

from __future__ import annotations

import argparse
import os
import pickle
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from bench_train import toy_store

from hoidata import schema
from hoidata.store import decode_record, read_shard_members
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.augment import float_image
from hoisdf.data.loader import _key_seed, sample_sdf_arrays

N_HAND, N_OBJECT, NEAR, SEED = 600, 200, 0.05, 0


def export_per_file(store: Path, out: Path) -> list[str]:
    """Write every record of ``store`` as per-frame files under ``out``; returns the keys in store order."""
    for kind in ("rgb", "seg", "heatmap", "sdf", "meta"):
        (out / kind).mkdir(parents=True, exist_ok=True)
    keys = []
    for shard in sorted(store.glob("shard-*.tar")):
        for members in read_shard_members(shard):
            rec = decode_record(members, str(shard))
            key = rec["__key__"]
            (out / "rgb" / f"{key}.jpg").write_bytes(members[schema.IMG])
            (out / "seg" / f"{key}.png").write_bytes(members[schema.SEG])
            (out / "heatmap" / f"{key}.png").write_bytes(members[schema.HEATMAP])
            xyz, sdf_hand, sdf_obj, part = schema.dequantize_sdf(rec[schema.SDF])
            np.savez(out / "sdf" / f"{key}.npz", xyz=xyz, sdf_hand=sdf_hand, sdf_obj=sdf_obj, part=part)
            with open(out / "meta" / f"{key}.pkl", "wb") as f:
                pickle.dump(rec[schema.META], f)
            keys.append(key)
    return keys


class PerFileDataset(torch.utils.data.Dataset):
    """The upstream-style baseline: each item opens its five files and builds float32 tensors."""

    def __init__(self, root: Path, keys: list[str], epoch: int = 0):
        self.root, self.keys, self.epoch = root, keys, epoch

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, i: int) -> dict:
        key, root = self.keys[i], self.root
        img = cv2.imread(str(root / "rgb" / f"{key}.jpg"), cv2.IMREAD_COLOR)[:, :, ::-1]
        seg = cv2.imread(str(root / "seg" / f"{key}.png"), cv2.IMREAD_UNCHANGED)
        heatmap = cv2.imread(str(root / "heatmap" / f"{key}.png"), cv2.IMREAD_UNCHANGED)
        with np.load(root / "sdf" / f"{key}.npz") as z:
            xyz, sdf_hand, sdf_obj = z["xyz"], z["sdf_hand"], z["sdf_obj"]
        with open(root / "meta" / f"{key}.pkl", "rb") as f:
            meta = pickle.load(f)
        rng = np.random.default_rng([SEED, self.epoch, _key_seed(key)])
        out = sample_sdf_arrays(xyz, sdf_hand, sdf_obj, meta["sdf_counts"], rng, N_HAND, N_OBJECT, NEAR)
        f32 = lambda x: np.asarray(x, dtype=np.float32)
        out.update({
            "img": np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32) / 255.0,
            "seg": ((seg[None] >> np.arange(4, dtype=np.uint8)[:, None, None]) & 1).astype(bool),
            "heatmap": heatmap[None].astype(np.float32) / 255.0,
            "K": f32(meta["K"]), "hand_root": f32(meta["hand_root"]), "joints_3d": f32(meta["joints_3d"]),
            "joints_2d": f32(meta["joints_2d"]), "mano_pose": f32(meta["mano_pose"]),
            "mano_betas": f32(meta["mano_betas"]), "object_pose": f32(meta["object_pose"]),
            "hand_box": f32(meta["hand_box"]), "object_box": f32(meta["object_box"]),
            "object_id": np.int64(meta["object_id"]), "mirrored": np.bool_(meta["mirrored"]),
            "is_synthetic": np.bool_(meta["dataset"] == "synthetic"), "key": key,
        })
        return out


def baseline_loader(root: Path, keys: list[str], batch: int, workers: int, samples: int):
    sampler = torch.utils.data.RandomSampler(keys, num_samples=samples, generator=torch.Generator().manual_seed(SEED))
    return torch.utils.data.DataLoader(PerFileDataset(root, keys), batch_size=batch, sampler=sampler,
                                       num_workers=workers, drop_last=True)


def ours_loader(store: Path, batch: int, workers: int, samples: int):
    data = build_dataset([StoreSpec(store)], batch, samples, SEED, N_HAND, N_OBJECT, NEAR, 64, training=True)
    return make_loader(data, workers)


def rate(loader, batches: int) -> float:
    """Samples per second over ``batches`` batches after the first (worker start-up excluded)."""
    it = iter(loader)
    next(it)
    start, n = time.perf_counter(), 0
    for _ in range(batches):
        n += len(next(it)["key"])
    seconds = time.perf_counter() - start
    del it
    return n / seconds


def check_same(store: Path, root: Path, keys: list[str], batch: int) -> int:
    """Our batch and the baseline's items for the same keys: equal in every key and value. Returns
    the number of values compared."""
    ours = next(iter(ours_loader(store, batch, 0, batch * 2)))
    index = {k: i for i, k in enumerate(keys)}
    dataset = PerFileDataset(root, keys)
    theirs = torch.utils.data.default_collate([dataset[index[k]] for k in ours["key"]])
    assert set(ours) == set(theirs), sorted(set(ours) ^ set(theirs))
    compared = 0
    for name, value in ours.items():
        if name == "key":
            assert value == theirs[name]
            continue
        if name in ("img", "heatmap"):  # ours: uint8, converted on the device
            value = float_image(value)
        assert value.dtype == theirs[name].dtype and torch.equal(value, theirs[name]), name
        compared += value.numel()
    return compared


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", default=None)
    parser.add_argument("--records", type=int, default=96, help="records of the toy store built without --store")
    parser.add_argument("--batch", type=int, default=22)
    parser.add_argument("--batches", type=int, default=12, help="timed batches per measurement")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_loader_"))
    try:
        store = Path(args.store) if args.store else toy_store(work, args.records, workers=2)[0]
        keys = export_per_file(store, work / "per_file")
        print(f"{len(keys)} records, {args.batch} per batch; same tensors checked: "
              f"{check_same(store, work / 'per_file', keys, args.batch)} values equal")
        samples = args.batch * (args.batches + 1)
        rows = {}
        for _ in range(args.rounds):
            for w in args.workers:
                rows.setdefault(w, {"ours": [], "per-file": []})
                rows[w]["ours"].append(rate(ours_loader(store, args.batch, w, samples * max(1, w)), args.batches))
                rows[w]["per-file"].append(rate(baseline_loader(work / "per_file", keys, args.batch, w, samples * max(1, w)),
                                                args.batches))
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"samples/s, median of {args.rounds} interleaved rounds; load average {load} (1, 5, 15 min)")
        print(f"{'workers':>7} {'ours':>8} {'per-file':>9} {'x':>6}  x per round")
        for w, r in rows.items():
            ratios = np.array(r["ours"]) / np.array(r["per-file"])
            print(f"{w:>7} {np.median(r['ours']):8.1f} {np.median(r['per-file']):9.1f} {np.median(ratios):6.2f}  "
                  + " ".join(f"{x:.2f}" for x in ratios))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
