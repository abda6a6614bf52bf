"""The one store writer of the recipes that write store shards (build-sdf, render-synthetic): the parent's side of a
store, from its first file to its last.

- ``build.json`` pins a store folder to its settings, record keys and input fingerprints (:func:`check_build_file`;
  a resume with others is refused, naming the first difference);
- which shards are done (:func:`shards_done`: intact on disk, with a skips file that agrees), for the engine's
  resume, and whether the files a kept shard was built from changed since (:mod:`hoidata.records.fingerprint`);
- the per-shard skips files and their summaries; the index, written once every shard is done, by whichever
  process finishes last (:func:`finish_store`: safe to call from many processes at once, see its docstring), and
  right after it the dataset card and the other loaders' index files (:func:`hoidata.store.card.write_store_files`);
- the run's :class:`~hoidata.engine.RunSummary`, completed with the store's state.

:class:`StoreWriter` holds the four for one store; :class:`StoreTask` is the engine task base of a recipe that
writes one.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from hoidata import schema, shapes, store
from hoidata.atomic import write_json_atomic
from hoidata.engine import RunSummary, ShardTask
from hoidata.errors import DataError
from hoidata.provenance import INPUTS, git_commit
from hoidata.reading import parse_json, read_json
from hoidata.records import fingerprint
from hoidata.records.records import RecordSettings
from hoidata.store.card import write_store_files

BUILD_FILE = "build.json"


def extra_name(number: int) -> str:
    """The name of shard ``number``'s skips file (beside its tar and sidecar)."""
    return f"shard-{number:06d}.skips.json"


def read_shard_skips(out: Path, number: int) -> dict:
    """Shard ``number``'s skips file, checked: {"skipped": [...], "records": n, "inputs": {...}, ...}."""
    path = Path(out) / extra_name(number)
    value = read_json(path, "skips file", "rerun the build to rewrite it")
    ok = isinstance(value, dict) and isinstance(value.get("skipped"), list) and type(value.get("records")) is int
    if not ok or not all(isinstance(s, dict) and {"frame_id", "reason"} <= set(s) for s in value["skipped"]):
        raise DataError(path, None, "not a skips file (expected 'skipped' entries and 'records'); rerun the build")
    return value


def skip_dict(skip) -> dict:
    """A Skip as a plain dict (its toolkit sample_index kept when it has one)."""
    if isinstance(skip, dict):
        return skip
    sample = getattr(skip, "sample_index", -1)
    return {"frame_id": skip.frame_id, "reason": skip.reason, "path": skip.path,
            **({"sample_index": sample} if sample >= 0 else {})}


def skip_groups(skips) -> list[tuple[str, int, str]]:
    """(reason without its file path, count, an example path) of a skips list, most frequent first."""
    groups: dict[str, list] = {}
    for skip in map(skip_dict, skips):
        reason, path = str(skip["reason"]), str(skip.get("path") or "")
        head, sep, tail = reason.partition(": ")
        kind = tail if sep and (head == path or Path(head).suffix or "/" in head) else reason
        entry = groups.setdefault(kind, [0, head if kind == tail else path])
        entry[0] += 1
    return sorted(((k, n, p) for k, (n, p) in groups.items()), key=lambda g: -g[1])


def describe_skips(skips, who: str, limit: int = 3) -> str:
    """'<who> N: reason (e.g. path), ...' in one line, the most frequent reasons first."""
    groups = skip_groups(skips)
    parts = [f"{n} x {kind}" + (f" ({path})" if path else "") for kind, n, path in groups[:limit]]
    more = f", and {len(groups) - limit} other reasons" if len(groups) > limit else ""
    return f"{who} {len(skips)}" + (": " + "; ".join(parts) + more if parts else "")


