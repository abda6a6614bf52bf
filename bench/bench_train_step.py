"""Training-step time of model variants side by side in one run: conv memory layout and token-MLP width.

Usage: python -m bench.bench_train_step [--config toy] [--store STORE] [--mano DIR] [--device cpu]
           [--batch-size 8] [--rounds 3] [--steps 4] [--variants nchw nhwc ...] [--json OUT]

Variants (everything else from ``--config``): ``nchw``: NCHW convolutions (``model.channels_last=false``)
with the paper's token MLP (1024-512-256), i.e. the model before these options existed; ``nhwc``: NHWC
convolutions; ``token``: NCHW with the config's own ``model.token_hidden``; ``nhwc+token``: both. Each variant gets its own
Trainer on the same loader batches (same seed, so the same initial weights up to layout) and runs both
query-point paths ("gt" and "field"). The variants are timed in turns, ``--rounds`` times over, each turn
``--steps`` steps after one untimed warm-up step; the table holds the median ms/step over the rounds, so
load from other jobs hits every variant alike. A second table times the backbone alone (forward + backward
of the ResNet-U-Net on the batch's images) in both layouts, the same way.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from bench.common import NOISE, resolve_device, store_and_mano, sync, test_inputs
from hoidata.hand import load_mano
from hoisdf.config import load_train_config
from hoisdf.data import StoreSpec
from hoisdf.training.trainer import Trainer

PAPER_TOKEN = "[1024, 512, 256]"


VARIANTS = ("nchw", "nhwc", "token", "nhwc+token")


def variants(config_token: list[int]) -> dict[str, list[str]]:
    return {"nchw": ["model.channels_last=false", f"model.token_hidden={PAPER_TOKEN}"],
            "nhwc": ["model.channels_last=true", f"model.token_hidden={PAPER_TOKEN}"],
            "token": ["model.channels_last=false", f"model.token_hidden={config_token}"],
            "nhwc+token": ["model.channels_last=true", f"model.token_hidden={config_token}"]}


def time_steps(trainer: Trainer, batches: list[dict], points: str, steps: int) -> float:
    """ms per step of ``steps`` training steps after one warm-up step."""
    trainer.train_step(batches[0], points, NOISE)
    sync(trainer.device)
    start = time.perf_counter()
    for i in range(steps):
        trainer.train_step(batches[(1 + i) % len(batches)], points, NOISE)
    sync(trainer.device)
    return (time.perf_counter() - start) / steps * 1e3


def time_backbone(backbone: torch.nn.Module, img: torch.Tensor, steps: int) -> float:
    """ms per forward + backward of the backbone alone, after one warm-up pass."""
    times = []
    for i in range(1 + steps):
        start = time.perf_counter()
        pyramid, maps = backbone(img)
        (sum(f.float().mean() for f in pyramid) + maps.float().mean()).backward()
        sync(img.device)
        times.append(time.perf_counter() - start)
    return sum(times[1:]) / steps * 1e3


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="toy")
    p.add_argument("--store", type=Path, default=None)
    p.add_argument("--mano", type=Path, default=None)
    p.add_argument("--device", default=None)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--steps", type=int, default=4)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS,
                   help="variants to time (nchw, the baseline, and nhwc, for the backbone table, always run)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    device = resolve_device(args.device)
    work = Path(tempfile.mkdtemp(prefix="bench_step_"))
    store, mano_dir = store_and_mano(args, work, records=4 * args.batch_size)
    mano = load_mano(mano_dir, side="right")
    common = ["train.workers=0", f"train.batch_size={args.batch_size}"]
    token = list(load_train_config(args.config, common).model.token_hidden)
    trainers = {}
    chosen = {"nchw", "nhwc", *args.variants}
    for name, extra in variants(token).items():
        if name not in chosen:
            continue
        torch.manual_seed(0)
        cfg = load_train_config(args.config, common + extra)
        trainers[name] = Trainer(cfg, [StoreSpec(store)], mano, work / name, device)
    loader = iter(trainers["nchw"].loader)
    batches = [next(loader) for _ in range(1 + args.steps)]
    times = {(n, pts): [] for n in trainers for pts in ("gt", "field")}
    times.update({(n, "backbone"): [] for n in ("nchw", "nhwc")})
    img = test_inputs(batches[0], trainers["nchw"].config, device)["img"]  # the network's input crop
    for r in range(args.rounds):
        for (name, points), values in times.items():
            if points == "backbone":
                values.append(time_backbone(trainers[name].model.backbone, img, args.steps))
            else:
                values.append(time_steps(trainers[name], batches, points, args.steps))
        print(f"round {r + 1}/{args.rounds} done", flush=True)
    rows = {f"{n}/{pts}": statistics.median(v) for (n, pts), v in times.items()}
    print(f"\n{args.config} config, batch {args.batch_size}, device {device}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads; median ms/step over {args.rounds} rounds of {args.steps} steps")
    print(f"{'variant':<12} {'gt ms':>8} {'field ms':>9} {'x gt':>6} {'x field':>8}")
    for name in trainers:
        gt, field = rows[f"{name}/gt"], rows[f"{name}/field"]
        print(f"{name:<12} {gt:8.0f} {field:9.0f} {rows['nchw/gt'] / gt:6.2f} {rows['nchw/field'] / field:8.2f}")
    print(f"\nbackbone alone (forward + backward, {tuple(img.shape)}): NCHW {rows['nchw/backbone']:.0f} ms, "
          f"NHWC {rows['nhwc/backbone']:.0f} ms, x{rows['nchw/backbone'] / rows['nhwc/backbone']:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"config": args.config, "device": str(device), "batch": args.batch_size,
                                         "token_hidden": token, "ms_per_step": rows,
                                         "all_rounds": {f"{n}/{p}": v for (n, p), v in times.items()}}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
