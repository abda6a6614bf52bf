"""Training, inference and data-loading throughput of HOISDF, side by side in one run.

Usage: python -m bench.bench_train [--config toy] [--store STORE] [--mano DIR] [--device cuda]
           [--batch-size B] [--warmup N] [--steps N] [--frames N] [--infer-batch B]
           [--workers 0 1 2 ...] [--loader-batch B] [--loader-batches N] [--json OUT]
           [--compile [--compile-mode MODE] [--precision fp32|bf16]] [--skip train infer loader]

Model: the paper's full-size HOISDF by default (ResNet-50, 256 px input, 600 + 200 query points, 64^3
grid, 6 + 4 hand and 3 object transformer layers); ``--config toy`` for the small CPU model. Data: a
small toy DexYCB store built in a temporary folder with 512 px crops (so the 256 px network input is the
central crop at context 2), unless ``--store`` names an existing store; MANO: the procedural toy hand
unless ``--mano``. Defaults depend on the device (CUDA: batch 22 as the paper, 20 timed steps; CPU:
batch 4, 3 timed steps, so the whole run takes a few minutes on 2 cores).

Measured:

1. train: ``Trainer.train_step`` (augmentation on the device, forward, loss, backward, AdamW step) on
   loader batches already in memory (the loader is not in the timing), for both query-point paths
   ("gt": noisy near-surface ground-truth points; "field": field-guided grid sampling), ``--warmup``
   untimed steps then ``--steps`` timed ones: ms/step, samples/s, peak GPU memory. bf16 autocast on
   CUDA, as the trainer does.
2. infer: eval mode, no_grad, bf16 autocast on CUDA, field-guided sampling, on test-time inputs (the
   central crop, prepared before timing) at batch 1 and at ``--infer-batch``: frames/s, beside the
   paper's 30.7 FPS (TITAN RTX), and where the time goes: backbone, query-point sampling (SDF decoders
   on the grid), and the rest of the pose path (pixel features, tokens, transformers, heads), from
   wrappers around those three calls (with a CUDA synchronize around each).
3. loader: ``make_loader(build_dataset(...))`` with 0, 1, 2, ... workers at batch ``--loader-batch``
   (22, the paper's, on every device), no model: time to the first batch (worker start-up) and
   samples/s after it, also per worker; then ``augment_batch`` per training batch on the device
   (training augmentation and the test-time crop).
4. with ``--compile``: eager against ``torch.compile`` on the same weights and batches (``compile_bench.py``):
   inference with the compact and the fixed-shape sampling path eager and the fixed-shape model compiled
   (fullgraph; CUDA graphs on CUDA) at batch 1 and ``--infer-batch``, then training steps eager and compiled
   (fixed-shape model) for both query-point paths. ``--skip`` leaves sections out (e.g. the loader).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import tempfile
import time
from contextlib import contextmanager, nullcontext
from dataclasses import replace
from pathlib import Path

import torch

from bench.common import NOISE, resolve_device, store_and_mano, sync, test_inputs
from hoisdf.config import load_train_config, sdf_rows
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.augment import augment_batch
from hoisdf.model import build_model
from hoisdf.training.trainer import Trainer, to_device

PAPER_FPS = 30.7  # HOISDF paper, TITAN RTX


def autocast(device: torch.device):
    """bf16 autocast on CUDA (as the trainer and the evaluator), nothing on the CPU."""
    return torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda" else nullcontext()


# --- batches ------------------------------------------------------------------------------------------------
def first_samples(batches: list[dict], n: int) -> dict:
    """The first ``n`` samples of a list of loader batches, as one batch."""
    out = {}
    for k, v in batches[0].items():
        values = [b[k] for b in batches]
        out[k] = torch.cat(values)[:n] if torch.is_tensor(v) else [x for v in values for x in v][:n]
    return out


# --- 1. training steps --------------------------------------------------------------------------------------
def bench_train(trainer: Trainer, batches: list[dict], points: str, warmup: int, steps: int) -> dict:
    device = trainer.device
    trainer.model.train()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    for i in range(warmup):
        trainer.train_step(batches[i % len(batches)], points, NOISE)
    sync(device)
    start = time.perf_counter()
    for i in range(steps):
        trainer.train_step(batches[(warmup + i) % len(batches)], points, NOISE)
    sync(device)
    seconds = (time.perf_counter() - start) / steps
    return {"points": points, "batch": len(batches[0]["key"]), "ms_per_step": seconds * 1e3,
            "samples_per_s": len(batches[0]["key"]) / seconds, "peak_gib": peak_gib(device)}


def peak_gib(device: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None


# --- 2. inference -------------------------------------------------------------------------------------------
@contextmanager
def stage_times(model, device: torch.device, times: dict):
    """Add the seconds spent in the backbone, the query-point sampling and the pose path to ``times``."""
    stages = {"backbone": (model.backbone, "forward"), "sampling": (model, "_queries"), "pose": (model, "_pose")}

    def timed(name, fn):
        def call(*args, **kwargs):
            sync(device)
            start = time.perf_counter()
            out = fn(*args, **kwargs)
            sync(device)
            times[name] = times.get(name, 0.0) + time.perf_counter() - start
            return out
        return call

    for name, (owner, attr) in stages.items():
        setattr(owner, attr, timed(name, getattr(owner, attr)))  # an instance attribute shadows the method
    try:
        yield
    finally:
        for owner, attr in stages.values():
            delattr(owner, attr)


@torch.no_grad()
def bench_infer(model, inputs: dict, batch: int, frames: int, warmup: int, device: torch.device) -> dict:
    x = {k: v[:batch] for k, v in inputs.items()}
    iters = max(1, math.ceil(frames / batch))
    with autocast(device):
        for _ in range(max(1, warmup)):
            model(x, points="field")
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        times: dict[str, float] = {}
        sync(device)
        start = time.perf_counter()
        with stage_times(model, device, times):
            for _ in range(iters):
                model(x, points="field")
        sync(device)
    seconds = time.perf_counter() - start
    ms = {k: v / (iters * batch) * 1e3 for k, v in times.items()}
    ms["other"] = seconds / (iters * batch) * 1e3 - sum(ms.values())
    return {"batch": batch, "frames": iters * batch, "frames_per_s": iters * batch / seconds,
            "ms_per_frame": seconds / (iters * batch) * 1e3, "stage_ms_per_frame": ms, "peak_gib": peak_gib(device)}


# --- 3. loader and augmentation ----------------------------------------------------------------------------
def bench_loader(store: Path, config, batch: int, workers: int, batches: int, device: torch.device) -> dict:
    m, t = config.model, config.train
    data = build_dataset([StoreSpec(store)], batch, batch * (batches + 1) * max(1, workers), t.seed,
                         *sdf_rows(config), t.near, t.shuffle_buffer, training=True)
    start = time.perf_counter()
    it = iter(make_loader(data, workers, pin_memory=device.type == "cuda"))
    next(it)
    first = time.perf_counter()
    samples = 0
    for _ in range(batches):
        samples += len(next(it)["key"])
    seconds = time.perf_counter() - first
    del it  # stops the workers
    rate = samples / seconds
    return {"workers": workers, "batch": batch, "first_batch_s": first - start, "samples": samples,
            "samples_per_s": rate, "per_worker": rate / max(1, workers)}


def bench_augment(batch: dict, config, device: torch.device, reps: int) -> dict:
    batch = to_device(batch, device)
    generator = torch.Generator().manual_seed(0)
    out = {"batch": len(batch["key"])}
    for train in (True, False):
        augment_batch(batch, config.augment, generator, train)  # warm-up
        sync(device)
        start = time.perf_counter()
        for _ in range(reps):
            augment_batch(batch, config.augment, generator, train)
        sync(device)
        out["train_ms" if train else "test_ms"] = (time.perf_counter() - start) / reps * 1e3
    return out


def fmt(value: float | None, spec: str) -> str:
    """``value`` formatted by ``spec``, or "-" (not measured) right-aligned to the same width."""
    return format(value, spec) if value is not None else format("-", f">{spec.split('.')[0]}")


def print_train(rows: list[dict]) -> None:
    print("\ntraining (train_step on batches in memory; augmentation + forward + loss + backward + AdamW)")
    print(f"{'points':>6} {'batch':>5} {'ms/step':>9} {'samples/s':>10} {'peak GiB':>9}")
    for r in rows:
        print(f"{r['points']:>6} {r['batch']:>5} {r['ms_per_step']:>9.0f} {r['samples_per_s']:>10.2f} "
              f"{fmt(r['peak_gib'], '9.2f')}", flush=True)


def run_infer(config, mano, batches: list[dict], infer_batch: int, frames: int, warmup: int,
              device: torch.device) -> list[dict]:
    """Section 2 on one model: both grid paths at batch 1 and ``infer_batch``."""
    model = build_model(config.model, mano).to(device).eval()
    inputs = test_inputs(first_samples(batches, infer_batch), config, device)
    rows = []
    for grid_path in ("direct", "projected"):  # the baseline grid path and the default one, same weights
        model.features.project_grid = grid_path == "projected"
        for b in sorted({1, infer_batch}):
            rows.append({"grid_path": grid_path, **bench_infer(model, inputs, b, frames, warmup, device)})
    print(f"\ninference (field-guided points, eval, no_grad{', bf16' if device.type == 'cuda' else ''}); paper: "
          f"{PAPER_FPS} FPS on a TITAN RTX; grid path: direct = sample all pyramid channels per grid point, "
          "projected = sdf_in's first layer applied to the pyramid before sampling (the default, exact)")
    print(f"{'grid path':>9} {'batch':>5} {'frames':>6} {'frames/s':>9} {'ms/frame':>9} {'backbone':>9} "
          f"{'sampling':>9} {'pose':>7} {'other':>7} {'peak GiB':>9}")
    for r in rows:
        s = r["stage_ms_per_frame"]
        print(f"{r['grid_path']:>9} {r['batch']:>5} {r['frames']:>6} {r['frames_per_s']:>9.2f} "
              f"{r['ms_per_frame']:>9.0f} {s['backbone']:>9.0f} {s['sampling']:>9.0f} {s['pose']:>7.0f} "
              f"{s['other']:>7.0f} {fmt(r['peak_gib'], '9.2f')}", flush=True)
    return rows


def print_loader(rows: list[dict], augment: dict, loader_batch: int, loader_batches: int, device) -> None:
    print(f"\nloader (make_loader(build_dataset), batch {loader_batch}, {loader_batches} timed batches after "
          "the first)")
    print(f"{'workers':>7} {'first batch s':>13} {'samples/s':>10} {'per worker':>11}")
    for r in rows:
        print(f"{r['workers']:>7} {r['first_batch_s']:>13.2f} {r['samples_per_s']:>10.1f} {r['per_worker']:>11.1f}")
    b = augment["batch"]
    print(f"augment_batch on {device}, batch {b}: training {augment['train_ms']:.1f} ms/batch "
          f"({augment['train_ms'] / b:.1f} ms/sample), test-time crop {augment['test_ms']:.1f} ms/batch "
          f"({augment['test_ms'] / b:.1f} ms/sample)")


# --- main ---------------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="pipelines/<name>.toml (default: the paper's full-size model)")
    p.add_argument("--store", default=None, help="an existing store (default: a toy store in a temp folder)")
    p.add_argument("--mano", default=None, help="MANO folder (default: the procedural toy hand)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--batch-size", type=int, default=None, help="training batch (default 22 on CUDA, 4 on CPU)")
    p.add_argument("--warmup", type=int, default=None, help="untimed steps first (default 3 on CUDA, 1 on CPU)")
    p.add_argument("--steps", type=int, default=None, help="timed training steps per path (default 20 / 3)")
    p.add_argument("--frames", type=int, default=None, help="timed inference frames per batch size (default 200 / 8)")
    p.add_argument("--infer-batch", type=int, default=None, help="the larger inference batch (default 22 / 4)")
    p.add_argument("--workers", type=int, nargs="+", default=None, help="loader worker counts (default 0 1 2 4 8 ...)")
    p.add_argument("--loader-batch", type=int, default=22, help="loader batch size (default 22)")
    p.add_argument("--loader-batches", type=int, default=None, help="timed loader batches (default 50 / 20)")
    p.add_argument("--json", type=Path, default=None, metavar="OUT", help="write the numbers to this file")
    p.add_argument("--compile", action="store_true", help="also time torch.compile against eager (section 4)")
    p.add_argument("--compile-mode", default=None, help="torch.compile mode (default reduce-overhead on CUDA)")
    p.add_argument("--backend", default="inductor", help="torch.compile backend (eager: a quick check of the script)")
    p.add_argument("--precision", choices=("fp32", "bf16"), default=None,
                   help="autocast of the compile section (default bf16 on CUDA, fp32 on the CPU)")
    p.add_argument("--skip", nargs="*", default=[], choices=("train", "infer", "loader"), help="sections to leave out")
    return p


def bench_compile(args, config, mano, batches: list[dict], infer_batch: int, frames: int, warmup: int,
                  steps: int, device: torch.device) -> dict:
    """Section 4: eager vs compiled inference and training on the same weights (see compile_bench.py)."""
    from bench.compile_bench import (
        compile_inference,
        inference_rows,
        print_rows,
        training_rows,
    )

    precision = args.precision or ("bf16" if device.type == "cuda" else "fp32")
    fixed = replace(config.model, fixed_shape=True)
    torch.manual_seed(0)
    compact = build_model(config.model, mano).to(device).eval()
    eager_fixed = build_model(fixed, mano).to(device).eval()
    eager_fixed.load_state_dict(compact.state_dict())
    inputs = test_inputs(first_samples(batches, infer_batch), config, device)
    infer_rows = [] if "infer" in args.skip else inference_rows(
        compact, eager_fixed, compile_inference(eager_fixed, device, args.compile_mode, args.backend), inputs,
        sorted({1, infer_batch}), frames, warmup, device, precision)
    del compact, eager_fixed, inputs
    generator = torch.Generator().manual_seed(0)
    train_batches = [augment_batch(to_device(b, device), config.augment, generator, train=True) for b in batches]
    train_rows = [] if "train" in args.skip else training_rows(
        lambda: build_model(fixed, mano), mano, config.loss, fixed.cls_dist, train_batches, warmup, steps, device,
        precision, args.compile_mode, args.backend)
    print(f"\ncompiled vs eager ({precision}, torch {torch.__version__}; inference: fixed = whole grid, boxes as "
          "masks, compiled with fullgraph=True; training: fixed-shape model, graph breaks allowed)")
    print_rows(infer_rows, train_rows)
    return {"precision": precision, "infer": infer_rows, "train": train_rows}


def main() -> None:
    args = build_parser().parse_args()
    device = resolve_device(args.device)
    cuda = device.type == "cuda"

    def pick(value, gpu, cpu):
        return value if value is not None else (gpu if cuda else cpu)

    batch, warmup, steps = pick(args.batch_size, 22, 4), pick(args.warmup, 3, 1), pick(args.steps, 20, 3)
    frames, infer_batch = pick(args.frames, 200, 8), pick(args.infer_batch, 22, 4)
    loader_batches = pick(args.loader_batches, 50, 20)
    cores = os.cpu_count() or 1
    workers = args.workers or [0, 1, 2] + [w for w in (4, 8, 16) if w <= cores]

    from hoidata.hand import load_mano

    work = Path(tempfile.mkdtemp(prefix="bench_train_"))
    try:
        store, mano_dir = store_and_mano(args, work, records=32)
        mano = load_mano(mano_dir, side="right")
        n_batches = max(min(warmup + steps, 4), math.ceil(infer_batch / batch))  # distinct batches held in memory
        config = load_train_config(args.config, [f"train.batch_size={batch}", "train.workers=0",
                                                 f"train.epoch_samples={batch * n_batches}"])
        m = config.model
        print(f"device {device}; model ResNet-{m.depth}, {m.image_size} px, {m.hand_queries}+{m.object_queries} points, "
              f"{m.grid_resolution}^3 grid, layers {m.hand_layers}+{m.decoder_layers}/{m.object_layers}; "
              f"store {store}; {cores} CPU cores", flush=True)

        trainer = Trainer(config, [StoreSpec(store)], mano, work / "run", device)
        torch.manual_seed(0)
        batches = list(trainer.loader)[:n_batches]
        result = {"device": str(device), "cpu_cores": cores, "config": args.config or "default",
                  "model": config.as_dict()["model"], "store": str(store) if args.store else "toy (temporary)",
                  "paper_fps": PAPER_FPS}
        if "train" not in args.skip:
            result["train"] = [bench_train(trainer, batches, points, warmup, steps) for points in ("gt", "field")]
            print_train(result["train"])
        del trainer
        if cuda:
            torch.cuda.empty_cache()
        if "infer" not in args.skip:
            result["infer"] = run_infer(config, mano, batches, infer_batch, frames, warmup, device)
        if "loader" not in args.skip:
            result["loader"] = [bench_loader(store, config, args.loader_batch, w, loader_batches, device)
                                for w in workers]
            result["augment"] = bench_augment(first_samples(batches, batch), config, device, reps=pick(None, 50, 10))
            print_loader(result["loader"], result["augment"], args.loader_batch, loader_batches, device)
        if args.compile:
            result["compile"] = bench_compile(args, config, mano, batches, infer_batch, frames, warmup, steps, device)
        if args.json:
            args.json.write_text(json.dumps(result, indent=2))
            print(f"wrote {args.json}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