def finish_store(out: Path, config: dict, models_dir: Path, numbers: list[int], reader_skips: list,
                 summary, provenance: dict | None = None) -> list[dict]:
    """Write the index once every shard is done; returns every shard's build-time skips.

    Any number of processes may call this, in any order and at the same time (the array tasks of one build, a
    rerun part, the launcher): they write the index one at a time under :func:`hoidata.store.index_lock`, and
    whoever finds the index already listing exactly these shards writes nothing (so a finished store on a
    read-only disk can be "rebuilt", and a second finisher does not write it again). The one that writes checks
    every shard's bytes against its sidecar in the same pass that gathers the labels; a shard damaged since it
    was written is an error (a rerun of the build rewrites it).
    """
    build_skips = [s for n in numbers for s in read_shard_skips(out, n)["skipped"]]
    infos = [store.read_sidecar(out, n) for n in numbers]
    if not sum(info.count for info in infos):
        raise DataError(out, None, f"no records: every frame was skipped while building; "
                                   f"{describe_skips(build_skips, 'skipped')}")
    summary.finish_kept = True  # the index already lists these shards: nothing to write (a read-only rerun)
    if not _index_lists(out, infos):
        with store.index_lock(out):
            if not _index_lists(out, infos):  # nobody wrote it while this process waited for the lock
                write_store_index(out, config, models_dir, numbers, reader_skips, provenance)
                summary.notes += write_store_files(out)
                summary.finish_kept = False
    summary.finished = True
    summary.empty_units = sum(info.count == 0 for info in infos)
    return build_skips


def _index_lists(out: Path, infos: list) -> bool:
    """Whether ``out`` has an index that lists exactly these shards."""
    try:
        return store.read_index(out).shards == infos
    except DataError:
        return False


def _shard_metas(path: Path, info) -> list[dict]:
    """The meta.json of every record of a shard, read in the same pass that checks its bytes against its sidecar
    (size and sha256: a shard damaged since it was written is a DataError asking for a rerun)."""
    digest = hashlib.sha256()
    try:
        members = store.read_shard_members(path, info.size, digest)
        metas = [parse_json(store.record_member(m, schema.META, path), path, f"{m.get('__key__')}.{schema.META}")
                 for m in members]
    except DataError as exc:
        raise DataError(path, exc.field, f"{exc.problem}; rerun the build into this folder to rewrite it") from None
    if digest.hexdigest() != info.sha256:
        raise DataError(path, None, "does not match its sidecar's sha256 (damaged since it was written); "
                                    "rerun the build into this folder to rewrite it")
    return metas


def write_store_index(out: Path, config: dict, models_dir: Path, numbers: list[int], reader_skips: list,
                      provenance: dict | None = None) -> None:
    """Gather every shard's labels and skips and write index.zarr (config and provenance are recorded)."""
    from hoidata.objects import load_simplified

    shards, metas, skipped = [], [], list(reader_skips)  # Skips keep their toolkit sample_index
    for n in numbers:
        skipped += read_shard_skips(out, n)["skipped"]
        shards.append(store.read_sidecar(out, n))
        metas += _shard_metas(out / shards[-1].name, shards[-1])
    names = sorted({m["object_name"] for m in metas})
    meshes = {}
    for name in names:
        simple = load_simplified(models_dir, name)
        meshes[name] = (simple.vertices, simple.faces)
    labels = store.index_labels(metas)
    store.write_index(out, shards, labels, meshes, skipped, config, {"git_commit": git_commit(), **(provenance or {})})


def check_build_file(out: Path, config: dict, keys: list[str], inputs: dict) -> None:
    """Pin a new store folder to ``config``, the record ``keys`` and the ``inputs``' fingerprints (writes
    ``build.json``); refuse to resume into a store built with other settings, frames or inputs (it would mix
    records), naming the first difference."""
    spec = {"config": config, "keys_sha256": hashlib.sha256("\n".join(keys).encode()).hexdigest(),
            "frames": len(keys), "schema_version": schema.SCHEMA_VERSION, "inputs": inputs}
    spec = json.loads(json.dumps(spec))
    path = Path(out) / BUILD_FILE
    if path.exists():  # a folder of that name is refused by the read
        old = read_json(path, "store build file", "use a new --out folder")
        where = fingerprint.first_difference(fingerprint.current_names(old, RecordSettings.RENAMED), spec)
        if where is not None:
            raise DataError(path, where, f"{fingerprint.describe_difference(where)}; resuming would mix records: "
                                         "use a new --out folder (nothing was changed)")
    else:
        Path(out).mkdir(parents=True, exist_ok=True)
        write_json_atomic(path, spec)


