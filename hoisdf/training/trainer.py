"""The training loop: one step, one epoch, validation, checkpoints, logs. The CLI is :mod:`hoisdf.train`.

Exact resume: a checkpoint holds the model, optimizer, scheduler, every rank's RNG states (torch CPU/CUDA,
Python ``random``, the augmentation/sampling generator; gathered from all ranks under DDP, and each rank
gets its own back) and the position in the epoch. Resuming rebuilds the epoch's loader (its order depends
only on seed and epoch), skips the batches already trained on without computing anything, and then
restores the RNG states, so a run interrupted after step k continues exactly as if it had not stopped
(on the CPU, with any number of processes; cuDNN kernels are not bitwise deterministic on GPUs).
Every file a run appends to per step drops what was logged after the checkpoint (:func:`trim_logs`: metrics.csv,
the keys files, TensorBoard's events). An epoch's checkpoint is written
before its validation runs, and validation stores are opened when the trainer is built.
"""

from __future__ import annotations

import csv
import io
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from hoidata.atomic import append_whole, write_atomic
from hoidata.errors import DataError, naming_os_errors
from hoidata.reading import read_bytes, read_text
from hoidata.store import read_index
from hoisdf.config import TrainConfig, sdf_rows
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.augment import augment_batch
from hoisdf.data.kinds import check_trainable
from hoisdf.model import build_model
from hoisdf.model.sampling import noise_scale
from hoisdf.scoring.metrics import pa_mje
from hoisdf.training.checkpoint import (
    CHECKPOINTS,
    LAST,
    check_training_payload,
    copy_checkpoint,
    load_weights,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from hoisdf.training.losses import HOISDFLoss

CURVE = "metrics.csv"
KEYS = "keys-rank{rank}.txt"  # train.record_keys: the key of every record a rank trained on, one a line


@dataclass
class Progress:
    epoch: int = 0
    step: int = 0  # batches done in this epoch
    global_step: int = 0


def to_device(batch: dict, device: torch.device) -> dict:
    """Move every tensor of a batch to ``device`` (non-blocking when the batch is in pinned memory)."""
    return {k: v.to(device, non_blocking=True) if torch.is_tensor(v) else v for k, v in batch.items()}


def epoch_lr(epoch: int, lr: float, drop: int, gamma: float, lr_min: float) -> float:
    """The reference schedule: lr * gamma^(epoch // drop), floored at lr_min."""
    return max(lr * gamma ** (epoch // drop), lr_min)


def validates_after(epoch: int, schedule: str, every: int, point_sampling_epoch: int) -> bool:
    """Whether validation runs after (0-based) ``epoch``: ``every``, after each ``every``-th epoch (0: never);
    ``upstream``, after epochs 0, 5, 10, ... before ``point_sampling_epoch`` and after every epoch from it
    (upstream's main/train.py:164-169)."""
    if schedule == "upstream":
        return epoch >= point_sampling_epoch or epoch % 5 == 0
    return bool(every) and (epoch + 1) % every == 0


def make_optimizer(model: nn.Module, optimizer: str, lr: float, weight_decay: float) -> torch.optim.Optimizer:
    """``train.optimizer`` over the model's trainable parameters, one group (upstream's ``get_optimizer``: PyTorch's
    betas and eps; a parameter that gets no gradient in a step is skipped by the optimizer, weight decay included)."""
    params = [p for p in model.parameters() if p.requires_grad]
    return {"adamw": torch.optim.AdamW, "adam": torch.optim.Adam}[optimizer](params, lr=lr, weight_decay=weight_decay)


def optimisation_step(model: nn.Module, loss: nn.Module, optimizer: torch.optim.Optimizer, batch: dict, points: str,
                      noise: float, generator: torch.Generator | None, autocast: bool = False):
    """One step on an augmented batch: forward, weighted loss terms, backward, optimizer step; returns (total,
    terms) (tensors). ``autocast``: bf16 autocast on CUDA for the forward."""
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=autocast):
        out = model(batch, points=points, noise=noise, generator=generator)
    total, terms = loss(out, batch)
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    optimizer.step()
    return total, terms


def unwrap(model: nn.Module) -> nn.Module:
    return model.module if hasattr(model, "module") else model


def trim_keys(path: Path, size: int | None, lines: int) -> int:
    """Cut a rank's keys file back to what a checkpoint covers: its first ``size`` bytes (what the checkpoint
    recorded), or, from a checkpoint that recorded none (an older version), its first ``lines`` lines (training
    batches are whole: ``global_step x batch_size`` keys). Returns the file's size after."""
    if not path.is_file():
        return 0
    data = read_bytes(path, "keys file")
    if size is None:
        end = 0
        for _ in range(lines):
            end = data.find(b"\n", end) + 1
            if end == 0:
                return len(data)
        size = end
    if len(data) > size:
        write_atomic(path, data[:size])
    return min(len(data), size)


def trim_log(path: Path, global_step: int) -> None:
    """Drop the metrics.csv rows logged after ``global_step`` (a resumed run logs those steps again)."""
    if not path.is_file():
        return
    try:
        rows = list(csv.reader(io.StringIO(read_text(path, "training log"), newline="")))
    except csv.Error as exc:  # a field past csv's limit: not a log this run wrote
        raise DataError(path, None, f"not a training log ({exc})") from None
    if not rows:
        return
    kept = [rows[0]] + [r for r in rows[1:] if len(r) == 5 and r[2].isdigit() and int(r[2]) <= global_step]
    if len(kept) != len(rows):
        text = io.StringIO()
        csv.writer(text).writerows(kept)
        write_atomic(path, text.getvalue().encode())


def quiet_event_writer_threads() -> None:
    """Keep TensorBoard's event writer thread from printing its own traceback when a write fails (a full disk).

    The thread stores the error, and the writer's next ``add_scalar`` / ``flush`` raises it in the training loop,
    where it becomes the one error line naming ``RUN/tb``; the thread's re-raise would print a second report.
    Installed once, as ``threading.excepthook``; any other thread's error goes to the previous hook."""
    import threading

    previous = threading.excepthook
    if getattr(previous, "quiet_event_writer", False):
        return

    def hook(args) -> None:
        if type(args.thread).__name__ == "_AsyncWriterThread" and issubclass(args.exc_type, OSError):
            return  # raised again by the writer's flush() in the training loop
        previous(args)

    hook.quiet_event_writer = True
    threading.excepthook = hook


class Trainer:
    """Owns the model, loss, optimizer and data of one training run on one rank."""

    def __init__(self, config: TrainConfig, stores: list[StoreSpec], mano, run_dir: Path, device: torch.device,
                 val_stores: list[StoreSpec] = (), rank: int = 0, world_size: int = 1):
        self.config, self.run_dir, self.device = config, Path(run_dir), device
        self.rank, self.world_size = rank, world_size
        self.run_dir.mkdir(parents=True, exist_ok=True)
        t, m = config.train, config.model
        model = build_model(m, mano).to(device)
        if world_size > 1:
            model = nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
        self.model = model
        self.loss = HOISDFLoss(config.loss, mano, m.sdf_scale, m.sdf_clamp, m.cls_dist)
        self.optimizer = make_optimizer(model, t.optimizer, t.lr, t.weight_decay)
        rows_hand, rows_object = sdf_rows(config)  # SDF rows drawn per sample (default: the model's query counts)
        self.dataset = build_dataset(list(stores), t.batch_size, t.epoch_samples or None, t.seed, rows_hand, rows_object,
                                     t.near, t.shuffle_buffer, training=True, shuffle=t.shuffle, progress=rank == 0,
                                     upstream=config.augment.upstream)
        self.loader = make_loader(self.dataset, t.workers, pin_memory=device.type == "cuda")
        self.val_stores = list(val_stores)
        # opened and checked now (index, every shard file), not at the end of the first epoch
        self.val_data = build_dataset(self.val_stores, t.batch_size, seed=t.seed, n_hand=rows_hand, n_object=rows_object,
                                      training=False) if self.val_stores else None
        for spec in self.val_stores:  # validation losses need every label, as training does
            check_trainable(spec.path, read_index(spec.path))
        self.generator = torch.Generator().manual_seed(t.seed * 1000 + rank)
        self.progress = Progress()
        self.autocast = device.type == "cuda" and t.bf16
        self._writer = None
        self._purge_step = None  # resumed: TensorBoard drops the events logged after the checkpoint
        self._checkpoint = self.run_dir / CHECKPOINTS / LAST  # the one resumed from (named in errors)
        self._keys_bytes = 0  # the size of this rank's keys file: what a checkpoint written now covers

    # --- state ----------------------------------------------------------------------------------------------
    def state_dict(self, rng_ranks: list[dict] | None = None, keys_bytes: list[int] | None = None) -> dict:
        """The checkpoint; ``rng_ranks``: every rank's RNG states in rank order (default: this rank's only);
        ``keys_bytes``: every rank's keys file size (default: this rank's)."""
        p = self.progress
        rng_ranks = rng_ranks or [rng_state(self.generator)]
        return {"model": unwrap(self.model).state_dict(), "optimizer": self.optimizer.state_dict(),
                "rng": rng_ranks[0], "rng_ranks": rng_ranks, "config": self.config.as_dict(),
                "progress": {"epoch": p.epoch, "step": p.step, "global_step": p.global_step},
                "keys_bytes": keys_bytes or [self._keys_bytes]}

    def save(self, name: str = LAST) -> Path | None:
        """Write the checkpoint (rank 0); every rank must call it, since it gathers every rank's RNG states and
        keys file size."""
        mine = (rng_state(self.generator), self._keys_bytes)
        states = [mine]
        if self.world_size > 1:
            states = [None] * self.world_size
            torch.distributed.all_gather_object(states, mine)
        if self.rank != 0:
            return None
        payload = self.state_dict([s[0] for s in states], [s[1] for s in states])
        path = save_checkpoint(self.run_dir / CHECKPOINTS / LAST, payload)
        if name != LAST:  # the same bytes under the epoch's name, copied rather than serialised twice
            copy_checkpoint(path, self.run_dir / CHECKPOINTS / name)
        return path

    def load(self, payload: dict, path: Path | str = "<checkpoint>") -> dict:
        """Restore model, optimizer and progress from a checked checkpoint; drop the log rows written after it;
        returns this rank's RNG states, to apply after skipping batches."""
        check_training_payload(payload, path)
        ranks = payload.get("rng_ranks", [payload["rng"]])
        if len(ranks) != self.world_size:
            raise DataError(path, "rng_ranks", f"written by {len(ranks)} training process(es), this run has "
                                               f"{self.world_size}: resume with the same number (torchrun --nproc_per_node)")
        load_weights(unwrap(self.model), payload["model"], path,
                     "; model settings cannot change on --resume: start a new run instead")
        try:
            self.optimizer.load_state_dict(payload["optimizer"])
        except (ValueError, KeyError, TypeError, RuntimeError) as exc:
            raise DataError(path, "optimizer", f"does not fit this model ({exc})") from None
        self.progress, self._checkpoint = Progress(**payload["progress"]), path
        self.trim_logs(payload)
        return ranks[self.rank]

    def trim_logs(self, payload: dict) -> None:
        """Every file the run appends to per step cut back to what the checkpoint covers (a resumed run logs those
        steps again): metrics.csv's rows by their step (rank 0), this rank's keys file to the size the checkpoint
        recorded, TensorBoard's events from the next step on (its reader drops them: ``purge_step``)."""
        step = self.progress.global_step
        if self.rank == 0:
            trim_log(self.run_dir / CURVE, step)
        sizes = payload.get("keys_bytes")
        size = sizes[self.rank] if isinstance(sizes, list) and len(sizes) == self.world_size else None
        size = size if type(size) is int and size >= 0 else None  # an older checkpoint: by steps instead
        batch = payload.get("config", {}).get("train", {}).get("batch_size", self.config.train.batch_size)
        self._keys_bytes = trim_keys(self.run_dir / KEYS.format(rank=self.rank), size, step * int(batch))
        self._purge_step = step + 1

    # --- one step -------------------------------------------------------------------------------------------
    def train_step(self, batch: dict, points: str, noise: float) -> dict[str, float]:
        batch = augment_batch(to_device(batch, self.device), self.config.augment, self.generator, train=True)
        total, terms = optimisation_step(self.model, self.loss, self.optimizer, batch, points, noise, self.generator,
                                         self.autocast)
        logged = {name: float(v.detach()) for name, v in terms.items()}
        logged["total"] = float(total.detach())
        return logged

    def _points_mode(self, epoch: int) -> str:
        t = self.config.train
        if epoch < t.point_sampling_epoch:
            return "gt"
        return "field" if float(torch.rand((), generator=self.generator)) < t.field_prob else "gt"

    # --- epochs ---------------------------------------------------------------------------------------------
    def fit(self, rng_after_skip: dict | None = None, progress_bar: bool = True) -> Progress:
        """Train until ``train.epochs`` (or ``train.max_steps`` steps in total); returns the final progress."""
        t = self.config.train
        while self.progress.epoch < t.epochs and not self._done():
            self._run_epoch(rng_after_skip, progress_bar)
            rng_after_skip = None
        return self.progress

    def _done(self) -> bool:
        max_steps = self.config.train.max_steps
        return bool(max_steps) and self.progress.global_step >= max_steps

    def _run_epoch(self, rng_after_skip: dict | None, progress_bar: bool) -> None:
        t, p = self.config.train, self.progress
        for group in self.optimizer.param_groups:
            group["lr"] = epoch_lr(p.epoch, t.lr, t.lr_drop, t.lr_gamma, t.lr_min)
        skip = self.dataset.set_epoch(p.epoch, start=p.step)  # resumed: a stream is read past its first p.step
        unwrap(self.model).train()
        n_batches = len(self.dataset)
        if p.step > n_batches:
            raise DataError(self._checkpoint, "progress.step",
                            f"{p.step} is past the end of the epoch ({n_batches} batches with these stores)")
        # resume: a checkpoint from an epoch's end holds the RNG before the next loader starts (it draws its
        # seed from torch's RNG); one from inside an epoch holds it after that draw and the batches done
        if rng_after_skip is not None and p.step == 0:
            set_rng_state(rng_after_skip, self.generator)
        batches = iter(self.loader)
        for _ in range(skip):  # batches; the global shuffle starts at batch p.step itself
            next(batches)
        if rng_after_skip is not None and p.step > 0:
            set_rng_state(rng_after_skip, self.generator)
        bar = self._bar(n_batches, p.step, progress_bar)
        tick, seen = time.perf_counter(), 0
        for batch in batches:
            points = self._points_mode(p.epoch)
            terms = self.train_step(batch, points, noise_scale(p.step / n_batches, t.noise_ratios, t.noise_dists))
            self._record_keys(batch["key"])
            p.step += 1
            p.global_step += 1
            seen += len(batch["key"]) * self.world_size
            rate = seen / max(time.perf_counter() - tick, 1e-9)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{terms['total']:.3f}", samples_s=f"{rate:.1f}", points=points)
            if p.global_step % t.log_every == 0 or p.step == 1:
                self.log("train", {**terms, "lr": self.optimizer.param_groups[0]["lr"], "samples_per_s": rate})
            if self._done():
                break
        if bar is not None:
            bar.close()
        if p.step >= n_batches:  # a finished epoch: checkpoint, then validate (a failing validation loses nothing)
            epoch = p.epoch
            p.epoch, p.step = p.epoch + 1, 0
            if t.ckpt_every and p.epoch % t.ckpt_every == 0:
                self.save(f"epoch-{epoch:03d}.pt")
            due = validates_after(epoch, t.val_schedule, t.val_every, t.point_sampling_epoch)
            if due and self.val_data is not None and self.rank == 0:
                self.log("val", self.validate())
        if self._done():
            self.save()

    def _bar(self, total: int, start: int, enabled: bool):
        if self.rank != 0 or not enabled:
            return None
        from tqdm import tqdm

        return tqdm(total=total, initial=start, desc=f"epoch {self.progress.epoch}", unit="batch", leave=False)

    def _record_keys(self, keys: list[str]) -> None:
        if self.config.train.record_keys:
            data = "".join(k + "\n" for k in keys).encode()
            append_whole(self.run_dir / KEYS.format(rank=self.rank), data)
            self._keys_bytes += len(data)

    # --- validation and logs --------------------------------------------------------------------------------
    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Mean loss terms, root-relative MJE and PA-MJE and object centre error (mm) on up to ``val_batches``
        batches (0: every batch of the validation stores)."""
        t, m = self.config.train, self.config.model
        model = unwrap(self.model)
        model.eval()
        sums: dict[str, float] = {}
        count = 0
        for i, batch in enumerate(self.val_data):
            if i == t.val_batches and t.val_batches:
                break
            batch = augment_batch(to_device(batch, self.device), self.config.augment, None, train=False)
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.autocast):
                out = model(batch, points="field")
            total, terms = self.loss(out, batch)
            gt = batch["joints_3d"] - batch["hand_root"][:, None]
            values = {**{k: float(v) for k, v in terms.items()}, "total": float(total),
                      "mje_mm": float((out["joints"].float() - gt).norm(dim=-1).mean()) * 1000,
                      # upstream's rigid_align: similarity with a proper rotation (no reflection)
                      "pa_mje_mm": float(pa_mje(out["joints"].detach().double().cpu().numpy(),
                                                gt.detach().double().cpu().numpy(), reflection=False).mean()) * 1000,
                      "oce_mm": float((out["obj_translation"] - batch["object_pose"][:, :3, 3]).norm(dim=-1).mean()) * 1000}
            n = len(batch["key"])
            for k, v in values.items():
                sums[k] = sums.get(k, 0.0) + v * n
            count += n
        model.train()
        return {**{k: v / max(count, 1) for k, v in sums.items()}, "samples": float(count)}

    def log(self, split: str, values: dict[str, float]) -> None:
        if self.rank != 0:
            return
        p = self.progress
        path = self.run_dir / CURVE
        rows = io.StringIO()  # whole rows or none: a full disk never leaves half a row (append_whole)
        writer = csv.writer(rows)
        if not path.exists():
            writer.writerow(["split", "epoch", "step", "name", "value"])
        for name, value in values.items():
            writer.writerow([split, p.epoch, p.global_step, name, f"{value:.6g}"])
        append_whole(path, rows.getvalue().encode())
        with naming_os_errors(self.run_dir / "tb"):  # the event writer's errors name no file
            self._log_tensorboard(split, values)

    def _log_tensorboard(self, split: str, values: dict[str, float]) -> None:
        if self._writer is None:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:  # tensorboard is optional; metrics.csv has the same numbers
                self._writer = False
            else:
                quiet_event_writer_threads()
                self._writer = SummaryWriter(str(self.run_dir / "tb"), purge_step=self._purge_step)
        if self._writer:
            for name, value in values.items():
                self._writer.add_scalar(f"{split}/{name}", value, self.progress.global_step)
            self._writer.flush()
