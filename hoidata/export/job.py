"""``hoidata export``: a dataset (read through our readers and a pipeline setting) -> another codebase's files.

The work is cut like ``build-sdf``'s (:func:`hoidata.engine.engine.run_task` runs :class:`ExportTask`, each
worker process one :class:`~hoidata.export.worker.ExportWorker`): chunk k holds the
frames k*R .. (k+1)*R-1 of the reader's order; a chunk writes its per-frame files (each to a temporary name,
then renamed) and then its manifest ``.hoidata-export/<format>-<splits>/chunk-%06d.json`` with the annotation
entries and the files it wrote. A chunk whose manifest and files exist is done, so a killed export resumes,
``--part i/N`` jobs split it, and any number of workers gives the same files (per-frame randomness is seeded
from the record key). When every chunk is done, the format's annotation files are assembled from the
manifests in frame order. ``export.json`` pins the settings and frames; a folder exported with others is
refused.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from hoidata import schema
from hoidata.datasets.open import read_splits
from hoidata.engine import Plan, RunSummary, ShardTask, run_task
from hoidata.errors import DataError
from hoidata.reading import read_json
from hoidata.export import gsdf, handoccnet
from hoidata.export.files import write_json
from hoidata.export.formats import DATASETS, FORMATS
from hoidata.export.worker import ExportJob, ExportWorkerSpec, chunk_path
from hoidata.records import BuildConfig, RecordSettings, build_inputs, fingerprint, stated_count_warnings

WORK_DIR = ".hoidata-export"
SPEC_FILE = "export.json"


def export_frames(cfg: BuildConfig, root: Path, mano_dir: Path, models_dir: Path, splits) -> tuple[list, list, list]:
    """(frames, reader skips, ids) of the splits, in reader order; ids are the consumer's image ids: the
    DexYCB toolkit's sample index, or an HO-3D frame's line in ``<split>.txt``. Frames without a hand pose
    (HO-3D's evaluation split) are kept: annotation formats carry what the split has. A DexYCB
    ``dataset.frame_list`` is read as ``build-sdf`` reads it: exactly the listed frames."""
    d = cfg.dataset
    got = read_splits(d.name, root, mano_dir, splits, models_dir=models_dir, dexycb=d.dexycb_setting(),
                      version=d.version, frame_list=d.frame_list)
    return got.frames, got.skips, got.ids


def _spec(fmt: str, cfg: BuildConfig, splits, keys: list[str], options: dict, inputs: dict) -> dict:
    """What ``export.json`` pins: format, settings, splits, frames, options, and the fingerprints of the inputs
    (MANO files, object models, annotations: :func:`hoidata.records.build_inputs`, as ``build.json``)."""
    return json.loads(json.dumps({
        "format": fmt, "config": cfg.as_dict(), "splits": list(splits), "frames": len(keys),
        "keys_sha256": hashlib.sha256("\n".join(keys).encode()).hexdigest(), "options": options,
        "schema_version": schema.SCHEMA_VERSION, "inputs": inputs}))


def _check_spec(work: Path, spec: dict) -> None:
    """Pin a new export's folder to ``spec``; refuse a rerun whose settings, frames, options or inputs differ,
    naming the first difference (the chunks kept would mix with new ones)."""
    path = work / SPEC_FILE
    if path.exists():  # a folder of that name is refused by the read
        old = read_json(path, "valid export.json", "use a new --out folder (nothing was changed)")
        where = fingerprint.first_difference(fingerprint.current_names(old, RecordSettings.RENAMED), spec)
        if where is not None:
            raise DataError(path, where, f"{fingerprint.describe_difference(where, 'export')}; this folder holds an "
                                         "export made with other settings, frames or inputs: use a new --out "
                                         "folder (nothing was changed)")
    else:
        write_json(path, spec, indent=1)


def work_dir(out: Path, fmt: str, splits) -> Path:
    """``out/.hoidata-export/<format>-<splits>``: exports of other splits into the same folder (gSDF's train and
    test lists, say) keep apart and write their own annotation files."""
    return Path(out) / WORK_DIR / f"{fmt}-{'-'.join(splits)}"


def read_manifest(work: Path, number: int) -> dict:
    """Chunk ``number``'s manifest, checked: {"entries": [{..., "files": [...]}], "skipped": [...]}; a missing,
    damaged or malformed one is a DataError naming it."""
    path = chunk_path(work, number)
    hint = "rerun the export to write the chunk again"
    value = read_json(path, "chunk manifest", hint)
    entries = value.get("entries") if isinstance(value, dict) else None
    ok = isinstance(entries, list) and isinstance(value.get("skipped"), list)
    if not ok or not all(isinstance(e, dict) and isinstance(e.get("files"), list) and "split" in e for e in entries):
        raise DataError(path, None, f"not a chunk manifest (expected 'entries' with 'files', and 'skipped'); {hint}")
    return value


def chunk_done(out: Path, work: Path, number: int) -> bool:
    """A chunk is done when its manifest reads and every file it lists exists; a damaged manifest is not done
    (the chunk is exported again: the same files)."""
    try:
        manifest = read_manifest(work, number)
    except DataError:
        return False
    return all(isinstance(f, str) and (out / f).is_file() for e in manifest["entries"] for f in e["files"])


def read_chunks(work: Path, numbers: list[int]):
    """The manifests' entries, in frame order (one chunk in memory at a time)."""
    for n in numbers:
        yield from read_manifest(work, n)["entries"]


@dataclass
class ExportTask(ShardTask):
    """An export's task for :func:`hoidata.engine.run_task`: chunk n holds frames n*R .. (n+1)*R-1."""

    fmt: str
    frames: list
    ids: list
    keys: list[str]
    out: Path
    work: Path
    opts: dict  # picklable options every chunk job carries (recorded in export.json)
    worker: ExportWorkerSpec
    plan: Plan
    desc: str = "export"

    def job(self, number: int) -> ExportJob:
        cut = slice(number * self.plan.per, (number + 1) * self.plan.per)
        return ExportJob(number, self.fmt, self.frames[cut], self.ids[cut], self.keys[cut], str(self.out), self.opts)

    def done(self, numbers: list[int], starting: bool) -> set[int]:
        return {n for n in numbers if chunk_done(self.out, self.work, n)}


def export_dataset(fmt: str, cfg: BuildConfig, root: Path, mano_dir: Path, models_dir: Path, out: Path,
                   splits=None, store: Path | None = None, workers: int = 1, part: tuple[int, int] = (0, 1),
                   chunk_size: int = 64, progress: bool = True, executor=None) -> RunSummary:
    """Export (or resume exporting) the frames of ``cfg``'s setting into ``out`` in format ``fmt``.

    Args:
        fmt: 'handoccnet' or 'gsdf'.
        cfg: the pipeline settings (its ``[dataset]`` selects the frames; ``[record]`` is not used).
        root: the dataset folder.
        mano_dir: the MANO folder (MANO_RIGHT.pkl, MANO_LEFT.pkl).
        models_dir: the YCB models folder.
        out: the folder the consumer's loader reads (see docs/other-codebases.md).
        splits: the splits to export (default: the format's, see :func:`default_splits`).
        store: gsdf: a built store whose SDF rows are re-used for the frames it holds unmirrored.
        workers: worker processes.
        part: ``(i, N)`` of ``--part i/N``: this run does the i-th of N equal slices of the work.
        chunk_size: frames per unit of work (and of resume).
        executor: what runs the chunk jobs (see :func:`hoidata.engine.run_task`).
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; expected one of {tuple(FORMATS)}")
    if cfg.dataset.name not in DATASETS[fmt]:
        raise DataError(None, "dataset.name",
                        f"the {fmt} format reads {' and '.join(DATASETS[fmt])}, not {cfg.dataset.name}")
    start, root, out = time.perf_counter(), Path(root), Path(out)
    splits = tuple(dict.fromkeys(splits or default_splits(fmt, cfg)))  # train,train is one split
    if cfg.dataset.frame_list and len(splits) != 1:
        raise DataError(cfg.dataset.frame_list, "dataset.frame_list",
                        f"a frame list holds the ids of one split, not {splits}")
    frames, reader_skips, ids = export_frames(cfg, root, Path(mano_dir), Path(models_dir), splits)
    if not frames:
        raise DataError(root, None, f"no frames to export for splits {splits} (skipped: {len(reader_skips)})")
    for line in stated_count_warnings(cfg.dataset, [f.split for f in frames]):
        print(line, file=sys.stderr)
    keys = [schema.record_key(f.dataset, f.split, f.frame_id) for f in frames]
    inputs = build_inputs(frames, root, Path(mano_dir), Path(models_dir))
    if store is not None and fmt == "gsdf":  # before anything is written: the store's rows must be of these inputs
        gsdf.check_store_inputs(Path(store), inputs)
    opts = options(fmt, cfg, root, Path(mano_dir), Path(models_dir), store)
    work = work_dir(out, fmt, splits)
    work.mkdir(parents=True, exist_ok=True)
    _check_spec(work, _spec(fmt, cfg, splits, keys, {k: str(v) for k, v in opts.items()}, inputs))
    opts["work"] = str(work)

    spec = ExportWorkerSpec(Path(mano_dir), Path(models_dir), opts.get("store"))
    task = ExportTask(fmt, frames, ids, keys, out, work, opts, spec, Plan(len(frames), chunk_size), f"export {fmt}")
    summary = run_task(task, workers, part, progress, executor)
    summary.out = out
    summary.reader_skipped = [{"frame_id": s.frame_id, "reason": s.reason, "path": s.path} for s in reader_skips]
    if summary.all_done:  # the whole export's skips and frames, then the format's annotation files
        numbers = summary.units
        summary.skipped = [s for n in numbers for s in read_manifest(work, n)["skipped"]]
        summary.written = sum(1 for _ in read_chunks(work, numbers))
        finish = finish_function(fmt)
        summary.files, sdf_sources, summary.notes = finish(out, cfg, splits, lambda: read_chunks(work, numbers), root,
                                                           Path(models_dir))
        summary.extra["sdf_sources"] = sdf_sources
        summary.finished = True
    summary.seconds = time.perf_counter() - start
    return summary


def default_splits(fmt: str, cfg: BuildConfig) -> tuple[str, ...]:
    """The splits a format's loaders read: HO-3D's train and evaluation lists; for DexYCB the setting's splits."""
    if cfg.dataset.name == "ho3d":
        return ("train", "evaluation")
    return tuple(cfg.dataset.splits)


def options(fmt: str, cfg, root: Path, mano_dir: Path, models_dir: Path, store) -> dict:
    """The picklable options every chunk job carries (recorded in ``export.json``)."""
    out = {"root": str(Path(root).resolve()), "setup": cfg.dataset.setup, "dataset": cfg.dataset.name}
    if fmt == "gsdf":
        out["store"] = str(Path(store).resolve()) if store else ""
    return out


def finish_function(fmt: str):
    """The format's last step: (out, cfg, splits, entries(), root, models_dir) -> (files, sdf sources, notes)."""
    return handoccnet.finish if fmt == "handoccnet" else gsdf.finish
