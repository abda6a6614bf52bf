"""N training steps of the upstream recipe on a GPU: samples/s, peak memory, and the first steps' losses beside the
same steps on the CPU, in one short run.

Two steps, as ``bench_gpu.py`` (the GPU machine has torch, numpy and scipy but not the data packages):

1. here, on any machine with the project installed::

       python -m bench.bench_recipe_gpu prepare --config dexycb --out bench/recipe_inputs

   resolves the pipeline's training settings (``dexycb``: ``train.recipe = "upstream"``, fp32, the full-size model),
   reads ``--batches`` batches of ``train.batch_size`` (22) from a toy DexYCB store (or ``--store``) through the
   trainer's loader (under ``augment.upstream``, the recipe's default, the store must be built with
   ``record.upstream_region = ["train"]``, as the ``dexycb`` preset builds it; ``augment.upstream=false`` takes any
   store), applies the training augmentation with a seeded generator, and saves them (images as uint8)
   with the resolved settings and the toy MANO: about 10 MB per batch of 22;

2. on the GPU machine (device tool: carry ``["bench/recipe_inputs"]``)::

       python -m bench.bench_recipe_gpu run --inputs bench/recipe_inputs --steps 30 --json $OUT/recipe_gpu.json

   builds the model (seed 0) with the saved settings and runs the recipe's step (its optimizer and learning rate of
   epoch 0, its precision: fp32 under ``upstream``, bf16 autocast when ``train.bf16``) on the saved batches:

   - **compare**: ``--compare`` steps with the ground-truth-guided points of the first epochs and the first noise
     half-width, dropout off (a dropout mask comes from each device's own generator), on the CPU and on the GPU
     from the same weights: the total loss of every step side by side and their relative difference;
   - **timing**: with the recipe's dropout, ``--warmup`` untimed steps then ``--steps`` timed ones, for the "gt"
     (epochs 0-39) and the "field" (60 % of the steps from epoch 40) points: ms/step, samples/s, peak GPU memory,
     and the epoch and 70-epoch times for ``--records`` training records (DexYCB's 29,656 by default) at that rate.

   Without CUDA it says so on one line and runs everything on the CPU (the comparison then has one column); the
   test suite runs it so at its smallest size. The JSON is rewritten after each section.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from types import SimpleNamespace

import torch

DEXYCB_TRAIN = 29656  # records of the dexycb training split (pipelines/dexycb.toml expected_frames)


def prepare(out: Path, config_name: str, overrides: list[str], store: Path | None, mano: Path | None,
            batches: int) -> None:
    from bench.common import store_and_mano
    from hoisdf.config import load_train_config, sdf_rows
    from hoisdf.data import StoreSpec, build_dataset
    from hoisdf.data.augment import augment_batch

    config = load_train_config(config_name, overrides)
    m, t = config.model, config.train
    work = Path(tempfile.mkdtemp(prefix="bench_recipe_"))
    try:
        store, mano_dir = store_and_mano(argparse.Namespace(store=store, mano=mano), work, records=batches * t.batch_size)
        data = build_dataset([StoreSpec(store)], t.batch_size, batches * t.batch_size, t.seed, *sdf_rows(config),
                             t.near, training=True, progress=False, upstream=config.augment.upstream)
        generator = torch.Generator().manual_seed(t.seed)
        saved = []
        for _, batch in zip(range(batches), data):
            batch = augment_batch(batch, config.augment, generator, train=True)
            packed = {k: v for k, v in batch.items() if torch.is_tensor(v)}
            packed["img"] = (packed["img"].clamp(0, 1) * 255).round().to(torch.uint8)
            saved.append(packed)
        out.mkdir(parents=True, exist_ok=True)
        torch.save({"model": asdict(m), "train": asdict(t), "loss": asdict(config.loss), "batches": saved,
                    "config": config_name, "overrides": list(overrides)}, out / "inputs.pt")
        shutil.copy(Path(mano_dir) / "MANO_RIGHT.pkl", out / "MANO_RIGHT.pkl")
        size = (out / "inputs.pt").stat().st_size / 2**20
        print(f"wrote {out}/inputs.pt ({len(saved)} batches of {t.batch_size}, recipe {t.recipe}, {size:.1f} MB)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _unpack(batch: dict, device: torch.device) -> dict:
    out = {k: v.to(device) for k, v in batch.items()}
    out["img"] = out["img"].float() / 255.0
    return out


class Steps:
    """The recipe's training step on one device, from the weights of seed 0 (as ``Trainer.train_step`` after the
    augmentation: forward, loss, zero_grad, backward, optimizer step)."""

    def __init__(self, data: dict, mano, device: torch.device, dropout: bool):
        from hoisdf.config import LossWeights
        from hoisdf.model.build import build_model
        from hoisdf.training.losses import HOISDFLoss

        settings = dict(data["model"], weights="", token_hidden=tuple(data["model"]["token_hidden"]))
        if not dropout:
            settings.update(dropout=0.0, sdf_dropout=0.0)
        t = data["train"]
        torch.manual_seed(0)
        # build_model reads the settings by attribute: the saved ModelSettings fields, without importing the config
        self.model = build_model(SimpleNamespace(**settings), mano).to(device).train()
        params = [p for p in self.model.parameters() if p.requires_grad]
        self.optimizer = {"adamw": torch.optim.AdamW, "adam": torch.optim.Adam}[t["optimizer"]](
            params, lr=t["lr"], weight_decay=t["weight_decay"])
        self.loss = HOISDFLoss(LossWeights(**data["loss"]), mano, settings["sdf_scale"], settings["sdf_clamp"],
                               settings["cls_dist"])
        self.autocast = device.type == "cuda" and t["bf16"]
        self.noise = t["noise_dists"][0]
        self.generator = torch.Generator().manual_seed(t["seed"] * 1000)
        self.device = device

    def __call__(self, batch: dict, points: str) -> float:
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.autocast):
            out = self.model(batch, points=points, noise=self.noise, generator=self.generator)
        total, _ = self.loss(out, batch)
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizer.step()
        return float(total.detach())


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def compare(data: dict, mano, devices: list[torch.device], steps: int) -> list[dict]:
    """Total loss of the first ``steps`` steps ("gt" points, dropout off) on each device, same weights and batches."""
    losses = {}
    for device in devices:
        run = Steps(data, mano, device, dropout=False)
        batches = [_unpack(b, device) for b in data["batches"]]
        losses[device.type] = [run(batches[i % len(batches)], "gt") for i in range(steps)]
    rows = []
    for i in range(steps):
        cpu, gpu = losses["cpu"][i], losses.get("cuda", [None] * steps)[i]
        rows.append({"step": i + 1, "cpu": cpu, "cuda": gpu,
                     "rel_diff": None if gpu is None else abs(gpu - cpu) / max(abs(cpu), 1e-12)})
    return rows


def timing(data: dict, mano, device: torch.device, points: str, warmup: int, steps: int, records: int,
           epochs: int) -> dict:
    run = Steps(data, mano, device, dropout=True)
    batches = [_unpack(b, device) for b in data["batches"]]
    for i in range(warmup):
        run(batches[i % len(batches)], points)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    _sync(device)
    start = time.perf_counter()
    for i in range(steps):
        run(batches[(warmup + i) % len(batches)], points)
    _sync(device)
    seconds = (time.perf_counter() - start) / steps
    rate = len(batches[0]["img"]) / seconds
    return {"device": device.type, "points": points, "batch": len(batches[0]["img"]), "ms_per_step": seconds * 1e3,
            "samples_per_s": rate, "epoch_h": records / rate / 3600, "epochs": epochs,
            "peak_gib": torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None}


def projected_hours(rows: list[dict], epochs: int, point_sampling_epoch: int, field_prob: float) -> float | None:
    """Wall time of ``epochs`` epochs from the "gt" and "field" rates: "gt" before ``point_sampling_epoch``, then
    ``field_prob`` of the steps "field" (the loader and validation not counted)."""
    rate = {r["points"]: r["epoch_h"] for r in rows}
    if set(rate) != {"gt", "field"}:
        return None
    late = max(epochs - point_sampling_epoch, 0)
    return (epochs - late) * rate["gt"] + late * (field_prob * rate["field"] + (1 - field_prob) * rate["gt"])


def run(inputs: Path, json_out: Path | None, steps: int, warmup: int, compare_steps: int, records: int) -> None:
    from hoidata.hand import load_mano

    data = torch.load(inputs / "inputs.pt", weights_only=True)
    mano = load_mano(inputs, side="right")
    cuda = torch.cuda.is_available()
    device = torch.device("cuda" if cuda else "cpu")
    if not cuda:
        print("no CUDA device: the GPU columns stay empty, the timing runs on the CPU")
    t = data["train"]
    result = {"device": torch.cuda.get_device_name(device) if cuda else "cpu", "torch": torch.__version__,
              "config": data["config"], "overrides": data["overrides"], "recipe": t["recipe"],
              "precision": "bf16 autocast" if cuda and t["bf16"] else "fp32", "records": records}

    def save():
        if json_out:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(result, indent=2))

    torch.backends.cudnn.benchmark = True  # as upstream's main/train.py:62
    result["compare"] = compare(data, mano, [torch.device("cpu")] + ([device] if cuda else []), compare_steps)
    print(f"recipe {t['recipe']}, {result['precision']}, batch {len(data['batches'][0]['img'])}, {result['device']}")
    print(f"\n{'step':>4} {'loss cpu':>12} {'loss cuda':>12} {'rel diff':>9}   (gt points, dropout off)")
    for r in result["compare"]:
        gpu = "-" if r["cuda"] is None else f"{r['cuda']:.6g}"
        diff = "-" if r["rel_diff"] is None else f"{r['rel_diff']:.1e}"
        print(f"{r['step']:>4} {r['cpu']:>12.6g} {gpu:>12} {diff:>9}")
    save()
    result["timing"] = [timing(data, mano, device, points, warmup, steps, records, t["epochs"])
                        for points in ("gt", "field")]
    result["projected_h"] = projected_hours(result["timing"], t["epochs"], t["point_sampling_epoch"], t["field_prob"])
    print(f"\n{'device':>6} {'points':>6} {'batch':>5} {'ms/step':>9} {'samples/s':>10} {'peak GiB':>9} {'h/epoch':>8}")
    for r in result["timing"]:
        peak = "-" if r["peak_gib"] is None else f"{r['peak_gib']:.2f}"
        print(f"{r['device']:>6} {r['points']:>6} {r['batch']:>5} {r['ms_per_step']:>9.0f} {r['samples_per_s']:>10.2f} "
              f"{peak:>9} {r['epoch_h']:>8.2f}")
    print(f"projected {t['epochs']} epochs of {records} records on {result['device']}: {result['projected_h']:.1f} h "
          f"(steps only: no loader, no validation)")
    save()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    prep = sub.add_parser("prepare", help="resolve the recipe and save augmented batches (needs the data packages)")
    prep.add_argument("--out", type=Path, default=Path("bench/recipe_inputs"))
    prep.add_argument("--config", default="dexycb", help="pipeline whose training settings run (default dexycb)")
    prep.add_argument("--store", type=Path, default=None, help="an existing store (default: a toy store)")
    prep.add_argument("--mano", type=Path, default=None, help="MANO folder (default: the procedural toy hand)")
    prep.add_argument("--batches", type=int, default=3, help="distinct batches saved (the steps cycle through them)")
    prep.add_argument("overrides", nargs="*", metavar="section.key=value", help="e.g. train.batch_size=2")
    go = sub.add_parser("run", help="the steps (needs only torch, numpy, scipy)")
    go.add_argument("--inputs", type=Path, default=Path("bench/recipe_inputs"))
    go.add_argument("--json", type=Path, default=None)
    go.add_argument("--steps", type=int, default=30, help="timed steps per points mode")
    go.add_argument("--warmup", type=int, default=3, help="untimed steps first")
    go.add_argument("--compare", type=int, default=5, help="steps compared between the CPU and the GPU")
    go.add_argument("--records", type=int, default=DEXYCB_TRAIN, help="training records per epoch (projection)")
    args = p.parse_args(argv)
    if args.cmd == "prepare":
        prepare(args.out, args.config, args.overrides, args.store, args.mano, args.batches)
    else:
        run(args.inputs, args.json, args.steps, args.warmup, args.compare, args.records)
    return 0


if __name__ == "__main__":
    sys.exit(main())
