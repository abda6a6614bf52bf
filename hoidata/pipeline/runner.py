"""``hoidata build-sdf``: frames -> records -> shards, in parallel, resumable, splittable into parts.

The unit of work is a shard: shard k holds the frames k*R .. (k+1)*R-1 of the reader's order (R
records per shard), so its content depends only on the frames and the record settings. Workers, parts
(``--part i/N`` takes the shards with k % N == i) and resumed runs therefore produce byte-identical
shards. A finished shard has a sidecar with its checksum; a resumed build keeps intact shards.
When every planned shard is done, the zarr index is written (:mod:`hoidata.pipeline.finish`: by the last part to
finish, whatever the order). The shard jobs run in a local process pool, or on another engine with the same
contract (``engine``: :func:`hoidata.pipeline.ray_tasks.run_ray`); ``hoidata.pipeline.slurm`` submits the parts
as a Slurm array.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from hoidata import schema, store
from hoidata.atomic import write_json_atomic
from hoidata.datasets.frame import Skip
from hoidata.datasets.frame_list import frame_list_provenance, read_frame_list
from hoidata.datasets.open import read_splits
from hoidata.errors import DataError
from hoidata.pipeline import fingerprint
from hoidata.pipeline.finish import (  # noqa: F401 - re-exported: render-synthetic and the CLI use them from here
    _extra_name,
    _skip_dict,
    describe_skips,
    finish_store,
    git_commit,
    read_shard_skips,
    skip_groups,
)
from hoidata.pipeline.settings import BuildConfig, stated_count_warnings

BUILD_FILE = "build.json"


def read_frames(cfg: BuildConfig, root: Path, mano_dir: Path,
                models_dir: Path | None = None) -> tuple[list, list[Skip]]:
    """All frames of the configured splits, in reader order, and the reader's skips. ``models_dir`` (default
    ``root/models``) is what DexYCB's proximity filter reads: the build's ``--models``, as export's
    (:func:`hoidata.datasets.open.read_splits`, with the frame-list check)."""
    d = cfg.dataset
    got = read_splits(d.name, root, mano_dir, d.splits, models_dir=models_dir, dexycb=d.dexycb_setting(),
                      version=d.version, frame_list=d.frame_list)
    return got.frames, got.skips


@dataclass
class BuildSummary:
    store: Path
    frames: int = 0
    records: int = 0
    skipped: list = field(default_factory=list)  # frames skipped while building (every shard's, once the store is done)
    reader_skipped: list = field(default_factory=list)  # frames the dataset reader left out, with their reasons
    shards_written: int = 0
    empty_shards: int = 0  # shards whose frames were all skipped
    shards_kept: int = 0
    seconds: float = 0.0
    index_written: bool = False  # the store is complete: its index lists every shard
    index_kept: bool = False  # ... and this run found it so (an earlier run or another part wrote it)

    @property
    def frames_per_second(self) -> float:
        return self.records / self.seconds if self.seconds else 0.0


_WORKER: dict = {}


def _init_worker(mano_dir: Path, models_dir: Path, crop_size: int) -> None:
    """Per-process state: MANO layers (loaded on first use), object geometry cache and one mask renderer."""
    import torch

    from hoidata.render.masks import MaskRenderer

    torch.set_num_threads(1)
    _WORKER.update(mano_dir=Path(mano_dir), manos={}, models_dir=Path(models_dir), objects={},
                   renderer=MaskRenderer(crop_size // 2, crop_size // 2))


def hand_model(side: str, fix_left_shapedirs: bool):
    """The worker's MANO layer for a side and left-hand shape convention, loaded once."""
    import torch

    from hoidata.hand import load_mano

    key = (side, fix_left_shapedirs or side == "right")
    if key not in _WORKER["manos"]:
        _WORKER["manos"][key] = load_mano(_WORKER["mano_dir"], side=side, fix_left_shapedirs=key[1], dtype=torch.float64)
    return _WORKER["manos"][key]


