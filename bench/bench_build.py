"""Whole build-sdf throughput and bytes per frame, against the AlignSDF/HOISDF sample layout.

Usage: python -m bench.bench_build [--frames 60] [--root DIR] [--rounds 2] [--workers 1 2] [--profile]

Writes a small toy DexYCB (unless --root points at one), then in one run:
- builds the frames once untimed with 1 worker (this process then has its modules imported, the numba kernels
  loaded and the GL libraries initialised, as a long build has after its first seconds; without it the first
  timed configuration alone would pay for them);
- builds --frames frames with 1 worker (the per-core rate, and the CPU time per frame of this process, which runs
  a 1-worker build itself; reading the frames, the renderer's start-up and the
  index included) and, on the same frames, with 2 workers (spawned: their start-up included), each with the
  SDF backend build-sdf uses
  (``record.sdf_backend="bvh"``) and with the previous one as the baseline (``"igl"``), interleaved
  over --rounds rounds (medians reported; the machine's load average is printed with them);
- measures the bytes per record in the store, split by member, against the layout HOISDF trains from:
  20,000 float32 samples per mesh (hand file and object file, 6 columns each) per frame;
- with ``--profile``: one more 1-worker build (default backend) under cProfile, its time per frame split into the
  build's stages (STAGES: the cumulative time of each stage's function; "other" is the rest: reading the frame
  list, the index, the worker's loop). cProfile's own overhead inflates the total by some 10-30 %, the Python-heavy
  stages most; the shares are what to read.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import toy_root
from hoidata import schema, store
from hoidata.build_sdf import build_store
from hoidata.records.settings import load_build_config

BACKENDS = ("bvh", "igl")  # record.sdf_backend: build-sdf's, then the baseline
ALIGNSDF_BYTES = 2 * 20_000 * 6 * 4  # two files (hand, object) of 20k float32 rows of 6 columns, per frame


def timed_build(root: Path, out: Path, workers: int, backend: str) -> tuple[float, int, float]:
    """(wall seconds, records, CPU seconds of this process): with 1 worker the build runs in this process, so its
    CPU time is the build's (less sensitive to other jobs' load than the wall time); with more it leaves out the
    spawned workers."""
    cfg = load_build_config("toy", ['dataset.splits=["train", "val"]', "store.records_per_shard=8",
                                    f'record.sdf_backend="{backend}"'])
    shutil.rmtree(out, ignore_errors=True)
    start, cpu = time.perf_counter(), time.process_time()
    summary = build_store(cfg, root, root / "mano", root / "models", out, workers=workers, progress=False)
    return time.perf_counter() - start, summary.written, time.process_time() - cpu


# stage -> (file suffix, function): each stage's cumulative time in a profile of a 1-worker build
STAGES = {
    "read frame list": ("hoidata/build_sdf.py", "read_frames"),
    "object assets (load, repair)": ("hoidata/records/worker.py", "load_object_asset"),
    "MANO model load": ("hoidata/hand/model.py", "load_mano"),
    "decode (frame JPEG)": ("hoidata/datasets/frame.py", "load_image"),
    "crop (warp)": ("hoidata/geometry/crop.py", "warp_image"),
    "MANO hand": ("hoidata/records/records.py", "posed_hand"),
    "object posing": ("hoidata/records/records.py", "posed_object"),
    "render (masks)": ("hoidata/render/masks.py", "masks"),
    "dataset-mask IoU": ("hoidata/records/records.py", "dataset_mask_iou"),
    "SDF samples": ("hoidata/geometry/sampling.py", "build_sdf_record"),
    "heatmap": ("hoidata/records/records.py", "summed_heatmap"),
    "encode (JPEG, PNG, npy, json)": ("hoidata/store/codec.py", "encode_record"),
    "write shard": ("hoidata/store/shards.py", "write_shard"),
    "index (finish_store)": ("hoidata/records/store_writer.py", "finish_store"),
}


def profile_stages(root: Path, out: Path) -> tuple[int, float, dict[str, float]]:
    """(records, total seconds, {stage: seconds}) of one 1-worker build under cProfile. The crop's warp is counted
    without the dataset-mask IoU's own warp (which stays in that stage)."""
    profiler = cProfile.Profile()
    profiler.enable()
    seconds, records, _ = timed_build(root, out, 1, BACKENDS[0])
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    found = {}
    for stage, (suffix, name) in STAGES.items():
        found[stage] = sum(v[3] for (file, _, func), v in stats.items() if file.endswith(suffix) and func == name)
    inner_warp = sum(ct for (_, _, func), (*_, callers) in stats.items() if func == "warp_image"
                     for (_, _, caller), (_, _, _, ct) in callers.items() if caller == "dataset_mask_iou")
    found["crop (warp)"] -= inner_warp
    return records, seconds, found


