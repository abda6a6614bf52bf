"""Loader throughput: ``make_loader(build_dataset(...))`` against two per-file loaders, at equal workers.

Usage: python -m bench.bench_loader [--frames 96] [--batch 22] [--batches 12] [--rounds 3] [--workers 0 1 2]

Builds a toy DexYCB (its right-hand training frames: gSDF reads right hands only), a store of them with 512 px
crops and ``hoidata export --format gsdf`` of the same frames (AlignSDF's SDF files, 20,000 rows per mesh), then
measures, interleaved over ``--rounds`` rounds per worker count (median samples/s, the ratios per round):

- ours: ``make_loader(build_dataset(...))`` (tar shards, strict reads against the index, uint8 images, packed
  masks; batch 22, 600 + 200 SDF points and as many near points, as training uses);
- "upstream-style" (``per_file_loaders.UpstreamDataset``): what HOISDF's and gSDF's loaders do per item, from
  per-frame files: the original 640x480 frame JPEG cut to the crop by an affine warp, the dataset's label map
  warped to the masks, AlignSDF's npz files unpacked, a label pickle, float32 images; the baseline issue 17
  asks for;
- "same crops" (``per_file_loaders.SameCropsDataset``): the store's own pre-cut members as per-frame files
  (crop JPEG, mask PNG, SDF npz of the store's rows, label pickle), decoded per item to float32: the container
  and the decode path alone, with less work per item than any upstream loader does.

The baselines use DataLoader's default collation with a shuffling sampler, ours its own batches; every loader
is timed over ``--batches`` batches after an untimed first one (worker start-up excluded). Before timing, a batch
of each baseline is compared with ours for the same keys: "same crops" value by value (our image through
``float_image``, our masks through ``unpack_masks``), "upstream-style" in keys, shapes and dtypes, labels value by
value, and image and masks by how close they are (other source pixels: see per_file_loaders).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.common import toy_train_root
from bench.per_file_loaders import LABEL_FIELDS, SameCropsDataset, UpstreamDataset
from hoidata.export import export_dataset
from hoidata.pipeline.runner import build_store
from hoidata.pipeline.settings import load_build_config
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.augment import float_image, unpack_masks

N_HAND, N_OBJECT, NEAR, SEED, CROP = 600, 200, 0.05, 0, 512
SETTINGS = ['dataset.splits=["train"]', 'dataset.sides=["right"]', f"record.crop_size={CROP}",
            "store.records_per_shard=32"]
LOADERS = ("ours", "upstream-style", "same crops")


def prepare(frames: int, work: Path) -> tuple[Path, dict]:
    """(store, {loader name: (folder, keys)}) of a toy DexYCB's right-hand training frames."""
    root = toy_train_root(frames, work)
    cfg = load_build_config("toy", SETTINGS)
    paths = (root, root / "mano", root / "models")
    build_store(cfg, *paths, work / "store", workers=2, progress=False)
    export_dataset("gsdf", cfg, *paths, work / "gsdf", splits=["train"], workers=2, progress=False)
    same = SameCropsDataset.export(work / "store", work / "same_crops")
    upstream = UpstreamDataset.export(work / "store", work / "gsdf", work / "upstream")
    return work / "store", {"same crops": (work / "same_crops", same), "upstream-style": (work / "upstream", upstream)}


def dataset(name: str, folder: Path, keys: list[str]):
    if name == "same crops":
        return SameCropsDataset(folder, keys, N_HAND, N_OBJECT, NEAR, SEED)
    return UpstreamDataset(folder, keys, N_HAND, N_OBJECT, NEAR, CROP, SEED)


def loader(name: str, store: Path, per_file: dict, batch: int, workers: int, samples: int):
    if name == "ours":
        data = build_dataset([StoreSpec(store)], batch, samples, SEED, N_HAND, N_OBJECT, NEAR, 64, training=True)
        return make_loader(data, workers)
    folder, keys = per_file[name]
    sampler = torch.utils.data.RandomSampler(keys, num_samples=samples, generator=torch.Generator().manual_seed(SEED))
    return torch.utils.data.DataLoader(dataset(name, folder, keys), batch_size=batch, sampler=sampler,
                                       num_workers=workers, drop_last=True)


