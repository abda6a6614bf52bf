"""Loader samples/s per core under ``augment.upstream`` beside upstream HOISDF's own ``Dataset.__getitem__`` (train
mode) on the same toy frames, in one run.

Usage: python -m bench.bench_upstream_aug [--frames 48] [--batch 22] [--batches 6] [--rounds 2] [--workers 0 1]
           [--root DIR] [--upstream CHECKOUT]

- ours: ``make_loader(build_dataset(..., upstream=True))`` over a store built with ``record.upstream_region`` (the
  stored frame file decoded with Pillow, SDF rows drawn, upstream's warp, blur and colour per sample, collated),
  600 + 200 SDF points and as many near points, as training uses;
- upstream: upstream's ``data/dexycb.py`` ``Dataset.__getitem__`` in mode ``train`` from an upstream checkout
  (``--upstream``, e.g. a clone of amathislab/HOISDF; the project holds none of its code), one process, on the same
  frames: its JPEG decode, SDF ``.npy`` read (synthetic rows in its layout, 20,000 per block like AlignSDF's), masks
  unpacked and warped, ``data_aug``, tensors. Its Dataset is made with ``__new__`` and given what ``__getitem__``
  reads; ``libyana`` / ``pytorch3d`` / ``manopth`` are stubbed when not installed. Without ``--upstream`` that
  column prints "not run".

Per core: samples/s divided by the processes that work (1 + workers, at most the machine's cores). Interleaved
over ``--rounds`` rounds, medians, and ours per core / upstream's per core in each round; the load average before
and after and the store's size are printed with the table.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

from bench.common import toy_train_root
from hoidata import schema
from hoidata.build_sdf import build_store, read_frames
from hoidata.records.settings import load_build_config
from hoisdf.data import StoreSpec, build_dataset, make_loader

N_HAND, N_OBJECT, NEAR, SEED = 600, 200, 0.05, 0
SETTINGS = ['dataset.splits=["train"]', 'dataset.sides=["right"]', 'record.upstream_region=["train"]',
            "store.records_per_shard=32"]
SDF_ROWS = 20000  # per block in the synthetic upstream SDF files


def ours_rate(store: Path, batch: int, batches: int, workers: int) -> float:
    """samples/s of the project's loader under augment.upstream (first batch untimed)."""
    data = build_dataset([StoreSpec(store)], batch, batch * (batches + 1) * max(1, workers), SEED, N_HAND, N_OBJECT,
                         NEAR, training=True, upstream=True)
    data.set_epoch(0)
    it = iter(make_loader(data, workers))
    next(it)
    start, n = time.perf_counter(), 0
    for _ in range(batches):
        n += len(next(it)["key"])
    return n / (time.perf_counter() - start)


def _stub_modules() -> None:
    """Stand-ins for upstream's module-level imports this path never calls, when they are not installed."""
    for name, attrs in (("libyana.meshutils.meshio", ("fast_load_obj",)), ("pytorch3d.io", ("load_obj",)),
                        ("manopth.manopth.manolayer", ("ManoLayer",))):
        try:
            __import__(name)
        except ImportError:
            parts = name.split(".")
            for i in range(1, len(parts) + 1):
                sys.modules.setdefault(".".join(parts[:i]), types.ModuleType(".".join(parts[:i])))
            for attr in attrs:
                setattr(sys.modules[name], attr, None)


def upstream_dataset(root: Path, work: Path):
    """Upstream's DexYCB Dataset (train mode) over the toy's right-hand training frames, made with ``__new__`` (in
    a process whose PYTHONPATH starts with the checkout: :func:`upstream_rate`)."""
    _stub_modules()
    import torchvision.transforms as T
    from data import dataset_util, dexycb  # noqa: the checkout's modules

    from hoidata.objects import load_points, object_points_path

    frames, _ = read_frames(load_build_config("toy", SETTINGS), root, root / "mano")
    ds = dexycb.Dataset.__new__(dexycb.Dataset)
    ds.mode, ds.inp_res, ds.heatmap_res, ds.transform, ds.image_fast_path = "train", 256, 128, T.ToTensor(), "/"
    ds.num_samp_hand, ds.num_samp_obj, ds.dist, ds.hand_sdf_scale, ds.obj_sdf_scale = N_HAND, N_OBJECT, NEAR, 3.1, 3.1
    ds.hue, ds.contrast, ds.brightness, ds.saturation, ds.blur_radius = 0.15, 0.5, 0.5, 0.5, 0.5
    ds.scale_jittering, ds.center_jittering, ds.max_rot = 0.2, 0.1, np.pi
    ds.mano_handcomponent_right = ds.mano_handcomponent_left = np.eye(45)
    ds.mano_handmean = np.zeros(45)
    ds.sample_dict, ds.sample_list_processed, ds.hand_segs, ds.obj_segs = {}, [], [], []
    ds.sdf_path_list, ds.sdf_index_list, ds.obj_bbox3d = [], [], {}
    rng = np.random.default_rng(0)
    for f in frames:
        key = schema.record_key(f.dataset, f.split, f.frame_id)
        pose_m = np.zeros(51, np.float32)
        pose_m[:48] = f.mano_pose
        ds.sample_dict[key] = {
            "color_file": str(f.image_path), "intrinsics": {"fx": f.K[0, 0], "fy": f.K[1, 1], "ppx": f.K[0, 2],
                                                            "ppy": f.K[1, 2]},
            "pose_m": pose_m.tolist(), "mano_betas": [0.0] * 10, "joint_3d": f.joints_3d.tolist(),
            "joint_2d": f.joints_2d.tolist(), "pose_y": [f.object_pose[:3].tolist()], "ycb_ids": [f.object_id],
            "ycb_grasp_ind": 0, "mano_side": f.side}
        ds.sample_list_processed.append(key)
        ds.hand_segs.append(np.packbits(np.zeros((480, 640), bool)))
        ds.obj_segs.append(np.packbits(np.zeros((480, 640), bool)))
        ds.obj_bbox3d[f.object_id] = dataset_util.get_bbox21_3d_from_dict(
            {0: load_points(object_points_path(root / "models", f.object_name))})[0]
        xyz = f.joints_3d[0][None] + rng.normal(0, 0.05, (2 * SDF_ROWS, 3))
        rows = np.concatenate([xyz, rng.uniform(-0.06, 0.06, (2 * SDF_ROWS, 2)), np.zeros((2 * SDF_ROWS, 1))], 1)
        np.save(work / f"{key}.npy", rows.astype(np.float32))
        ds.sdf_path_list.append(str(work / f"{key}.npy"))
        ds.sdf_index_list.append(np.array([SDF_ROWS, SDF_ROWS]))
    return ds


