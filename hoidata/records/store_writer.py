"""The end of a build: per-shard skips files, skip summaries, and the index written once every shard is done.

:func:`finish_store` is what the last process to finish a store's shards calls (whichever part, node or engine
that is): it is safe to call from many processes at once (see its docstring).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from hoidata import schema, store
from hoidata.errors import DataError
from hoidata.provenance import git_commit  # the runner also names it from here


def extra_name(number: int) -> str:
    """The name of shard ``number``'s skips file (beside its tar and sidecar)."""
    return f"shard-{number:06d}.skips.json"



def read_shard_skips(out: Path, number: int) -> dict:
    """Shard ``number``'s skips file, checked: {"skipped": [...], "records": n, "inputs": {...}, ...}."""
    path = Path(out) / extra_name(number)
    try:
        value = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:  # RecursionError: nested too deeply
        raise DataError(path, None, f"unreadable skips file ({type(exc).__name__}: {exc}); rerun the build to "
                                    "rewrite it") from None
    ok = isinstance(value, dict) and isinstance(value.get("skipped"), list) and isinstance(value.get("records"), int)
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
    summary.index_kept = True  # the index already lists these shards: nothing to write (a read-only rerun)
    if not _index_lists(out, infos):
        with store.index_lock(out):
            if not _index_lists(out, infos):  # nobody wrote it while this process waited for the lock
                write_store_index(out, config, models_dir, numbers, reader_skips, provenance)
                summary.index_kept = False
    summary.index_written = True
    summary.empty_shards = sum(info.count == 0 for info in infos)
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
        metas = [json.loads(m[schema.META]) for m in store.read_shard_members(path, info.size, digest)]
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