def object_asset(models_dir: Path, name: str, upstream: bool = False):
    """Repaired full-resolution object geometry and its 21-point box, for SDF and masks; ``upstream``: also the
    21-point box of its ``points.xyz`` as upstream's loaders build it (``record.crop = "upstream"``)."""
    import numpy as np

    from hoidata.geometry.upstream_crop import box21_upstream
    from hoidata.objects import box21, load_object_mesh, load_points, object_mesh_path, object_points_path, repair_mesh
    from hoidata.pipeline.records import ObjectAsset

    geo, report = repair_mesh(load_object_mesh(object_mesh_path(models_dir, name)))
    points = box21_upstream(load_points(object_points_path(models_dir, name))) if upstream else None
    return ObjectAsset(name, np.asarray(geo.vertices), np.asarray(geo.faces), bool(report.watertight),
                       box21(np.asarray(geo.vertices)), points)


def _renderer(size: int):
    """The worker's mask renderer for records of ``size`` px (masks at half of it); other sizes than the store's
    crop_size (upstream crops: 256 px) get their own, made on first use."""
    from hoidata.render.masks import MaskRenderer

    if _WORKER["renderer"].width == size // 2:
        return _WORKER["renderer"]
    more = _WORKER.setdefault("more_renderers", {})
    if size not in more:
        more[size] = MaskRenderer(size // 2, size // 2)
    return more[size]


def _close_renderers() -> None:
    """Close this process's renderers (the serial run's own)."""
    for renderer in [_WORKER.pop("renderer", None), *_WORKER.pop("more_renderers", {}).values()]:
        if renderer is not None:
            renderer.close()


def _build_one(frame, key: str, settings, source=None):
    """One frame's encoded record; ``source`` (when given) replaces ``frame.source`` in the stored meta only: the
    frame keeps the paths its files are read from."""
    from hoidata.pipeline.records import build_eval_record, build_record
    from hoidata.pipeline.upstream_records import record_size

    objects = _WORKER["objects"]
    if frame.object_name not in objects:
        objects[frame.object_name] = object_asset(_WORKER["models_dir"], frame.object_name, settings.crop == "upstream")
    if not frame.has_hand_pose:  # e.g. HO-3D's evaluation split: no hand mesh, so no masks or SDF
        rec = build_eval_record(frame, objects[frame.object_name], key, settings)
    else:
        mano = hand_model(frame.side, frame.fix_left_shapedirs)  # the model the frame's labels were made with
        renderer = _renderer(record_size(frame, settings))
        rec = build_record(frame, mano, objects[frame.object_name], renderer, key, settings)
    if source is not None:
        rec["meta"]["source"] = source
    return store.encode_record(key, rec["img"], rec["seg"], rec["heatmap"], rec["sdf"], rec["meta"])


@dataclass
class ShardJob:
    """One shard to build: its frames and keys, the record settings, the store folder; ``root`` (the dataset
    folder) makes the shard's skips file fingerprint the files its frames read; ``extra`` goes into that file."""

    number: int
    frames: list
    keys: list[str]
    settings: object
    out: Path
    root: Path | None = None
    extra: dict | None = None


def _build_shard(job: ShardJob) -> tuple[int, int, list]:
    """Build and write one shard (empty when every frame was skipped); returns (number, records written, skips).

    The shard (tar and sidecar) is written first, then its skips file: a shard counts as done only with both.
    """
    records, skips, inputs = [], [], {}
    for frame, key in zip(job.frames, job.keys):
        source = None
        if job.root is not None:
            inputs.update(fingerprint.frame_inputs(frame, Path(job.root)))
            # the record's 'source' names files relative to the dataset folder, however --root was spelled; the
            # frame itself keeps its paths (the record recipe may read them: labels, HO-3D's meta for upstream crops)
            source = fingerprint.root_relative(frame.source, Path(job.root))
        try:
            records.append((key, _build_one(frame, key, job.settings, source)))
        except (DataError, ValueError) as e:  # a broken frame is skipped with its reason, the build goes on
            skips.append({"frame_id": frame.frame_id, "reason": str(e), "path": str(frame.image_path)})
    store.write_shard(job.out, job.number, records)
    write_json_atomic(Path(job.out) / _extra_name(job.number),
                      {"skipped": skips, "records": len(records), "inputs": inputs, **(job.extra or {})})
    return job.number, len(records), skips


def _shard_done(out: Path, number: int, complete: set[int]) -> bool:
    """Done: the shard is intact on disk (complete) and its skips file is readable and agrees with it; a lost
    or damaged skips file makes the shard be built again (the same bytes)."""
    if number not in complete:
        return False
    try:
        return read_shard_skips(out, number)["records"] == store.read_sidecar(out, number).count
    except DataError:
        return False


def _check_build_file(out: Path, config: dict, keys: list[str], inputs: dict) -> None:
    """Refuse to resume into a store built with other settings, frames or inputs (it would mix records)."""
    import hashlib

    spec = {"config": config, "keys_sha256": hashlib.sha256("\n".join(keys).encode()).hexdigest(),
            "frames": len(keys), "schema_version": schema.SCHEMA_VERSION, "inputs": inputs}
    spec = json.loads(json.dumps(spec))
    path = out / BUILD_FILE
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:  # RecursionError: nested too deeply
            raise DataError(path, None, f"unreadable ({type(exc).__name__}: {exc}); use a new --out folder") from None
        where = fingerprint.first_difference(old, spec)
        if where is not None:
            raise DataError(path, where, f"{fingerprint.describe_difference(where)}; resuming would mix records: "
                                         "use a new --out folder (nothing was changed)")
    else:
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(path, spec)


def build_inputs(frames, root: Path, mano_dir: Path, models_dir: Path, upstream: bool = False) -> dict:
    """What build.json pins besides settings and keys (see hoidata.pipeline.fingerprint); ``upstream``: the
    models' whole folders (upstream's crop reads points.xyz too)."""
    return {"mano": fingerprint.files(mano_dir, fingerprint.MANO_FILES),
            "models": fingerprint.models(models_dir, {f.object_name for f in frames}, whole_folder=upstream),
            "annotations": fingerprint.annotations(frames, root)}


def build_store(cfg: BuildConfig, root: Path, mano_dir: Path, models_dir: Path, out: Path, workers: int = 1,
                part: tuple[int, int] = (0, 1), progress: bool = True, engine=None) -> BuildSummary:
    """Build (or resume) the store in `out`; see the module docstring (``engine``: see :func:`run_shards`)."""
    root, out, models_dir = Path(root), Path(out), Path(models_dir)
    start = time.perf_counter()
    frames, reader_skips = read_frames(cfg, root, Path(mano_dir), models_dir)
    if not frames:
        raise DataError(root, None, f"no frames to build for splits {cfg.dataset.splits}: "
                                    f"{describe_skips(reader_skips, 'the reader skipped')}")
    for line in stated_count_warnings(cfg.dataset, [f.split for f in frames]):
        print(line, file=sys.stderr)
    keys = [schema.record_key(f.dataset, f.split, f.frame_id) for f in frames]
    _check_build_file(out, cfg.as_dict(), keys, build_inputs(frames, root, Path(mano_dir), models_dir,
                                                                      cfg.record.crop == "upstream"))
    per = cfg.store.records_per_shard

    def make_job(n):
        return ShardJob(n, frames[n * per:(n + 1) * per], keys[n * per:(n + 1) * per], cfg.record, out, root)

    def check_kept(numbers):
        fingerprint.check_kept_inputs(lambda n: read_shard_skips(out, n).get("inputs", {}), numbers, root)

    init = (Path(mano_dir), models_dir, cfg.record.crop_size)
    summary, numbers, done = run_shards(out, len(keys), per, make_job, _build_shard, _init_worker, init, workers,
                                        part, progress, "build-sdf", check_kept=check_kept, engine=engine)
    summary.reader_skipped = [_skip_dict(s) for s in reader_skips]
    if done:
        summary.skipped = finish_store(out, cfg.as_dict(), models_dir, numbers, reader_skips, summary,
                                       toolkit_provenance(cfg, root))
    summary.seconds = time.perf_counter() - start
    return summary


def toolkit_provenance(cfg: BuildConfig, root: Path) -> dict:
    """DexYCB: ``{"toolkit_splits": {split: {"name": "s0_test", "size": N}}}``, the toolkit's enumeration the
    records' ``sample_index`` refers to (result files must hold every valid id of it); else {}."""
    if cfg.dataset.name != "dexycb":
        return {}
    from hoidata.datasets.dexycb_layout import toolkit_split

    splits, listed = {}, cfg.dataset.frame_list
    for split in cfg.dataset.splits:
        try:
            enum = toolkit_split(root, cfg.dataset.setup, split)
            splits[split] = {"name": enum.name, "size": enum.size}
        except DataError:  # the reader recorded the unreadable meta.yml; the ids are unknown
            splits[split] = {"name": f"{cfg.dataset.setup}_{split}", "size": None}
    return {"toolkit_splits": splits, **({"frame_list": frame_list_provenance(listed, read_frame_list(listed))}
                                         if listed else {})}


def run_shards(out: Path, n_items: int, per: int, make_job, shard_fn, init, initargs, workers: int,
               part: tuple[int, int], progress: bool, desc: str, done=None,
               check_kept=None, engine=None) -> tuple[BuildSummary, list[int], bool]:
    """Run the missing shard jobs of this part, serially or in a pool (hoidata.pipeline.pool); report whether all
    are done (of every part: sidecars, sizes and skips files; finish_store checks the bytes before indexing).

    make_job(n) -> the picklable job of shard n; shard_fn(job) -> (number, records written, skips);
    init(*initargs) sets up each worker process. done(n) -> whether unit n is finished, for jobs that write
    something other than store shards (default: the store shard, its sidecar and its skips file are intact).
    check_kept(numbers) may refuse the units a resumed run keeps (inputs that changed since). engine: what runs
    the jobs, with run_pool's signature and contract (default run_pool; e.g. ray_tasks.run_ray).
    """
    from hoidata.pipeline.pool import run_pool

    start = time.perf_counter()
    numbers = list(range((n_items + per - 1) // per))
    # count left open: items skipped while building make a shard shorter (build.json pins the items)
    plan = [store.ShardInfo(n, store.shard_name(n), None) for n in numbers]
    owned = [p for p in plan if p.number % part[1] == part[0]]
    if done is None:
        complete = store.completed_shards(out, owned)  # also clears this part's leftovers of a killed run
        mine = [p.number for p in owned if not _shard_done(out, p.number, complete)]
    else:
        complete = {p.number for p in owned if done(p.number)}
        mine = [p.number for p in owned if p.number not in complete]
    if check_kept is not None:
        check_kept([p.number for p in owned if p.number not in mine])
    jobs = [make_job(n) for n in mine]
    summary = BuildSummary(out, frames=n_items, shards_kept=len(owned) - len(mine))
    bar = tqdm(total=sum(min(per, n_items - n * per) for n in mine), desc=desc, unit="frame", disable=not progress)
    try:
        _run((engine or run_pool)(shard_fn, jobs, workers, init, initargs) if jobs else iter(()), summary, bar, start)
    finally:
        bar.close()
        _close_renderers()
    summary.seconds = time.perf_counter() - start
    if done is None:
        finished = store.completed_shards(out, plan, clean=False, check_bytes=False)  # others may still be writing
        return summary, numbers, all(_shard_done(out, n, finished) for n in numbers)
    return summary, numbers, all(done(n) for n in numbers)


def _run(results, summary: BuildSummary, bar, start: float) -> None:
    for _, written, skips in results:
        summary.records += written
        summary.shards_written += 1
        summary.empty_shards += written == 0
        summary.skipped += skips
        bar.update(written + len(skips))
        bar.set_postfix(fps=f"{summary.records / max(time.perf_counter() - start, 1e-9):.2f}")


def estimate_build(cfg: BuildConfig, root: Path, mano_dir: Path, models_dir: Path, workers: int = 1,
                   sample: int = 6) -> dict:
    """Time and disk of a build, from `sample` frames spread over the selection; writes nothing."""
    frames, skips = read_frames(cfg, Path(root), Path(mano_dir), Path(models_dir))
    if not frames:
        raise DataError(root, None, "no frames to build")
    picks = sorted({int(i) for i in range(0, len(frames), max(1, len(frames) // sample))})[:sample]
    _init_worker(Path(mano_dir), Path(models_dir), cfg.record.crop_size)
    _build_one(frames[picks[0]], "warmup", cfg.record)  # first call pays for object loading and GL set-up
    start, size = time.perf_counter(), 0
    for i in picks:
        f = frames[i]
        members = _build_one(f, schema.record_key(f.dataset, f.split, f.frame_id), cfg.record)
        size += sum(len(v) for v in members.values())
    per_frame = (time.perf_counter() - start) / len(picks)
    _close_renderers()
    return {"frames": len(frames), "skipped_by_reader": len(skips), "seconds_per_frame": round(per_frame, 3),
            "frames_per_second_per_worker": round(1 / per_frame, 2),
            "estimated_minutes": round(len(frames) * per_frame / max(workers, 1) / 60, 1),
            "bytes_per_frame": size // len(picks), "estimated_gb": round(size / len(picks) * len(frames) / 1e9, 3)}
