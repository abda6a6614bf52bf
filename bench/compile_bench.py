"""Eager against ``torch.compile`` for HOISDF, side by side (shared by ``bench_train.py --compile``, ``bench_gpu.py``).

Needs only torch and the model code (no stores, no loader), so it also runs where the data packages are not
installed. Inputs are batches already on the device: training batches after the training augmentation, test
inputs after the test-time crop (see ``bench.common.test_inputs``).

* inference: eval, no_grad, field-guided points; ``compact`` (the default sampling path, data-dependent
  shapes) and ``fixed`` (``model.fixed_shape``: the whole grid with the boxes as masks) eager, then ``fixed``
  compiled with ``fullgraph=True`` (mode ``reduce-overhead`` on CUDA: CUDA graphs); frames/s at each batch size,
  the compile time (first call), and the largest output difference to eager ``fixed``.
* training: forward + loss + backward + AdamW step on the same batches, eager and compiled (graph breaks
  allowed: the "gt" path draws its jitter from a CPU generator), for "gt" and "field" points; ms/step,
  samples/s, peak GPU memory.
"""

from __future__ import annotations

import time

import torch

from bench.common import NOISE, sync
from hoisdf.model.precision import autocast
from hoisdf.training.losses import HOISDFLoss

COMPARED = ("joints", "verts", "obj_translation", "obj_rotation", "hand_query", "obj_query")


