"""``python -m hoisdf.import_upstream SNAPSHOT --setting dexycb|dexycb_full|ho3d|ho3d_render --mano DIR --out RUN``

Turns one of the authors' released checkpoints (amathislab/HOISDF ``ckpts/<setting>/snapshot_*.pth.tar``) into a
run folder of this project: ``RUN/checkpoints/last.pt`` (the converted weights and the resolved settings that
compute upstream's forward: ``model.pixel_convention="upstream"``, ``sheared_grid``, ``normalize_input=false``,
``density_sign="code"``, ``object_rotation="axis_angle"``, the setting's decoder and pose regressor) and
``RUN/config.json`` (the same settings, the snapshot's path, sha256 and epoch). Evaluate it with
``python -m hoisdf.evaluate --ckpt RUN ...`` or fine-tune from it with ``python -m hoisdf.train --init RUN ...``.

The snapshot is read with ``torch.load(weights_only=True)`` on the CPU: tensors, numbers, strings and plain
containers only, no code runs. The MANO buffers inside it are compared with ``--mano`` and never copied.
See docs/released-weights.md for the key mapping.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import torch

from hoidata.atomic import write_atomic
from hoidata.cli_types import ArgumentParser
from hoidata.errors import DataError, run_cli
from hoisdf.training import upstream as U
from hoisdf.training.checkpoint import CHECKPOINTS, LAST, load_weights, save_checkpoint


def released_config(setting: str, extra: list[str] = ()):
    """TrainConfig of ``pipelines/<setting>.toml`` with the model switches that reproduce upstream's forward."""
    from hoisdf.config import load_train_config

    values = {**U.RELEASED_MODEL, **U.SETTINGS[setting]}
    overrides = [f"model.{k}={json.dumps(v)}" for k, v in values.items()]
    return load_train_config(setting, overrides + list(extra))


def import_snapshot(snapshot: Path, setting: str, mano_dir: Path, out: Path) -> dict:
    """Convert, check (MANO buffers; a strict load into the model) and write the run folder; returns its
    provenance dict. Nothing is written unless every check passes, and an existing checkpoint is never replaced."""
    from hoidata.hand import load_mano
    from hoisdf.model import build_model

    if setting not in U.SETTINGS:
        raise DataError(setting, "--setting", f"must be one of {sorted(U.SETTINGS)}")
    target = out / CHECKPOINTS / LAST
    if target.exists():
        raise DataError(target, None, "the run folder already holds a checkpoint: give another --out")
    payload, sha = U.read_snapshot(snapshot)
    network = {k[len("module."):] if k.startswith("module.") else k: v for k, v in payload["network"].items()}
    config = released_config(setting)
    load_mano(mano_dir, side="right")  # a readable MANO folder, as evaluate and train will need it
    with torch.device("meta"):  # names and shapes only: no memory, no random init
        model = build_model(config.model, None)
    U.check_mano(network, mano_dir, snapshot)
    state = U.convert_network(payload["network"], model.state_dict(), snapshot, ik=setting == "ho3d_render",
                              raw_6d=config.model.rot6d == "raw")  # the recipe's pose head: no identity shift
    with warnings.catch_warnings():  # "copying into a meta parameter is a no-op": only the check is wanted
        warnings.simplefilter("ignore")
        load_weights(model, state, snapshot)  # the model's own strict check of names and shapes
    epoch = payload.get("epoch")
    info = {"snapshot": str(Path(snapshot).resolve()), "sha256": sha, "setting": setting,
            "epoch": epoch if isinstance(epoch, int) else None, "mapped": len(state),
            "dropped": sorted(k for k in network if U.is_dropped(k))}
    save_checkpoint(target, {"model": state, "config": config.as_dict(), "upstream": info})
    write_atomic(out / "config.json", json.dumps({"config": config.as_dict(), "upstream": info}, indent=2).encode())
    return info


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="python -m hoisdf.import_upstream", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("snapshot", type=Path, help="the authors' snapshot_*.pth.tar")
    p.add_argument("--setting", required=True, choices=sorted(U.SETTINGS),
                   help="upstream's cfg.setting it was trained with")
    p.add_argument("--mano", required=True, type=Path, help="folder with MANO_RIGHT.pkl (checked against the snapshot)")
    p.add_argument("--out", required=True, type=Path, help="run folder to write")
    p.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def work() -> int:
        info = import_snapshot(args.snapshot, args.setting, args.mano, args.out)
        print(f"imported {args.snapshot} ({info['setting']}, epoch {info['epoch']}, sha256 {info['sha256'][:12]}...): "
              f"{info['mapped']} weights, {len(info['dropped'])} upstream keys dropped; run folder {args.out}")
        return 0
    return run_cli("", work, args.debug)


if __name__ == "__main__":
    sys.exit(main())