PINNED_MANO = shapes.Record(optional={"inputs": shapes.Record(optional={"mano": shapes.MapOf(shapes.String())})})


def pinned_mano(out: Path) -> dict:
    """The MANO files' sha256 that ``build.json`` pinned (file name -> digest; {} for a store pinned before them)."""
    path = Path(out) / BUILD_FILE
    pinned = shapes.check(read_json(path, "store build file"), PINNED_MANO, path)
    return pinned.get("inputs", {}).get("mano", {})


def shards_done(out: Path, numbers: list[int], starting: bool) -> set[int]:
    """The shards of ``numbers`` that are done: intact on disk (size and sidecar; with ``starting`` also their
    bytes) and with a readable skips file that agrees with the sidecar (a lost or damaged one makes the shard be
    built again: the same bytes). ``starting``: the engine's call before a run, with this part's shards only, which
    also clears their leftovers of a killed run; else the call after it, while other parts may still be writing."""
    plan = [store.ShardInfo(n, store.shard_name(n), None) for n in numbers]  # counts open: skipped frames shorten
    complete = store.completed_shards(out, plan, clean=starting, check_bytes=starting)
    return {n for n in complete if _skips_agree(out, n)}


def _skips_agree(out: Path, number: int) -> bool:
    try:
        return read_shard_skips(out, number)["records"] == store.read_sidecar(out, number).count
    except DataError:
        return False


@dataclass(frozen=True)
class StoreWriter:
    """One store's parent side (see the module docstring): ``out`` the store folder, ``config`` the settings its
    ``build.json`` and index record, ``models_dir`` the object models (the index's simplified meshes), ``root`` the
    dataset folder whose files the shards' skips files stamp (None: nothing to check on resume)."""

    out: Path
    config: dict
    models_dir: Path
    root: Path | None = None
    inputs: dict | None = None  # where the inputs came from (pipeline, preset, folders): the index records it

    def pin(self, keys: list[str], inputs: dict) -> None:
        """Write ``build.json`` into a new store folder, or refuse a store built with other settings, keys or
        inputs (:func:`check_build_file`)."""
        check_build_file(self.out, self.config, keys, inputs)

    def done(self, numbers: list[int], starting: bool) -> set[int]:
        """The engine's ``done``: :func:`shards_done`."""
        return shards_done(self.out, numbers, starting)

    def check_kept(self, numbers: list[int]) -> None:
        """Refuse kept shards whose frames' files changed since they were built (with a ``root``)."""
        if self.root is not None:
            fingerprint.check_kept_inputs(lambda n: read_shard_skips(self.out, n).get("inputs", {}), numbers,
                                          self.root)

    def finish(self, run: RunSummary, reader_skips: list, provenance: dict | None = None) -> RunSummary:
        """``run`` as the store's summary: its folder and, once every shard is done, the index written (or found
        written) and every shard's skips (:func:`finish_store`)."""
        run.out = self.out
        if run.all_done:
            if self.inputs is not None:  # with the MANO digests build.json pinned (hoidata.provenance)
                provenance = {**(provenance or {}), INPUTS: {**self.inputs, "mano_sha256": pinned_mano(self.out)}}
            run.skipped = finish_store(self.out, self.config, self.models_dir, run.units, reader_skips, run,
                                       provenance)
        return run


class StoreTask(ShardTask):
    """An engine task that writes the shards of one store: a subclass has a ``store`` (:class:`StoreWriter`), which
    says which shards are done and which kept ones to refuse."""

    store: StoreWriter

    def done(self, numbers: list[int], starting: bool) -> set[int]:
        return self.store.done(numbers, starting)

    def check_kept(self, numbers: list[int]) -> None:
        self.store.check_kept(numbers)