def print_profile(records: int, seconds: float, stages: dict[str, float]) -> None:
    stages = {**stages, "other (the build's loop, fingerprints)": seconds - sum(stages.values())}
    print(f"\nprofile of one 1-worker build under cProfile ({records} records, {seconds:.1f} s, "
          f"{1e3 * seconds / records:.1f} ms a frame with the profiler's overhead)")
    print(f"{'stage':<34} {'ms/frame':>9} {'share':>6}")
    for stage, t in stages.items():
        print(f"{stage:<34} {1e3 * t / records:>9.2f} {100 * t / seconds:>5.1f}%")


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
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts (1 first: the bytes)")
    parser.add_argument("--profile", action="store_true", help="also profile one 1-worker build by stage")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_build_"))
    try:
        root = Path(args.root) if args.root else toy_root(args.frames, work)
        timed_build(root, work / "warm-up", 1, BACKENDS[0])
        seconds, records, cpu = {}, {}, {}
        runs = [(b, w) for w in args.workers for b in BACKENDS]
        for _ in range(args.rounds):
            for backend, workers in runs:
                t, records[backend, workers], c = timed_build(root, work / f"store-{backend}{workers}", workers, backend)
                seconds.setdefault((backend, workers), []).append(t)
                cpu.setdefault((backend, workers), []).append(c)
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"median of {args.rounds} interleaved rounds; load average after the runs {load} (1, 5, 15 min)")
        print(f"{'backend':>8} {'workers':>7} {'records':>8} {'seconds':>8} {'frames/s':>9} {'per core':>9} "
              f"{'CPU ms/frame':>13}  runs (s)")
        for backend, workers in sorted(runs, key=lambda r: (r[1], BACKENDS.index(r[0]))):
            t = float(np.median(seconds[backend, workers]))
            fps = records[backend, workers] / t
            cpu_ms = 1e3 * float(np.median(cpu[backend, workers])) / records[backend, workers] if workers == 1 else None
            cpu_cell = f"{cpu_ms:>13.1f}" if cpu_ms is not None else f"{'-':>13}"
            print(f"{backend:>8} {workers:>7} {records[backend, workers]:>8} {t:>8.1f} {fps:>9.2f} {fps / workers:>9.2f} "
                  f"{cpu_cell}  " + " ".join(f"{x:.1f}" for x in seconds[backend, workers]))
        for workers in args.workers:
            print(f"{workers} worker(s): bvh {np.median(seconds['igl', workers]) / np.median(seconds['bvh', workers]):.2f}x "
                  "the igl baseline's frames/s")
        first = f"store-bvh{args.workers[0]}"
        sizes = member_bytes(work / first)
        total = sum(sizes.values())
        print("\nbytes per record: " + ", ".join(f"{m} {v / 1e3:.1f} kB" for m, v in sizes.items())
              + f", total {total / 1e3:.1f} kB")
        print(f"sdf.npy {sizes[schema.SDF] / 1e3:.1f} kB vs AlignSDF/HOISDF samples {ALIGNSDF_BYTES / 1e3:.0f} kB: "
              f"{sizes[schema.SDF] / ALIGNSDF_BYTES:.3f}x; whole record {total / ALIGNSDF_BYTES:.3f}x")
        checks = str(store.verify_store(work / first)).replace(str(work), "<work>")  # no temporary path in the table
        print(f"(store checks: {checks})")
        assert np.isfinite(total)
        if args.profile:
            print_profile(*profile_stages(root, work / "profiled"))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