def peak_gib(device: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def compile_inference(model, device: torch.device, mode: str | None, backend: str = "inductor"):
    """``torch.compile(model, fullgraph=True, dynamic=False)``; mode default: CUDA graphs on CUDA. ``backend``
    other than inductor (e.g. "eager": graph capture only) checks that the script runs, without code generation."""
    if backend != "inductor":
        return torch.compile(model, fullgraph=True, dynamic=False, backend=backend)
    mode = mode or ("reduce-overhead" if device.type == "cuda" else "default")
    return torch.compile(model, fullgraph=True, dynamic=False, mode=mode)


@torch.no_grad()
def time_inference(model, inputs: dict, batch: int, frames: int, warmup: int, device, precision: str) -> dict:
    """frames/s of ``model(x, points="field")`` on the first ``batch`` samples; the first call is timed apart
    (it compiles a compiled model)."""
    x = {k: v[:batch] for k, v in inputs.items()}
    iters = max(1, -(-frames // batch))
    with autocast(device, precision):
        sync(device)
        start = time.perf_counter()
        model(x, points="field")
        sync(device)
        first = time.perf_counter() - start
        for _ in range(max(0, warmup - 1)):
            model(x, points="field")
        reset_peak(device)
        sync(device)
        start = time.perf_counter()
        for _ in range(iters):
            out = model(x, points="field")
        sync(device)
        seconds = time.perf_counter() - start
        out = {k: out[k].detach().clone() for k in COMPARED if k in out}  # CUDA-graph outputs are reused
    return {"batch": batch, "frames": iters * batch, "frames_per_s": iters * batch / seconds,
            "ms_per_frame": seconds / (iters * batch) * 1e3, "first_call_s": first, "peak_gib": peak_gib(device),
            "outputs": out}


def max_difference(a: dict, b: dict) -> float:
    return max(float((a[k].float() - b[k].float()).abs().max()) for k in a if k in b)


def same_points(a: dict, b: dict) -> bool:
    return all(torch.equal(a[k], b[k]) for k in ("hand_query", "obj_query") if k in a and k in b)


def inference_rows(eager_compact, eager_fixed, compiled_fixed, inputs: dict, batches, frames: int, warmup: int,
                   device, precision: str) -> list[dict]:
    """The three inference variants at every batch size (same weights), with output differences."""
    rows = []
    for b in batches:
        ref = None
        for name, model in (("eager compact", eager_compact), ("eager fixed", eager_fixed),
                            ("compiled fixed", compiled_fixed)):
            r = time_inference(model, inputs, b, frames, warmup, device, precision)
            out = r.pop("outputs")
            if name == "eager fixed":
                r["same_points_as_compact"] = same_points(out, ref)
            if name == "eager compact":
                ref = out
            else:
                r["max_diff_vs_compact"] = max_difference(out, ref)
            if name == "eager fixed":
                fixed_out = out
            if name == "compiled fixed":
                r["max_diff_vs_eager_fixed"] = max_difference(out, fixed_out)
            rows.append({"variant": name, **r})
    return rows


def train_step(model, loss_fn, optimizer, batch: dict, points: str, generator, device, precision: str) -> float:
    with autocast(device, precision):
        out = model(batch, points=points, noise=NOISE, generator=generator)
    total, _ = loss_fn(out, batch)
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    optimizer.step()
    return float(total.detach())


def time_training(model, loss_fn, optimizer, batches: list[dict], points: str, warmup: int, steps: int, device,
                  precision: str) -> dict:
    generator = torch.Generator().manual_seed(0)
    model.train()
    sync(device)
    start = time.perf_counter()
    train_step(model, loss_fn, optimizer, batches[0], points, generator, device, precision)
    sync(device)
    first = time.perf_counter() - start
    for i in range(max(0, warmup - 1)):
        train_step(model, loss_fn, optimizer, batches[(1 + i) % len(batches)], points, generator, device, precision)
    reset_peak(device)
    sync(device)
    start = time.perf_counter()
    for i in range(steps):
        train_step(model, loss_fn, optimizer, batches[(warmup + i) % len(batches)], points, generator, device,
                   precision)
    sync(device)
    seconds = (time.perf_counter() - start) / steps
    n = len(batches[0]["img"])
    return {"points": points, "batch": n, "ms_per_step": seconds * 1e3, "samples_per_s": n / seconds,
            "first_step_s": first, "peak_gib": peak_gib(device)}


def training_rows(build, mano, loss_weights, cls_dist: float, batches: list[dict], warmup: int, steps: int, device,
                  precision: str, compile_mode: str | None = None, backend: str = "inductor") -> list[dict]:
    """Eager and compiled training steps for both query-point paths; ``build()`` returns a fresh model (same
    seed), so every variant starts from the same weights and optimizer state. ``cls_dist``: the model settings'
    ``cls_dist`` (the loss's, as the trainer passes it)."""
    rows = []
    for compiled in (False, True):
        for points in ("gt", "field"):
            torch.manual_seed(0)
            model = build().to(device)
            optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4,
                                          weight_decay=0.01)
            loss_fn = HOISDFLoss(loss_weights, mano, model.scale, model.clamp, cls_dist)
            options = {"mode": compile_mode} if backend == "inductor" else {"backend": backend}
            runner = torch.compile(model, dynamic=False, **options) if compiled else model
            r = time_training(runner, loss_fn, optimizer, batches, points, warmup, steps, device, precision)
            rows.append({"variant": "compiled" if compiled else "eager", "fixed_shape": model.fixed_shape, **r})
            del model, optimizer, runner
            if device.type == "cuda":
                torch.cuda.empty_cache()
    return rows


def print_rows(inference: list[dict], training: list[dict]) -> None:
    def f(v, spec):
        return format(v, spec) if v is not None else format("-", f">{spec.split('.')[0]}")

    if inference:
        print(f"{'variant':>15} {'batch':>5} {'frames/s':>9} {'ms/frame':>9} {'first call s':>12} "
              f"{'peak GiB':>9} {'max diff':>9}")
        for r in inference:
            diff = r.get("max_diff_vs_eager_fixed", r.get("max_diff_vs_compact"))
            print(f"{r['variant']:>15} {r['batch']:>5} {r['frames_per_s']:>9.2f} {r['ms_per_frame']:>9.1f} "
                  f"{r['first_call_s']:>12.1f} {f(r['peak_gib'], '9.2f')} {f(diff, '9.1e')}"
                  + ("" if "same_points_as_compact" not in r else
                     f"  same points as compact: {r['same_points_as_compact']}"))
    if training:
        print(f"\n{'variant':>9} {'points':>6} {'batch':>5} {'ms/step':>9} {'samples/s':>10} {'first step s':>12} "
              f"{'peak GiB':>9}")
        for r in training:
            print(f"{r['variant']:>9} {r['points']:>6} {r['batch']:>5} {r['ms_per_step']:>9.0f} "
                  f"{r['samples_per_s']:>10.2f} {r['first_step_s']:>12.1f} {f(r['peak_gib'], '9.2f')}")
