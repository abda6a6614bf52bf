"""HOT3D-Clips build throughput (records/s per core, the fisheye remap included) beside the DexYCB build, one run.

Usage: python -m bench.bench_hot3d [--hot3d-root DIR] [--dexycb-root DIR] [--frames 4] [--rounds 2]

Writes toy HOT3D clips (``make-toy --layout hot3d``, ``--frames`` per clip, 3 clips) and a toy DexYCB of about the
same record count unless the roots are given, then:
- builds each once untimed with 1 worker (modules imported, numba kernels loaded, GL initialised);
- builds each with 1 worker (records/s per core: reading the frames, the renderer's start-up and the index
  included), interleaved over --rounds rounds, medians reported, both with the same record settings
  (``record.crop_size=256``, 4096 hand and 2048 object SDF rows: the hot3d_clips preset's);
- times the HOT3D crop images alone (JPEG decode + FISHEYE624 remap into the crop camera, per record), the part
  the DexYCB build does not have;
- prints the load average and the goal (issue 33: >= 20 records/s per core for HOT3D).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import toy_root
from hoidata.build_sdf import build_store, read_frames
from hoidata.records.settings import load_build_config

GOAL = 20.0  # records/s per core (issue 33)
RECORD = ["record.crop_size=256", "record.sdf_samples_hand=4096", "record.sdf_samples_object=2048", "store.records_per_shard=16"]
SETS = {"hot3d_clips": ("hot3d_clips", ['dataset.splits=["train", "val"]'], "object_models_eval"),
        "dexycb (toy)": ("toy", ['dataset.splits=["train", "val"]'], "models")}


def timed_build(name: str, root: Path, out: Path) -> tuple[float, int]:
    preset, overrides, models = SETS[name]
    cfg = load_build_config(preset, overrides + RECORD)
    shutil.rmtree(out, ignore_errors=True)
    start = time.perf_counter()
    summary = build_store(cfg, root, root / "mano", root / models, out, workers=1, progress=False)
    return time.perf_counter() - start, summary.written


def crop_image_seconds(root: Path) -> tuple[float, int]:
    """Mean seconds per HOT3D record for its crop image alone (decode + remap), and the records timed."""
    cfg = load_build_config("hot3d_clips", SETS["hot3d_clips"][1] + RECORD)
    frames, _ = read_frames(cfg, root, root / "mano", root / "object_models_eval")
    frames[0].load_image()
    start = time.perf_counter()
    for f in frames:
        f.load_image()
    return (time.perf_counter() - start) / len(frames), len(frames)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hot3d-root", type=Path, default=None, help="toy or real HOT3D-Clips folder (default: write toy)")
    p.add_argument("--dexycb-root", type=Path, default=None, help="toy DexYCB folder (default: write one)")
    p.add_argument("--frames", type=int, default=4, help="frames per toy clip (written toys only)")
    p.add_argument("--rounds", type=int, default=2)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_hot3d_") as tmp:
        work = Path(tmp)
        roots = {"hot3d_clips": args.hot3d_root, "dexycb (toy)": args.dexycb_root}
        if roots["hot3d_clips"] is None:
            from hoidata.toy.make import make_toy

            roots["hot3d_clips"] = work / "hot3d"
            make_toy(roots["hot3d_clips"], "hot3d", frames=args.frames, progress=False)
        if roots["dexycb (toy)"] is None:
            roots["dexycb (toy)"] = toy_root(12 * args.frames, work / "dexycb")
        for name, root in roots.items():  # warm-up, untimed
            timed_build(name, root, work / "warm")
        times = {name: [] for name in roots}
        records = {}
        for _ in range(args.rounds):
            for name, root in roots.items():
                seconds, records[name] = timed_build(name, root, work / "store")
                times[name].append(seconds)
        crop_s, crop_n = crop_image_seconds(roots["hot3d_clips"])
    print(f"{'build (1 worker)':<18} {'records':>8} {'seconds':>8} {'records/s/core':>15}")
    rates = {}
    for name in roots:
        seconds = float(np.median(times[name]))
        rates[name] = records[name] / seconds
        print(f"{name:<18} {records[name]:>8} {seconds:>8.2f} {rates[name]:>15.2f}")
    print(f"HOT3D crop image alone (decode + fisheye remap): {crop_s * 1000:.1f} ms per record ({crop_n} records)")
    print(f"HOT3D / DexYCB rate: {rates['hot3d_clips'] / rates['dexycb (toy)']:.2f}; goal >= {GOAL:.0f} records/s "
          f"per core: {'met' if rates['hot3d_clips'] >= GOAL else 'NOT met'}")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"median of {args.rounds} interleaved rounds; load average after the runs {load} (1, 5, 15 min), "
          f"{os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
