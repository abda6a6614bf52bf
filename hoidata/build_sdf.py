"""``hoidata build-sdf``: frames -> records -> shards, in parallel, resumable, splittable into parts.

The unit of work is a shard: shard k holds the frames k*R .. (k+1)*R-1 of the reader's order (R
records per shard), so its content depends only on the frames and the record settings. Workers, parts
(``--part i/N`` takes the shards with k % N == i) and resumed runs therefore produce byte-identical
shards. A finished shard has a sidecar with its checksum; a resumed build keeps intact shards.
When every planned shard is done, the zarr index is written (:mod:`hoidata.records.store_writer`: by the last part to
finish, whatever the order).

build-sdf is a recipe on :mod:`hoidata.engine`: :class:`BuildTask` plans the shards, its store writer
(:class:`hoidata.records.StoreWriter`) says which are done; each worker process opens one
:class:`hoidata.records.RecordWorker` (MANO, objects, mask renderers)
that builds and writes the shards it is given. The jobs run in a local process pool, or on another executor with
the same contract (``executor``: :func:`hoidata.engine.ray_tasks.run_ray`); ``hoidata.engine.slurm`` submits
the parts as a Slurm array.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from hoidata import schema
from hoidata.datasets.frame import Skip
from hoidata.datasets.frame_list import frame_list_provenance, read_frame_list
from hoidata.datasets.open import read_splits
from hoidata.engine import Plan, RunSummary, run_task
from hoidata.errors import DataError
from hoidata.records import (
    BuildConfig,
    RecordSettings,
    RecordWorker,
    RecordWorkerSpec,
    ShardJob,
    StoreTask,
    StoreWriter,
    build_inputs,
    describe_skips,
    skip_dict,
    stated_count_warnings,
)


def read_frames(cfg: BuildConfig, root: Path, mano_dir: Path,
                models_dir: Path | None = None) -> tuple[list, list[Skip]]:
    """All frames of the configured splits, in reader order, and the reader's skips. ``models_dir`` (default
    ``root/models``) is what DexYCB's proximity filter reads: the build's ``--models``, as export's
    (:func:`hoidata.datasets.open.read_splits`, with the frame-list check)."""
    d = cfg.dataset
    got = read_splits(d.name, root, mano_dir, d.splits, models_dir=models_dir, dexycb=d.dexycb_setting(),
                      version=d.version, frame_list=d.frame_list)
    return got.frames, got.skips


class NoFramesDataError(DataError):
    """The selection holds no frame to build (raised before anything is written)."""


@dataclass
class BuildTask(StoreTask):
    """build-sdf's task for :func:`hoidata.engine.run_task`: shard n holds the frames n*R .. (n+1)*R-1 of the
    reader's order (``plan.per`` = R records per shard), built by a :class:`RecordWorker` per process; the
    :class:`StoreWriter` says which shards are done and refuses kept ones whose frames' files changed."""

    frames: list
    keys: list[str]
    settings: RecordSettings
    store: StoreWriter
    worker: RecordWorkerSpec
    plan: Plan
    desc: str = "build-sdf"

    def job(self, number: int) -> ShardJob:
        cut = slice(number * self.plan.per, (number + 1) * self.plan.per)
        return ShardJob(number, self.frames[cut], self.keys[cut], self.settings, self.store.out, self.store.root)


def build_store(cfg: BuildConfig, root: Path, mano_dir: Path, models_dir: Path, out: Path, workers: int = 1,
                part: tuple[int, int] = (0, 1), progress: bool = True, executor=None,
                inputs: dict | None = None) -> RunSummary:
    """Build (or resume) the store in `out`; see the module docstring (``executor``: what runs the shard jobs,
    see :func:`hoidata.engine.run_task`; ``inputs``: where the inputs came from, recorded in the index,
    :mod:`hoidata.provenance`). The summary counts frames (items) and shards (units)."""
    root, out, models_dir = Path(root), Path(out), Path(models_dir)
    start = time.perf_counter()
    frames, reader_skips = read_frames(cfg, root, Path(mano_dir), models_dir)
    if not frames:
        raise NoFramesDataError(root, None, f"no frames to build for splits {cfg.dataset.splits}: "
                                   f"{describe_skips(reader_skips, 'the reader skipped')}")
    for line in stated_count_warnings(cfg.dataset, [f.split for f in frames]):
        print(line, file=sys.stderr)
    keys = [schema.record_key(f.dataset, f.split, f.frame_id) for f in frames]
    writer = StoreWriter(out, cfg.as_dict(), models_dir, root, inputs)
    crops = cfg.record.crop_policy()
    writer.pin(keys, build_inputs(frames, root, Path(mano_dir), models_dir, crops.reads_object_folders))
    spec = RecordWorkerSpec(Path(mano_dir), models_dir, cfg.record.crop_size)
    task = BuildTask(frames, keys, cfg.record, writer, spec, Plan(len(keys), cfg.store.records_per_shard))
    summary = run_task(task, workers, part, progress, executor)
    summary.reader_skipped = [skip_dict(s) for s in reader_skips]
    summary.empty_splits = empty_splits(cfg.dataset.splits, frames)
    writer.finish(summary, reader_skips, store_provenance(cfg, root))
    summary.seconds = time.perf_counter() - start
    return summary


