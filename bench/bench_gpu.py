"""The GPU rows of the benchmarks in one short run: eager vs compiled, training and inference, full-size model.

Two steps, because the GPU machine has torch but not the data packages (webdataset, zarr, libigl, pyrender):

1. here, on any machine with the project installed (about a minute on 2 CPU cores)::

       python -m bench.bench_gpu prepare --out bench/gpu_inputs

   builds a toy DexYCB store (512 px crops), draws 3 batches of 22 with the full-size model's settings, applies
   the training augmentation (2 training batches) and the test-time crop (1 batch of test inputs), and saves
   them (images as uint8) with the model and loss settings and the toy MANO files: about 20 MB (``--config`` and
   trailing ``section.key=value`` overrides choose another model: the test suite's smoke run uses a tiny one);

2. on the GPU machine, with only torch, numpy and scipy (``run`` imports no data code)::

       python -m bench.bench_gpu run --inputs bench/gpu_inputs --json OUT/gpu.json

   times (same weights everywhere, bf16 autocast, geometry fp32): inference frames/s at batch 1 and 22 for
   the compact sampling path eager, the fixed-shape path eager, and the fixed-shape model compiled with
   ``fullgraph=True`` in ``reduce-overhead`` mode (CUDA graphs), with compile times and output differences;
   then training steps at batch 22 (samples/s, peak memory), eager and compiled, "gt" and "field" points.
   The JSON is rewritten after each section, so a run cut short keeps what it measured.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path
from types import SimpleNamespace

import torch

BATCH = 22
PAPER_FPS = 30.7  # HOISDF paper, TITAN RTX


def _pack(batch: dict) -> dict:
    """Tensors of a batch, with the image as uint8 (0..255) to keep the file small."""
    out = {k: v for k, v in batch.items() if torch.is_tensor(v)}
    out["img"] = (out["img"].clamp(0, 1) * 255).round().to(torch.uint8)
    return out


def _unpack(batch: dict, device: torch.device) -> dict:
    out = {k: v.to(device) for k, v in batch.items()}
    out["img"] = out["img"].float() / 255.0
    return out


def prepare(out: Path, config_name: str | None, store: Path | None = None, mano: Path | None = None,
            batch: int = BATCH, overrides: tuple[str, ...] = ()) -> None:
    from bench.common import store_and_mano, test_inputs
    from hoisdf.config import load_train_config, sdf_rows
    from hoisdf.data import StoreSpec, build_dataset
    from hoisdf.data.augment import augment_batch

    work = Path(tempfile.mkdtemp(prefix="bench_gpu_"))
    try:
        args = argparse.Namespace(store=store, mano=mano)
        store, mano_dir = store_and_mano(args, work, records=3 * batch)
        config = load_train_config(config_name, [*overrides, f"train.batch_size={batch}"])
        m, t = config.model, config.train
        data = build_dataset([StoreSpec(store)], batch, 3 * batch, t.seed, *sdf_rows(config), t.near,
                             t.shuffle_buffer, training=True)
        batches = [b for _, b in zip(range(3), data)]
        generator = torch.Generator().manual_seed(0)
        train = [_pack(augment_batch(b, config.augment, generator, train=True)) for b in batches[:2]]
        out.mkdir(parents=True, exist_ok=True)
        torch.save({"model": asdict(m), "loss": asdict(config.loss), "train_batches": train,
                    "test_inputs": _pack(test_inputs(batches[2], config, torch.device("cpu")))}, out / "inputs.pt")
        for name in ("MANO_RIGHT.pkl",):
            shutil.copy(Path(mano_dir) / name, out / name)
        print(f"wrote {out}/inputs.pt and the toy MANO ({(out / 'inputs.pt').stat().st_size / 2**20:.1f} MB)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


def run(inputs: Path, json_out: Path | None, frames: int, warmup: int, steps: int, precision: str,
        skip: list[str], backend: str = "inductor") -> None:
    from bench.compile_bench import (
        compile_inference,
        inference_rows,
        print_rows,
        training_rows,
    )
    from hoidata.hand import load_mano
    from hoisdf.model.build import build_model
    from hoisdf.config import LossWeights

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    data = torch.load(inputs / "inputs.pt", weights_only=True)
    mano = load_mano(inputs, side="right")
    settings = dict(data["model"], weights="", token_hidden=tuple(data["model"]["token_hidden"]))
    result = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "torch": torch.__version__, "precision": precision, "backend": backend, "paper_fps": PAPER_FPS,
              "model": settings}

    def save():
        if json_out:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(result, indent=2))

    def build(fixed: bool):
        torch.manual_seed(0)
        # build_model reads the settings by attribute: the saved ModelSettings fields, without importing the config
        return build_model(SimpleNamespace(**{**settings, "fixed_shape": fixed}), mano)

    torch.backends.cudnn.benchmark = True
    if "infer" not in skip:
        compact, fixed = build(False).to(device).eval(), build(True).to(device).eval()
        test = _unpack(data["test_inputs"], device)
        result["infer"] = inference_rows(compact, fixed, compile_inference(fixed, device, None, backend), test,
                                         sorted({1, len(test["img"])}), frames, warmup, device, precision)
        print_rows(result["infer"], [])
        save()
        del compact, fixed, test
    if "train" not in skip:
        batches = [_unpack(b, device) for b in data["train_batches"]]
        result["train"] = training_rows(lambda: build(True), mano, LossWeights(**data["loss"]), settings["cls_dist"],
                                        batches, warmup, steps, device, precision, backend=backend)
        print_rows([], result["train"])
        save()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    prep = sub.add_parser("prepare", help="build the inputs file (needs the data packages)")
    prep.add_argument("--out", type=Path, default=Path("bench/gpu_inputs"))
    prep.add_argument("--config", default=None, help="pipeline TOML of the model (default: the full-size model)")
    prep.add_argument("--store", type=Path, default=None, help="an existing store (default: a toy store in a temp folder)")
    prep.add_argument("--mano", type=Path, default=None, help="MANO folder (default: the procedural toy hand)")
    prep.add_argument("--batch", type=int, default=BATCH, help="batch of the saved batches (the larger inference batch)")
    prep.add_argument("overrides", nargs="*", metavar="section.key=value", help="model settings, e.g. model.depth=18")
    go = sub.add_parser("run", help="time eager vs compiled (needs only torch, numpy, scipy)")
    go.add_argument("--inputs", type=Path, default=Path("bench/gpu_inputs"))
    go.add_argument("--json", type=Path, default=None)
    go.add_argument("--frames", type=int, default=220, help="timed inference frames per batch size")
    go.add_argument("--warmup", type=int, default=3, help="untimed calls first (CUDA graphs record on the 2nd-3rd)")
    go.add_argument("--steps", type=int, default=10, help="timed training steps per variant")
    go.add_argument("--precision", choices=("fp32", "bf16"), default="bf16")
    go.add_argument("--skip", nargs="*", default=[], choices=("infer", "train"))
    go.add_argument("--backend", default="inductor", help="torch.compile backend (eager: a quick check of the script)")
    args = p.parse_args(argv)
    if args.cmd == "prepare":
        prepare(args.out, args.config, args.store, args.mano, args.batch, args.overrides)
    else:
        run(args.inputs, args.json, args.frames, args.warmup, args.steps, args.precision, args.skip, args.backend)
    return 0


if __name__ == "__main__":
    sys.exit(main())
