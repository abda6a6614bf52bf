"""Checkpoints: everything an exact ``--resume`` needs, written atomically, read with ``weights_only=True``.

A run folder (``python -m hoisdf.train --out RUN``) holds::

    RUN/config.json            resolved TrainConfig, stores, git commit, package version
    RUN/checkpoints/last.pt    the newest checkpoint (also epoch-NNN.pt at epoch ends)
    RUN/metrics.csv            one line per logging step and per validation (the training curve)
    RUN/tb/                    TensorBoard event files

A checkpoint is a dict: ``model`` (state dict; MANO is not in it), ``optimizer``, ``scheduler``, ``rng``
(torch CPU / CUDA and Python ``random`` states, the augmentation generator), ``progress`` (epoch, step in
the epoch, global step) and ``config`` (TrainConfig.as_dict()).
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import torch

from hoidata.errors import DataError

CHECKPOINTS = "checkpoints"
LAST = "last.pt"


def rng_state(generator: torch.Generator | None = None) -> dict:
    """Every random state the training loop draws from (torch CPU, CUDA, Python ``random``, the generator)."""
    state = {"torch": torch.get_rng_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    if generator is not None:
        state["generator"] = generator.get_state()
    return state


def set_rng_state(state: dict, generator: torch.Generator | None = None) -> None:
    torch.set_rng_state(state["torch"])
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    if generator is not None and "generator" in state:
        generator.set_state(state["generator"])


def save_checkpoint(path: Path, payload: dict) -> Path:
    """Write ``payload`` to ``path`` atomically (temporary file + rename): a crash never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def find_checkpoint(run_or_file: str | os.PathLike) -> Path:
    """A checkpoint file, or a run folder -> its ``checkpoints/last.pt``."""
    path = Path(run_or_file)
    if path.is_dir():
        path = path / CHECKPOINTS / LAST
    if not path.is_file():
        raise DataError(path, None, "checkpoint not found (give a run folder or a .pt file)")
    return path


def load_checkpoint(run_or_file: str | os.PathLike, map_location="cpu") -> dict:
    """Read a checkpoint with ``weights_only=True`` (no code in the file is run); errors name the file."""
    path = find_checkpoint(run_or_file)
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:
        raise DataError(path, None, f"cannot read checkpoint: {e}") from e
    for key in ("model", "config"):
        if key not in payload:
            raise DataError(path, key, "missing from the checkpoint")
    return payload


def load_model(run_or_file: str | os.PathLike, mano, device="cpu"):
    """(model in eval mode on ``device``, TrainConfig) from a run folder or checkpoint file."""
    from dataclasses import replace

    from hoisdf.config import config_from_dict
    from hoisdf.model import build_model

    payload = load_checkpoint(run_or_file)
    config = config_from_dict(payload["config"])
    model = build_model(replace(config.model, weights=""), mano)  # the state dict holds every weight
    model.load_state_dict(payload["model"])
    return model.to(device).eval(), config
