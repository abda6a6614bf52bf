"""Whole build-sdf throughput and bytes per frame, against the AlignSDF/HOISDF sample layout.

Usage: python bench/bench_build.py [--frames 60] [--root DIR]

Writes a small toy DexYCB (unless --root points at one), then in one run:
- builds --frames frames with 1 worker (the per-core rate; the first shard's start-up included)
  and, on the same frames, with 2 workers;
- measures the bytes per record in the store, split by member, against the layout HOISDF trains from:
  20,000 float32 samples per mesh (hand file and object file, 6 columns each) per frame.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from hoidata import schema, store
from hoidata.datasets.toy import write_assets
from hoidata.datasets.toy_dexycb import ToyDexYCBSize, write_toy_dexycb
from hoidata.pipeline.runner import build_store
from hoidata.pipeline.settings import load_build_config

ALIGNSDF_BYTES = 2 * 20_000 * 6 * 4  # two files (hand, object) of 20k float32 rows of 6 columns, per frame


def toy_root(frames: int, work: Path) -> Path:
    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=4, serials=(0, 6, 7), frames=max(1, -(-frames // 12)))
    write_toy_dexycb(root, mano, models, size, workers=2, progress=False)
    return root


def timed_build(root: Path, out: Path, frames: int, workers: int) -> tuple[float, int]:
    cfg = load_build_config("toy", ['dataset.splits=["train", "val"]', "store.records_per_shard=8"])
    start = time.perf_counter()
    summary = build_store(cfg, root, root / "mano", root / "models", out, workers=workers, progress=False)
    return time.perf_counter() - start, summary.records


def member_bytes(out: Path) -> dict[str, float]:
    sizes, n = {m: 0 for m in schema.MEMBERS}, 0
    for members in store.read_shard_members(sorted(out.glob("shard-*.tar"))[0]):
        n += 1
        for m in schema.MEMBERS:
            sizes[m] += len(members[m])
    return {m: s / n for m, s in sizes.items()}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--root", default=None)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_build_"))
    try:
        root = Path(args.root) if args.root else toy_root(args.frames, work)
        rows = []
        for workers in (1, 2):
            seconds, records = timed_build(root, work / f"store{workers}", args.frames, workers)
            rows.append((workers, records, seconds, records / seconds))
        sizes = member_bytes(work / "store1")
        total = sum(sizes.values())
        print(f"{'workers':>7} {'records':>8} {'seconds':>8} {'frames/s':>9} {'per core':>9}")
        for w, r, s, fps in rows:
            print(f"{w:>7} {r:>8} {s:>8.1f} {fps:>9.2f} {fps / w:>9.2f}")
        print("\nbytes per record: " + ", ".join(f"{m} {v / 1e3:.1f} kB" for m, v in sizes.items())
              + f", total {total / 1e3:.1f} kB")
        print(f"sdf.npy {sizes[schema.SDF] / 1e3:.1f} kB vs AlignSDF/HOISDF samples {ALIGNSDF_BYTES / 1e3:.0f} kB: "
              f"{sizes[schema.SDF] / ALIGNSDF_BYTES:.3f}x; whole record {total / ALIGNSDF_BYTES:.3f}x")
        print(f"(store checks: {store.verify_store(work / 'store1')})")
        assert np.isfinite(total)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
