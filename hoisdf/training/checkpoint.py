"""Checkpoints: everything an exact ``--resume`` needs, written atomically, read with ``weights_only=True``.

A run folder (``python -m hoisdf.train --out RUN``) holds::

    RUN/config.json            resolved TrainConfig, stores, git commit, package version
    RUN/checkpoints/last.pt    the newest checkpoint (also epoch-NNN.pt at epoch ends)
    RUN/metrics.csv            one line per logging step and per validation (the training curve)
    RUN/keys-rank<R>.txt       with train.record_keys: the key of every record trained on, per rank
    RUN/tb/                    TensorBoard event files

A checkpoint is a dict: ``model`` (state dict; MANO is not in it), ``optimizer``, ``scheduler``, ``rng``
(torch CPU / CUDA and Python ``random`` states, the augmentation generator) of rank 0 and ``rng_ranks`` (the
same for every rank, in rank order: a DDP resume gives each rank its own), ``progress`` (epoch, step in
the epoch, global step), ``config`` (TrainConfig.as_dict()) and ``keys_bytes`` (per rank, the size its keys file had:
``--resume`` cuts it back to that).
"""

from __future__ import annotations

import os
import random
import shutil
from pathlib import Path

import torch

from hoidata.atomic import atomic_file
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


class _KeptErrors:
    """The file ``torch.save`` writes through, keeping the OSError of a failed write: torch's zip writer turns it
    into a ``RuntimeError`` that names neither the file nor the reason (a full disk, a file size limit)."""

    def __init__(self, file):
        self.file, self.error = file, None

    def _kept(self, call, *args):
        try:
            return call(*args)
        except OSError as err:
            self.error = self.error or err
            raise

    def write(self, data) -> int:
        return self._kept(self.file.write, data)

    def flush(self) -> None:
        self._kept(self.file.flush)


def save_checkpoint(path: Path, payload: dict) -> Path:
    """Write ``payload`` to ``path`` atomically (temporary file, synced, renamed): a crash or a full disk never
    leaves half a file, and a checkpoint already at ``path`` stays whole. A failed write is the OSError naming
    ``path`` and the system's reason (``No space left on device``, ``File too large``), not torch's RuntimeError."""
    with atomic_file(path) as f:
        sink = _KeptErrors(f)
        try:
            torch.save(payload, sink)
        except RuntimeError:
            if sink.error is None:
                raise
            raise sink.error from None  # named by atomic_file
    return Path(path)


def copy_checkpoint(source: Path, path: Path) -> Path:
    """The checkpoint file ``source`` copied to ``path`` atomically; a failed write names ``path``."""
    with open(source, "rb") as src, atomic_file(path) as dst:
        shutil.copyfileobj(src, dst, 1 << 20)
    return Path(path)


def _check_rng(state, path, name: str) -> None:
    """An RNG state dict as rng_state writes it, tried on scratch generators (a bad one is a DataError)."""
    if not isinstance(state, dict) or "torch" not in state or "python" not in state:
        raise DataError(path, name, "expected a dict with 'torch' and 'python' random states")
    try:
        torch.Generator().set_state(state["torch"])
        if "generator" in state:
            torch.Generator().set_state(state["generator"])
        version, internal, gauss = state["python"]
        random.Random().setstate((version, tuple(internal), gauss))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise DataError(path, name, f"not a valid random state ({type(exc).__name__}: {exc})") from None


def check_training_payload(payload: dict, path) -> None:
    """What --resume needs, checked before anything is restored: optimizer, progress and every rank's RNG."""
    for key in ("optimizer", "progress", "rng"):
        if key not in payload:
            raise DataError(path, key, "missing from the checkpoint (it cannot be resumed; evaluate still reads it)")
    opt, progress = payload["optimizer"], payload["progress"]
    if not isinstance(opt, dict) or not {"state", "param_groups"} <= set(opt):
        raise DataError(path, "optimizer", "expected an optimizer state dict ('state', 'param_groups')")
    if not isinstance(progress, dict) or set(progress) != {"epoch", "step", "global_step"} or not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in progress.values()):
        raise DataError(path, "progress", f"expected epoch, step and global_step >= 0, got {progress!r}")
    if progress["step"] > progress["global_step"]:
        raise DataError(path, "progress", f"step {progress['step']} is past global_step {progress['global_step']}")
    ranks = payload.get("rng_ranks", [payload["rng"]])
    if not isinstance(ranks, list) or not ranks:
        raise DataError(path, "rng_ranks", "expected one random state per training process")
    for rank, state in enumerate(ranks):
        _check_rng(state, path, f"rng_ranks[{rank}]" if "rng_ranks" in payload else "rng")


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
    from hoidata.reading_media import read_torch

    path = find_checkpoint(run_or_file)
    payload = read_torch(path, "checkpoint", map_location)
    if not isinstance(payload, dict):
        raise DataError(path, None, f"expected a checkpoint dict, got {type(payload).__name__}")
    for key in ("model", "config"):
        if key not in payload:
            raise DataError(path, key, "missing from the checkpoint")
    if not isinstance(payload["model"], dict) or not all(torch.is_tensor(v) for v in payload["model"].values()):
        raise DataError(path, "model", "expected a state dict of tensors")
    return payload


def load_model(run_or_file: str | os.PathLike, mano, device="cpu"):
    """(model in eval mode on ``device``, TrainConfig) from a run folder or checkpoint file."""
    from dataclasses import replace

    from hoisdf.config import config_from_dict
    from hoisdf.model import build_model

    path = find_checkpoint(run_or_file)
    payload = load_checkpoint(path)
    config = config_from_dict(payload["config"], path)
    model = build_model(replace(config.model, weights=""), mano)  # the state dict holds every weight
    load_weights(model, payload["model"], path)
    return model.to(device).eval(), config


def load_weights(model, state_dict, path, hint: str = "") -> None:
    """``model.load_state_dict`` with a mismatch (other architecture, damaged file) as one DataError line.

    Every checkpoint is read through here: the keys of run folders written before the model was grouped into stages
    (``hand_sdf.*``, ``mano_head.*``, ...) are renamed to today's (:func:`hoisdf.model.hoisdf.renamed_state`); the
    parameter order is the same, so their optimizer state resumes as it is."""
    from hoisdf.model.hoisdf import renamed_state

    try:
        model.load_state_dict(renamed_state(state_dict))
    except (RuntimeError, KeyError, TypeError, ValueError) as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = lines[1] if len(lines) > 1 else (lines[0] if lines else type(exc).__name__)
        raise DataError(path, "model", f"the weights do not fit this model ({detail[:200]}){hint}") from None