def time_upstream(root: Path, work: Path, n: int) -> float:
    """samples/s of upstream's ``__getitem__`` in this process (first item untimed)."""
    ds = upstream_dataset(root, work)
    ds.__getitem__(0)
    start = time.perf_counter()
    for i in range(n):
        ds.__getitem__(i % len(ds.sample_list_processed))
    return n / (time.perf_counter() - start)


def upstream_rate(checkout: Path, root: Path, work: Path, n: int) -> float:
    """:func:`time_upstream` in a child process with the checkout first on its PYTHONPATH (upstream's modules import
    each other as top-level ``data`` and ``main``)."""
    project = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(checkout), str(project), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-m", "bench.bench_upstream_aug", "--time-upstream", str(root), str(work),
                           str(n)], env=env, capture_output=True, text=True, cwd=str(project))
    if done.returncode:
        raise SystemExit(f"{checkout}: upstream's loader failed:\n{done.stderr[-2000:]}")
    return float(done.stdout.split()[-1])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--batch", type=int, default=22)
    ap.add_argument("--batches", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--root", type=Path, help="an existing toy DexYCB (bench.common.toy_train_root layout)")
    ap.add_argument("--upstream", type=Path, help="an upstream HOISDF checkout (its data/dexycb.py is timed)")
    ap.add_argument("--time-upstream", nargs=3, help=argparse.SUPPRESS)  # ROOT WORK N: the child of upstream_rate
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    if args.time_upstream:
        print(time_upstream(Path(args.time_upstream[0]), Path(args.time_upstream[1]), int(args.time_upstream[2])))
        return
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        root = args.root or toy_train_root(args.frames, work)
        build_store(load_build_config("toy", SETTINGS), root, root / "mano", root / "models", work / "store",
                    workers=1, progress=False)
        stored = [p.stat().st_size for p in (work / "store").glob("shard-*.tar")]
        up = args.upstream.resolve() if args.upstream else None
        rates: dict[str, list[float]] = {}
        load_before = os.getloadavg()[0]
        for _ in range(args.rounds):
            for workers in args.workers:
                rates.setdefault(f"ours, {workers} worker(s)", []).append(
                    ours_rate(work / "store", args.batch, args.batches, workers))
            if up is not None:
                rates.setdefault("upstream __getitem__", []).append(
                    upstream_rate(up, root.resolve(), work, args.batch * args.batches))
    print_table(rates, args.workers, up is not None, load_before, sum(stored))


def print_table(rates: dict, workers_list, with_upstream: bool, load_before: float, store_bytes: int) -> None:
    """Medians per loader, per core, and ours per core / upstream's per core (median and per round)."""
    cores = os.cpu_count() or 1
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"store: {store_bytes / 1e6:.2f} MB of shards; samples/s, median of {len(next(iter(rates.values())))} "
          f"interleaved rounds; load average {load_before:.2f} before, {load} after (1, 5, 15 min), {cores} cores")
    print(f"{'loader':<24} {'samples/s':>10} {'per core':>9} {'x upstream':>11}  x upstream per round")
    upstream = np.array(rates["upstream __getitem__"]) if with_upstream else None
    for workers in workers_list:
        name = f"ours, {workers} worker(s)"
        per_core = np.array(rates[name]) / min(1 + workers, cores)
        ratio = per_core / upstream if with_upstream else None
        print(f"{name:<24} {np.median(rates[name]):>10.1f} {np.median(per_core):>9.1f} "
              + (f"{np.median(ratio):>11.2f}  " + " ".join(f"{x:.2f}" for x in ratio) if with_upstream else ""))
    if not with_upstream:
        print(f"{'upstream __getitem__':<24} {'not run (--upstream CHECKOUT)':>20}")
    else:
        rate = float(np.median(upstream))
        print(f"{'upstream __getitem__':<24} {rate:>10.1f} {rate:>9.1f}")

if __name__ == "__main__":
    main()
