"""Loader throughput: ``make_loader(build_dataset(...))`` against two per-file loaders, at equal workers.

Usage: python -m bench.bench_loader [--frames 96] [--batch 22] [--batches 12] [--rounds 3] [--workers 0 1 2]
           [--root DIR]

Builds a toy DexYCB (its right-hand training frames: gSDF reads right hands only), a store of them with 512 px
crops and ``hoidata export --format gsdf`` of the same frames (AlignSDF's SDF files, 20,000 rows per mesh), then
measures, interleaved over ``--rounds`` rounds per worker count (median samples/s, the ratios per round):

- ours: ``make_loader(build_dataset(...))`` (tar shards, strict reads against the index, uint8 images, packed
  masks; batch 22, 600 + 200 SDF points and as many near points, as training uses);
- training: ours followed by the training augmentation (``augment_batch(..., train=True)`` with the full-size
  model's settings, 256 px input) in the loading process, on the CPU: the whole CPU pipeline of a training sample
  (decode, SDF row sampling, collate, augmentation), which training runs on the device instead;
- "upstream-style" (``per_file_loaders.UpstreamDataset``): what HOISDF's and gSDF's loaders do per item, from
  per-frame files: the original 640x480 frame JPEG cut to the crop by an affine warp, the dataset's label map
  warped to the masks, AlignSDF's npz files unpacked, a label pickle, float32 images; the baseline issue 17
  asks for;
- "same crops" (``per_file_loaders.SameCropsDataset``): the store's own pre-cut members as per-frame files
  (crop JPEG, mask PNG, SDF npz of the store's rows, label pickle), decoded per item to float32: the container
  and the decode path alone, with less work per item than any upstream loader does.

``--root`` reads an existing toy DexYCB (``bench.common.toy_root`` / ``toy_train_root`` layout, with ``mano`` and
``models``) instead of writing one. Per core: samples/s divided by the processes that work, 1 + workers, at most
the machine's cores; torch runs one thread per process, so each process is at most one core.

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
from hoidata.build_sdf import build_store
from hoidata.records.settings import load_build_config
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.config import load_train_config
from hoisdf.data.augment import augment_batch, float_image, unpack_masks

N_HAND, N_OBJECT, NEAR, SEED, CROP = 600, 200, 0.05, 0, 512
SETTINGS = ['dataset.splits=["train"]', 'dataset.sides=["right"]', f"record.crop_size={CROP}",
            "store.records_per_shard=32"]
LOADERS = ("ours", "training", "upstream-style", "same crops")
CROP_KEYS = ("upstream_crop", "grid_hand_box", "grid_object_box", "object_anchor")  # hoisdf.data.loader.crop_entries


def prepare(frames: int, work: Path, root: Path | None = None) -> tuple[Path, dict]:
    """(store, {loader name: (folder, keys)}) of a toy DexYCB's right-hand training frames (``root``, or a toy
    DexYCB written into ``work``)."""
    root = root or toy_train_root(frames, work)
    cfg = load_build_config("toy", SETTINGS)
    paths = (root, root / "mano", root / "models")
    build_store(cfg, *paths, work / "store", workers=2, progress=False)
    export_dataset("gsdf", cfg, *paths, work / "gsdf", splits=["train"], workers=2, progress=False)
    same = SameCropsDataset.export(work / "store", work / "same_crops")
    upstream = UpstreamDataset.export(work / "store", root, work / "gsdf", work / "upstream")
    return work / "store", {"same crops": (work / "same_crops", same), "upstream-style": (work / "upstream", upstream)}


def dataset(name: str, folder: Path, keys: list[str]):
    if name == "same crops":
        return SameCropsDataset(folder, keys, N_HAND, N_OBJECT, NEAR, SEED)
    return UpstreamDataset(folder, keys, N_HAND, N_OBJECT, NEAR, CROP, SEED)


class Augmented:
    """Batches of ``make_loader`` passed through the training augmentation, as the trainer does (on the CPU here)."""

    def __init__(self, batches, augment):
        self.batches, self.augment = batches, augment
        self.generator = torch.Generator().manual_seed(SEED)

    def __iter__(self):
        for batch in self.batches:
            out = augment_batch(batch, self.augment, self.generator, train=True)
            out["key"] = batch["key"]
            yield out


def loader(name: str, store: Path, per_file: dict, batch: int, workers: int, samples: int):
    if name in ("ours", "training"):
        data = build_dataset([StoreSpec(store)], batch, samples, SEED, N_HAND, N_OBJECT, NEAR, 64, training=True)
        batches = make_loader(data, workers)
        return batches if name == "ours" else Augmented(batches, load_train_config(None).augment)
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


def same_values(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal value by value, NaN equal to NaN (a project-crop record's upstream-crop fields are NaN)."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    return bool(((a == b) | (a.isnan() & b.isnan())).all()) if a.is_floating_point() else torch.equal(a, b)


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
                assert key == "key" or same_values(value, theirs[key]), key
            lines.append(f"same crops: every value of a batch of {batch} equal to ours "
                         f"({sum(v.numel() for k, v in ours.items() if k != 'key')} values)")
            continue
        for key in (*LABEL_FIELDS, *CROP_KEYS, "object_id", "mirrored", "is_synthetic"):
            assert same_values(ours[key], theirs[key]), key
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
    parser.add_argument("--root", type=Path, default=None, help="an existing toy DexYCB (default: write one)")
    args = parser.parse_args()
    torch.set_num_threads(1)  # one core per process: DataLoader's workers run one thread too
    work = Path(tempfile.mkdtemp(prefix="bench_loader_"))
    try:
        store, per_file = prepare(args.frames, work, args.root)
        print(f"{len(per_file['same crops'][1])} records, {args.batch} per batch, {CROP} px crops")
        for line in check(store, per_file, args.batch):
            print(line)
        samples = args.batch * (args.batches + 1)
        rows = {w: {name: [] for name in LOADERS} for w in args.workers}
        load_before = os.getloadavg()[0]
        for _ in range(args.rounds):
            for w in args.workers:
                for name in LOADERS:
                    rows[w][name].append(rate(loader(name, store, per_file, args.batch, w, samples * max(1, w)),
                                              args.batches))
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"samples/s, median of {args.rounds} interleaved rounds; load average {load_before:.2f} before, "
              f"{load} after (1, 5, 15 min)")
        print(f"{'workers':>7} {'ours':>8} {'training':>9} {'upstream':>9} {'same':>8} {'x upstream':>11} {'x same':>7}"
              "  x upstream per round; x same per round")
        for w, r in rows.items():
            up, same = (np.array(r["ours"]) / np.array(r[name]) for name in ("upstream-style", "same crops"))
            print(f"{w:>7} {np.median(r['ours']):8.1f} {np.median(r['training']):9.1f} "
                  f"{np.median(r['upstream-style']):9.1f} {np.median(r['same crops']):8.1f} {np.median(up):11.2f} "
                  f"{np.median(same):7.2f}  " + " ".join(f"{x:.2f}" for x in up) + "; " + " ".join(f"{x:.2f}" for x in same))
        cores = os.cpu_count() or 1
        print(f"\nper core (samples/s / min(1 + workers, {cores} cores)): training = decode + SDF rows + collate + "
              "augmentation; upstream-style without its augmentation")
        print(f"{'workers':>7} {'cores':>5} {'training':>9} {'upstream':>9} {'x upstream':>11}  x per round")
        for w, r in rows.items():
            used = min(1 + w, cores)
            ratio = np.array(r["training"]) / np.array(r["upstream-style"])
            print(f"{w:>7} {used:>5} {np.median(r['training']) / used:9.1f} "
                  f"{np.median(r['upstream-style']) / used:9.1f} {np.median(ratio):11.2f}  "
                  + " ".join(f"{x:.2f}" for x in ratio))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
