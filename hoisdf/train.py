"""``python -m hoisdf.train --shards STORE[:WEIGHT] ... [--mano DIR] [--config NAME] [section.key=value ...]``

Trains HOISDF on one or more stores (weights set the mixing ratio, e.g. ``shards/dexycb:1.0
shards/ho3d_render:0.6``); a store is a folder or an explicit ``http(s)://``, ``s3://`` or ``gs://`` URL; a folder of
stores (``--shards shards/``) trains on its train stores and validates on the val or test stores beside them. The
preset (``--config``) and the MANO folder (``--mano``) default to what the stores were built with.
Multi-GPU / multi-process: ``torchrun --nproc_per_node N -m hoisdf.train ...``
(NCCL on GPUs, gloo on CPUs). ``--resume`` continues ``--out``'s last checkpoint exactly; ``--init RUN`` fine-tunes from
another run's weights (e.g. an imported released checkpoint) with its model settings.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import torch

from hoidata.atomic import write_atomic
from hoidata.cli_types import ArgumentParser, local_path
from hoidata.errors import DataError, redact_urls, run_cli
from hoidata.provenance import MANO_VARIABLE, git_commit
from hoidata.sections import pipeline_names
from hoidata.store import resolve_store
from hoidata.store.paths import refuse_repeated_stores
from hoidata.store.remote import url_authority
from hoisdf.config import TrainConfig, describe_config, overridden_config, resolve_train_config
from hoisdf.data import StoreSpec
from hoisdf.data.store_choice import (
    choose_stores,
    folder_facts,
    folder_lines,
    folder_of_stores,
    store_facts,
    stores_preset,
    training_mano,
)
from hoisdf.training.checkpoint import CHECKPOINTS, LAST, find_checkpoint, load_checkpoint, load_weights
from hoisdf.training.trainer import CURVE, KEYS, Trainer, unwrap


def parse_store(text: str) -> StoreSpec:
    """'store' or 'store:weight' (a finite weight > 0) -> StoreSpec. A store is a local folder, or an explicit
    http(s)://, s3:// or gs:// URL (hoidata.store.resolve_store; a folder name like 'pipe:...' is just a folder);
    in an http(s) URL a ':' after the host is the port, so a weight follows it (``http://host:8000/store:0.6``,
    ``http://host:8000:0.6``); a bucket name has no ':' (``s3://bucket:2`` is the bucket's root, weight 2)."""
    head = url_authority(text) or ""
    path, sep, weight = text[len(head):].rpartition(":")
    if sep and (path or head) and not weight.startswith(("/", "\\")):
        try:
            value = float(weight)
        except ValueError:
            pass
        else:
            if not (math.isfinite(value) and value > 0):
                raise DataError(text, "weight", f"must be a finite number > 0, got {weight}")
            return StoreSpec(resolve_store(head + path), value)
    return StoreSpec(resolve_store(text), 1.0)


_OVERRIDE = re.compile(r"^[A-Za-z_]+\.[A-Za-z_][A-Za-z0-9_]*=")


def _split_overrides(args) -> None:
    """``--shards a b train.x=1``: items that look like overrides and are no folder are overrides, so overrides
    work after --shards / --val-shards too."""
    for name in ("shards", "val_shards"):
        items = getattr(args, name)
        moved = [i for i in items if _OVERRIDE.match(i) and not Path(i).exists()]
        setattr(args, name, [i for i in items if i not in moved])
        args.overrides = [*moved, *args.overrides]
    if not args.shards:
        raise DataError(None, "--shards", "give at least one training store")


def clean_dead_run(run_dir: Path) -> list[str]:
    """Remove what an earlier run in ``run_dir`` left without ever writing a checkpoint (its logs, config and
    TensorBoard files describe training that cannot be resumed); returns the names removed."""
    removed = []
    logs = [run_dir / CURVE, run_dir / "config.json", run_dir / "tb", *sorted(run_dir.glob(KEYS.format(rank="*")))]
    for path in logs:
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
        else:
            continue
        removed.append(path.name)
    return removed


def distributed_setup(device_arg: str | None) -> tuple[int, int, torch.device]:
    """(rank, world size, device); initialises the process group under torchrun (WORLD_SIZE > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    if device_arg:
        device = torch.device(device_arg)
    else:
        device = torch.device(f"cuda:{local}" if torch.cuda.is_available() else "cpu")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world > 1:
        torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return rank, world, device


def write_run_info(run_dir: Path, config: TrainConfig, stores, val_stores, world: int, argv: list[str]) -> None:
    from hoisdf import __version__
    info = {"config": config.as_dict(), "stores": [[str(s.path), s.weight] for s in stores],
            "val_stores": [str(s.path) for s in val_stores], "git_commit": git_commit(), "version": __version__,
            "world_size": world, "argv": [redact_urls(a) for a in argv]}  # a store URL's password stays out
    write_atomic(run_dir / "config.json", json.dumps(info, indent=2).encode())


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="python -m hoisdf.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shards", nargs="+", required=True, metavar="STORE[:WEIGHT]",
                   help="training stores: folders or http(s)://, s3://, gs:// URLs; or one folder of stores (its train "
                        "stores train, the val or test stores beside them validate)")
    p.add_argument("--val-shards", nargs="*", default=[], metavar="STORE", help="validation stores (folders or URLs)")
    p.add_argument("--mano", default=None, type=Path, help="folder with MANO_RIGHT.pkl (default: the stores' build "
                                                           f"record, while its digest holds, else ${MANO_VARIABLE})")
    p.add_argument("--config", default=None, help=f"pipelines/<name>.toml ({', '.join(pipeline_names())}) or a path "
                                                  "(default: the preset the stores were built for)")
    p.add_argument("--out", type=local_path, default=None, help="run folder (default runs/<config>)")
    p.add_argument("--resume", action="store_true", help="continue the run folder's last checkpoint")
    p.add_argument("--init", type=Path, default=None, metavar="RUN_OR_CKPT",
                   help="fine-tune: start from these weights and their [model] settings (e.g. an imported released "
                        "checkpoint, python -m hoisdf.import_upstream); optimizer and progress start fresh")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--dry-run", action="store_true", help="print the stores, MANO folder and settings, then stop")
    p.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    p.add_argument("overrides", nargs="*", metavar="section.key=value", help="e.g. train.batch_size=8 model.depth=18")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_intermixed_args(argv)  # overrides before and after other options
    return run_cli("", lambda: run(args, argv), args.debug)


def choose_inputs(args) -> tuple[list[StoreSpec], list[StoreSpec], list, list, list[str]]:
    """(train stores, validation stores, what the train stores' indexes say, and every used store's, lines to print)
    from ``--shards`` (stores, or one folder of stores: :mod:`hoisdf.data.store_choice`) and ``--val-shards``."""
    folders = [f for f in map(folder_of_stores, args.shards) if f is not None]
    if folders and len(args.shards) > 1:
        raise DataError(folders[0], "--shards", "a folder of stores: give it alone, or name its stores")
    if folders:
        choice = choose_stores(folders[0], folder_facts(folders[0]))
        stores = [StoreSpec(f.path, 1.0) for f in choice.train]
        val = [StoreSpec(resolve_store(s)) for s in args.val_shards] or [StoreSpec(f.path) for f in choice.validation]
        used = choice.train + ([] if args.val_shards else choice.validation)
        return stores, val, choice.train, used, folder_lines(folders[0], choice)
    stores = [parse_store(s) for s in args.shards]
    val = [StoreSpec(resolve_store(s)) for s in args.val_shards]
    refuse_repeated_stores([s.path for s in stores], "--shards", " (a weight, STORE:2, samples a store more often)")
    refuse_repeated_stores([s.path for s in val], "--val-shards")
    need = args.config is None or args.mano is None  # read the indexes only for what the stores must tell
    facts = [store_facts(s.path) for s in stores] if need else []
    return stores, val, facts, facts, []


def chosen_config(args, facts) -> tuple[str | None, str]:
    """(--config's value or the stores' preset, why), None for hoisdf/config.py's defaults."""
    if args.config is not None:
        return args.config, "--config"
    found = stores_preset(facts)
    if found is None:
        return None, "the stores record no preset (built before stores recorded one): hoisdf/config.py's defaults"
    return found[0], f"the stores' preset; {found[1]}"


def run(args, argv: list[str]) -> int:
    from hoidata.hand import load_mano

    _split_overrides(args)
    stores, val_stores, train_facts, facts, lines = choose_inputs(args)
    name, why = chosen_config(args, train_facts)
    run_dir = args.out or Path("runs") / Path(name or "default").stem
    checkpoint = find_checkpoint(run_dir) if args.resume else None
    payload = load_checkpoint(checkpoint) if args.resume else None
    sources = None
    if payload:  # the run's own config; overrides (e.g. a later train.max_steps) still apply
        config = overridden_config(payload["config"], args.overrides, checkpoint)
    else:
        if (run_dir / CHECKPOINTS / LAST).exists():
            raise DataError(run_dir, None, "the run folder already holds a checkpoint: pass --resume or another --out")
        config, sources = resolve_train_config(name, args.overrides)
    init = load_checkpoint(args.init) if args.init and not payload else None
    if init:  # the weights' own model settings (model.* overrides still apply); the rest from --config
        model_overrides = [o for o in args.overrides if o.startswith("model.")]
        config = replace(config, model=overridden_config(init["config"], model_overrides, args.init).model)
        sources = {k: v for k, v in (sources or {}).items() if not k.startswith("model.")}  # printed apart
    mano_dir = training_mano(args.mano, facts)
    if int(os.environ.get("RANK", "0")) == 0:
        label = name if name is None or name.endswith(".toml") else f"pipelines/{name}.toml"
        lines += [f"config: {label or 'hoisdf/config.py defaults'} ({why})",
                  f"mano: {mano_dir.folder} ({mano_dir.origin})"]
        if sources is not None:
            lines += describe_config(config, sources)
        else:
            lines.append(f"resumed: the run's own resolved settings ({run_dir}/config.json, recipe "
                         f"{config.train.recipe})")
        if init:
            lines.append(f"model settings: {args.init}'s own (--init), with the command line's model.* overrides")
        print(redact_urls("\n".join(lines)), flush=True)  # a store or MANO URL's secrets stay out
    if args.dry_run:
        return 0
    rank, world, device = distributed_setup(args.device)
    torch.manual_seed(config.train.seed + rank)
    run_dir.mkdir(parents=True, exist_ok=True)
    if not payload and rank == 0 and (removed := clean_dead_run(run_dir)):
        print(f"note: {run_dir} held an earlier run that never wrote a checkpoint; removed its {', '.join(removed)}")
    mano = load_mano(mano_dir.folder, side="right")
    trainer = Trainer(config, stores, mano, run_dir, device, val_stores, rank, world)
    rng = trainer.load(payload, checkpoint) if payload else None
    if init:
        load_weights(unwrap(trainer.model), init["model"], args.init)
    if rank == 0 and not payload:
        write_run_info(run_dir, config, stores, val_stores, world, argv)
    if rank == 0:
        p = trainer.progress
        print(f"training {config.model.depth}-layer HOISDF on {device} x{world}: epoch {p.epoch} step {p.step}, "
              f"{len(trainer.dataset)} batches/epoch, run folder {run_dir}", flush=True)
    progress = trainer.fit(rng, progress_bar=not args.no_progress)
    if rank == 0:
        print(f"done: epoch {progress.epoch}, {progress.global_step} steps; checkpoint {run_dir}/checkpoints/last.pt")
    if world > 1:
        torch.distributed.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
