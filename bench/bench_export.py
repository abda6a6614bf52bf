"""``hoidata export --format gsdf`` throughput per core against ``hoidata build-sdf`` on the same frames.

Usage: python -m bench.bench_export [--frames 48] [--workers 1] [--root DIR]

Writes a small toy DexYCB (unless --root points at one) and selects its right-hand training frames (gSDF reads
right hands only), then in one run, one after the other on those frames with --workers processes:

1. ``build-sdf`` (default record settings: 512 px crop, masks, heatmap, 4096 + 2048 SDF samples, shards, index);
2. ``export --format gsdf`` sampling anew: AlignSDF's 2 x 20,000 points per frame with exact distances to both
   meshes, the three npz files, the COCO files;
3. ``export --format gsdf --store``: the store of step 1 re-used (its SDF rows normalised into the npz files).

Prints frames, seconds and frames/s per core for each, the bytes written per frame, and the load average
before and after (the machine is shared; other jobs inflate the times).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from bench.common import toy_train_root
from hoidata.export import export_dataset
from hoidata.build_sdf import build_store
from hoidata.records.settings import load_build_config

OVERRIDES = ['dataset.splits=["train"]', 'dataset.sides=["right"]', "store.records_per_shard=16"]


def folder_bytes(path: Path, pattern: str) -> int:
    return sum(p.stat().st_size for p in path.rglob(pattern) if p.is_file() and not p.is_symlink())


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--root", default=None)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_export_"))
    try:
        root = Path(args.root) if args.root else toy_train_root(args.frames, work)
        cfg = load_build_config("toy", OVERRIDES)
        paths = (root, root / "mano", root / "models")
        load_before = os.getloadavg()
        rows = []
        start = time.perf_counter()
        built = build_store(cfg, *paths, work / "store", workers=args.workers, progress=False)
        rows.append(("build-sdf", built.written, time.perf_counter() - start,
                     folder_bytes(work / "store", "shard-*.tar")))
        for label, store in (("export gsdf (sampled)", None), ("export gsdf --store", work / "store")):
            out = work / label.split()[-1].strip("()-")
            start = time.perf_counter()
            s = export_dataset("gsdf", cfg, *paths, out, store=store, workers=args.workers, progress=False)
            sources = s.extra["sdf_sources"]
            assert s.finished and sources == {"store" if store else "sampled": s.written}, sources
            rows.append((label, s.written, time.perf_counter() - start, folder_bytes(out / "data", "*.npz")))
        load_after = os.getloadavg()
        print(f"{args.workers} worker(s); load average before {load_before[0]:.2f}, after {load_after[0]:.2f} "
              f"(1 min), {os.cpu_count()} CPUs")
        print(f"{'step':<24} {'frames':>6} {'seconds':>8} {'frames/s/core':>14} {'kB/frame':>9}")
        for label, n, seconds, size in rows:
            print(f"{label:<24} {n:>6} {seconds:>8.1f} {n / seconds / args.workers:>14.2f} {size / n / 1e3:>9.1f}")
        base = rows[0][1] / rows[0][2]
        for label, n, seconds, _ in rows[1:]:
            print(f"{label}: {n / seconds / base:.2f}x build-sdf's frames/s")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