def empty_splits(splits, frames) -> tuple[str, ...]:
    """The splits of ``splits`` that none of ``frames`` is in (a store built from them holds none of those)."""
    found = {f.split for f in frames}
    return tuple(s for s in splits if s not in found)


def store_provenance(cfg: BuildConfig, root: Path) -> dict:
    """``source_dataset``: the dataset the records come from (its licence and citation go in the store's card):
    "toy" for a folder make-toy wrote, else ``dataset.name``. DexYCB also: ``{"toolkit_splits": {split: {"name":
    "s0_test", "size": N}}}``, the toolkit's enumeration the records' ``sample_index`` refers to (result files must
    hold every valid id of it)."""
    from hoidata.store.sources import TOY_MARKER

    source = {"source_dataset": "toy" if (Path(root) / TOY_MARKER).is_file() else cfg.dataset.name}
    if cfg.dataset.name != "dexycb":
        return source
    from hoidata.datasets.dexycb_layout import toolkit_split

    splits, listed = {}, cfg.dataset.frame_list
    for split in cfg.dataset.splits:
        try:
            enum = toolkit_split(root, cfg.dataset.setup, split)
            splits[split] = {"name": enum.name, "size": enum.size}
        except DataError:  # the reader recorded the unreadable meta.yml; the ids are unknown
            splits[split] = {"name": f"{cfg.dataset.setup}_{split}", "size": None}
    return {**source, "toolkit_splits": splits,
            **({"frame_list": frame_list_provenance(listed, read_frame_list(listed))} if listed else {})}


def estimate_build(cfg: BuildConfig, root: Path, mano_dir: Path, models_dir: Path, workers: int = 1,
                   sample: int = 6) -> dict:
    """Time and disk of a build, from `sample` frames spread over the selection; writes nothing."""
    frames, skips = read_frames(cfg, Path(root), Path(mano_dir), Path(models_dir))
    if not frames:
        raise DataError(root, None, "no frames to build")
    picks = sorted({int(i) for i in range(0, len(frames), max(1, len(frames) // sample))})[:sample]
    worker = RecordWorker(Path(mano_dir), Path(models_dir), cfg.record.crop_size)
    try:
        worker.record(frames[picks[0]], "warmup", cfg.record)  # the first call pays for object loading and GL set-up
        start, size = time.perf_counter(), 0
        for i in picks:
            f = frames[i]
            members = worker.record(f, schema.record_key(f.dataset, f.split, f.frame_id), cfg.record)
            size += sum(len(v) for v in members.values())
        per_frame = (time.perf_counter() - start) / len(picks)
    finally:
        worker.close()
    return {"frames": len(frames), "skipped_by_reader": len(skips), "seconds_per_frame": round(per_frame, 3),
            "frames_per_second_per_worker": round(1 / per_frame, 2),
            "estimated_minutes": round(len(frames) * per_frame / max(workers, 1) / 60, 1),
            "bytes_per_frame": size // len(picks), "estimated_gb": round(size / len(picks) * len(frames) / 1e9, 3),
            **({"splits_without_frames": ", ".join(empty)} if (empty := empty_splits(cfg.dataset.splits, frames)) else {})}


def mask_iou_line(store: Path) -> str | None:
    """The build summary's mask QA: the mean IoU (and the lowest) of the records' masks with the dataset's own
    (``seg_iou``: hand, object; -1 where the dataset has none), or None when no record has one."""
    import numpy as np

    from hoidata.store import read_index

    iou = read_index(store).labels.get("seg_iou")
    parts = []
    for i, name in enumerate(("hand", "object")):
        values = np.asarray(iou[:, i], np.float64) if iou is not None else np.array([])
        values = values[np.isfinite(values) & (values >= 0)]
        if values.size:
            parts.append(f"{name} {values.mean():.3f} (lowest {values.min():.3f}, {values.size} records)")
    return "mask IoU with the dataset's own masks: " + "; ".join(parts) if parts else None


def supervision_line(store: Path) -> str:
    """The build summary's line naming the store's supervision sources, from the settings its index records:
    the mask targets (``record.masks``) and the SDF samples (``record.sdf_points``); a store built before these
    settings existed holds the defaults."""
    from hoidata.store import read_index

    record = read_index(store).config.get("record", {})
    masks = {"dataset": "the dataset's own masks (visible planes; amodal ones rendered)"}.get(
        record.get("masks", "rendered"), "rendered from the meshes")
    points = {"deepsdf": "deepsdf (the authors' AlignSDF/DeepSDF per-entity blocks)"}.get(
        record.get("sdf_points", "project"), "project (hand, object and uniform sets)")
    return f"supervision: masks {masks}; SDF samples {points}"