def rate(batches_of, batches: int) -> float:
    """Samples per second over ``batches`` batches after the first (worker start-up excluded)."""
    it = iter(batches_of)
    next(it)
    start, n = time.perf_counter(), 0
    for _ in range(batches):
        n += len(next(it)["key"])
    seconds = time.perf_counter() - start
    del it
    return n / seconds


def check(store: Path, per_file: dict, batch: int) -> list[str]:
    """Compare a batch of ours with each baseline's items for the same keys; returns one line per baseline."""
    ours = next(iter(loader("ours", store, per_file, batch, 0, batch * 2)))
    bits = ours.pop("seg_bits")
    ours = {**ours, "img": float_image(ours["img"]), "seg": unpack_masks(bits).bool()}
    lines = []
    for name in ("same crops", "upstream-style"):
        folder, keys = per_file[name]
        index, data = {k: i for i, k in enumerate(keys)}, dataset(name, folder, keys)
        theirs = torch.utils.data.default_collate([data[index[k]] for k in ours["key"]])
        assert set(ours) == set(theirs) and theirs["key"] == ours["key"], sorted(set(ours) ^ set(theirs))
        for key, value in ours.items():
            if key != "key":
                assert value.shape == theirs[key].shape and value.dtype == theirs[key].dtype, key
        if name == "same crops":
            for key, value in ours.items():
                assert key == "key" or torch.equal(value, theirs[key]), key
            lines.append(f"same crops: every value of a batch of {batch} equal to ours "
                         f"({sum(v.numel() for k, v in ours.items() if k != 'key')} values)")
            continue
        for key in (*LABEL_FIELDS, "object_id", "mirrored", "is_synthetic"):
            assert torch.equal(ours[key], theirs[key]), key
        image = (ours["img"] - theirs["img"]).abs().mean().item() * 255
        masks = (ours["seg"][:, :2] == theirs["seg"][:, :2]).float().mean().item()
        lines.append(f"upstream-style: same keys, shapes and dtypes, labels equal; image {image:.2f} grey levels "
                     f"from ours on average (crop of the frame JPEG vs JPEG of the crop), visible masks "
                     f"{100 * masks:.1f} % of pixels equal (dataset label map vs our renders)")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=96, help="right-hand training frames of the toy DexYCB")
    parser.add_argument("--batch", type=int, default=22)
    parser.add_argument("--batches", type=int, default=12, help="timed batches per measurement")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_loader_"))
    try:
        store, per_file = prepare(args.frames, work)
        print(f"{len(per_file['same crops'][1])} records, {args.batch} per batch, {CROP} px crops")
        for line in check(store, per_file, args.batch):
            print(line)
        samples = args.batch * (args.batches + 1)
        rows = {w: {name: [] for name in LOADERS} for w in args.workers}
        for _ in range(args.rounds):
            for w in args.workers:
                for name in LOADERS:
                    rows[w][name].append(rate(loader(name, store, per_file, args.batch, w, samples * max(1, w)),
                                              args.batches))
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"samples/s, median of {args.rounds} interleaved rounds; load average {load} (1, 5, 15 min)")
        print(f"{'workers':>7} {'ours':>8} {'upstream':>9} {'same':>8} {'x upstream':>11} {'x same':>7}"
              "  x upstream per round; x same per round")
        for w, r in rows.items():
            up, same = (np.array(r["ours"]) / np.array(r[name]) for name in ("upstream-style", "same crops"))
            print(f"{w:>7} {np.median(r['ours']):8.1f} {np.median(r['upstream-style']):9.1f} "
                  f"{np.median(r['same crops']):8.1f} {np.median(up):11.2f} {np.median(same):7.2f}  "
                  + " ".join(f"{x:.2f}" for x in up) + "; " + " ".join(f"{x:.2f}" for x in same))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
