"""Evaluation throughput of ``hoisdf.evaluate`` with a freshly initialised HOISDF (no training: speed only).

Usage: python -m bench.bench_evaluate [--config toy] [--store STORE] [--mano DIR] [--device cuda]
           [--frames N] [--batch-size B] [--workers N] [--json OUT] [section.key=value ...]

Model: the paper's full-size HOISDF by default (``--config toy`` for the small one), randomly
initialised and saved as a checkpoint payload ``{"model", "config", "progress"}`` with
``hoisdf.training.checkpoint.save_checkpoint`` into a temporary run folder. Data: a toy DexYCB store with 512 px
crops built in a temporary folder (as bench_train.py), unless ``--store``. Defaults depend on the device
(CUDA: 352 frames at batch 22; CPU: 16 frames at batch 4, a minute or two on 2 cores).

Measured, in one run, on the first ``--frames`` records of the store:

1. load: ``load_for_eval`` (read the checkpoint, build the model, move it to the device);
2. infer: ``hoisdf.evaluate.infer`` (loader workers decode, test-time crop, batched forward with
   field-guided points, no_grad, bf16 autocast on CUDA, ground-truth MANO of every frame), after a
   warm-up ``infer`` of one batch: frames/s;
3. metrics, apart from inference: ``score`` + ``hoisdf.scoring.metrics.summarize`` (overall and per object),
   and the mean-pose baseline (``mean_hand`` + ``score``) that evaluate prints beside it;
4. end to end: ``evaluate(..., plausibility=0)`` (all of the above plus the result files), frames/s.
   The plausibility report (off here) is separate and per sample.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.common import resolve_device, store_and_mano, sync
from hoisdf.config import load_train_config
from hoisdf.evaluate import evaluate
from hoisdf.evaluation.inference import infer, load_for_eval
from hoisdf.evaluation.model_scores import mean_hand, score
from hoisdf.model import build_model
from hoisdf.scoring import metrics as M
from hoisdf.training.checkpoint import CHECKPOINTS, LAST, save_checkpoint

PAPER_FPS = 30.7  # HOISDF paper, TITAN RTX


def fresh_run(run: Path, config, mano) -> Path:
    """A run folder holding a randomly initialised model as ``checkpoints/last.pt``."""
    torch.manual_seed(0)
    model = build_model(config.model, mano)
    payload = {"model": model.state_dict(), "config": config.as_dict(),
               "progress": {"epoch": 0, "step": 0, "global_step": 0}}
    return save_checkpoint(run / CHECKPOINTS / LAST, payload)


def timed(fn, device: torch.device):
    """(result, seconds) of ``fn()``, synchronised on CUDA."""
    sync(device)
    start = time.perf_counter()
    out = fn()
    sync(device)
    return out, time.perf_counter() - start


def metrics_of(col, objects: dict) -> dict:
    """The per-sample metrics and their summary, as ``evaluate`` computes them."""
    obj_verts = [objects[n][0] for n in col.names]
    valid = np.ones(len(col.keys), bool)
    per_sample = score(col.get("joints"), col.get("gt_joints"), col.get("verts"), col.get("gt_verts"),
                       col.get("obj_pose"), col.get("gt_obj_pose"), obj_verts, valid)
    return M.summarize(per_sample, np.asarray(col.names))


def baseline_of(col, objects: dict, store: Path, mano, index) -> dict:
    """The mean-pose baseline's metrics (mean hand of the store placed at the wrist, object at its anchor)."""
    mean_j, mean_v, _ = mean_hand(store, mano, index=index)
    root, verts = col.get("root")[:, None], col.get("verts")
    pose = np.tile(np.eye(4), (len(root), 1, 1))
    pose[:, :3, 3] = col.get("obj_center")
    obj_verts = [objects[n][0] for n in col.names]
    per_sample = score(mean_j + root, col.get("gt_joints"), None if verts is None else mean_v + root,
                       col.get("gt_verts"), pose, col.get("gt_obj_pose"), obj_verts, np.ones(len(root), bool))
    return M.summarize(per_sample)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="pipelines/<name>.toml (default: the paper's full-size model)")
    p.add_argument("--store", default=None, help="an existing store (default: a toy store in a temp folder)")
    p.add_argument("--mano", default=None, help="MANO folder (default: the procedural toy hand)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--frames", type=int, default=None, help="records evaluated (default 352 on CUDA, 16 on CPU)")
    p.add_argument("--batch-size", type=int, default=None, help="evaluation batch (default 22 on CUDA, 4 on CPU)")
    p.add_argument("--workers", type=int, default=None, help="loader processes (default min(4, CPU cores))")
    p.add_argument("--json", type=Path, default=None, metavar="OUT", help="write the numbers to this file")
    p.add_argument("overrides", nargs="*", metavar="section.key=value", help="model settings, e.g. model.depth=18")
    return p


