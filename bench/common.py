"""What the benchmark scripts share: toy inputs (DexYCB trees, stores, the MANO folder) and device helpers.

The scripts run as modules of the ``bench`` package from the repository root (``python -m bench.bench_build``),
so they import this file and their helper modules (``bench.compile_bench``, ``bench.per_file_loaders``) by
package name, and never one another.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import torch

from hoidata.toy.dexycb import ToyDexYCBSize, write_toy_dexycb
from hoidata.toy.make import write_assets

NOISE = 0.03  # half-width of the "gt" query-point jitter (scaled units), the training schedule's first value


def toy_root(frames: int, work: Path) -> Path:
    """A toy DexYCB under ``work/data`` with about `frames` frames in all (subject 0, 4 sequences, 3 cameras,
    every split), and its MANO and model folders. Returns the dataset root."""
    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=4, serials=(0, 6, 7), frames=max(1, -(-frames // 12)))
    write_toy_dexycb(root, mano, models, size, workers=2, progress=False)
    return root


def toy_train_root(frames: int, work: Path) -> Path:
    """A toy DexYCB under ``work/data`` whose s0 train split holds about `frames` right-hand frames (sequences 0
    and 2 of 3, 3 cameras). Returns the dataset root."""
    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=3, serials=(0, 6, 7), frames=max(2, -(-frames // 6)))
    write_toy_dexycb(root, mano, models, size, workers=2, progress=False)
    return root


def resolve_device(name: str | None) -> torch.device:
    """`name` ('cpu', 'cuda', 'cuda:1'), or CUDA when there is one, else the CPU."""
    return torch.device(name or ("cuda" if torch.cuda.is_available() else "cpu"))


def sync(device: torch.device) -> None:
    """Wait for the device's queued work, so a timer around it measures the work (a no-op on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def toy_store(work: Path, records: int = 32, workers: int = 1) -> tuple[Path, Path]:
    """Build a toy DexYCB train store (512 px crops) of about ``records`` records; returns (store, mano dir)."""
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=4, serials=(0,), frames=max(1, math.ceil(records / 4)))
    write_toy_dexycb(root, mano, models, size, workers=workers, progress=False)
    cfg = load_build_config("toy", ['dataset.splits=["train"]', "record.crop_size=512", "store.records_per_shard=8"])
    build_store(cfg, root, mano, models, work / "store", workers=workers, progress=False)
    return work / "store", mano


def store_and_mano(args, work: Path, records: int) -> tuple[Path, Path]:
    """``args.store`` / ``args.mano``, or a toy store and the toy MANO written into ``work``."""
    if args.store is None:
        store, mano = toy_store(work, records, workers=min(4, os.cpu_count() or 1))
        return store, Path(args.mano) if args.mano else mano
    if args.mano:
        return Path(args.store), Path(args.mano)
    from hoidata.toy.hand import write_toy_mano

    write_toy_mano(work / "mano")
    return Path(args.store), work / "mano"


def test_inputs(batch: dict, config, device: torch.device) -> dict:
    """A loader batch -> the network's test-time input on ``device`` (no SDF rows: nothing but inference)."""
    from hoisdf.data.augment import augment_batch
    from hoisdf.training.trainer import to_device

    keep = {k: v for k, v in batch.items() if not k.endswith(("_points", "_sdf", "_rows"))}
    return augment_batch(to_device(keep, device), config.augment, None, train=False)