def main() -> None:
    args = build_parser().parse_args()
    device = resolve_device(args.device)
    cuda = device.type == "cuda"
    frames = args.frames or (352 if cuda else 16)
    batch = args.batch_size or (22 if cuda else 4)
    workers = args.workers if args.workers is not None else min(4, os.cpu_count() or 1)

    from hoidata.hand import load_mano
    from hoidata.store import read_index

    work = Path(tempfile.mkdtemp(prefix="bench_evaluate_"))
    try:
        store, mano_dir = store_and_mano(args, work, records=frames)
        mano = load_mano(mano_dir, side="right")
        config = load_train_config(args.config, args.overrides)
        ckpt = fresh_run(work / "run", config, mano)
        index = read_index(store)
        objects = index.objects
        m = config.model
        print(f"device {device}; model ResNet-{m.depth}, {m.image_size} px, {m.hand_queries}+{m.object_queries} points, "
              f"{m.grid_resolution}^3 grid (randomly initialised); store {store} ({len(index.keys)} records); "
              f"batch {batch}, {workers} loader workers", flush=True)

        (model, config, _), load_s = timed(lambda: load_for_eval(ckpt, mano, device), device)
        opts = {"indexes": {store: index}, "progress": False, "workers": workers}
        infer(model, mano, config, [store], batch, device, batch, **opts)  # warm-up: one batch
        if cuda:
            torch.cuda.reset_peak_memory_stats(device)
        col, infer_s = timed(lambda: infer(model, mano, config, [store], batch, device, frames, **opts), device)
        n = len(col.keys)
        peak = torch.cuda.max_memory_allocated(device) / 2**30 if cuda else None
        summary, metrics_s = timed(lambda: metrics_of(col, objects), device)
        _, baseline_s = timed(lambda: baseline_of(col, objects, store, mano, index), device)
        result, total_s = timed(lambda: evaluate(ckpt, [store], mano_dir, work / "eval", batch_size=batch, device=device,
                                                 limit=frames, plausibility=0, progress=False, workers=workers), device)

        print(f"\n{n} frames; paper: {PAPER_FPS} FPS on a TITAN RTX (model only)")
        print(f"{'stage':<36} {'seconds':>8} {'ms/frame':>9} {'frames/s':>9}")
        rows = [("load_for_eval (checkpoint, model)", load_s, None),
                (f"infer (batch {batch}, {workers} workers)", infer_s, n),
                ("metrics: score + summarize", metrics_s, n),
                ("mean-pose baseline (whole store)", baseline_s, None),
                ("evaluate end to end, plausibility 0", total_s, result["samples"])]
        for name, seconds, count in rows:
            per = f"{seconds / count * 1e3:>9.1f} {count / seconds:>9.2f}" if count else f"{'-':>9} {'-':>9}"
            print(f"{name:<36} {seconds:>8.2f} {per}")
        if peak is not None:
            print(f"peak GPU memory during infer: {peak:.2f} GiB")
        print(f"(random weights: MJE {summary['all'].get('rr_mje', float('nan')):.0f} mm, meaningless; speed only)")

        if args.json:
            out = {"device": str(device), "cpu_cores": os.cpu_count(), "config": args.config or "default",
                   "store": str(store) if args.store else "toy (temporary)", "frames": n, "batch": batch,
                   "workers": workers, "paper_fps": PAPER_FPS, "peak_gib": peak,
                   "seconds": {"load": load_s, "infer": infer_s, "metrics": metrics_s, "baseline": baseline_s,
                               "evaluate": total_s},
                   "frames_per_s": {"infer": n / infer_s, "evaluate": result["samples"] / total_s},
                   "metrics_ms_per_frame": metrics_s / n * 1e3}
            args.json.write_text(json.dumps(out, indent=2))
            print(f"wrote {args.json}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
