"""The parent side of a task that writes store shards (build-sdf, render-synthetic): the ``build.json`` that pins a
store to its settings, frames and inputs, and which shards are done (resume), for :mod:`hoidata.engine.engine`.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from hoidata import schema, store
from hoidata.atomic import write_json_atomic
from hoidata.errors import DataError
from hoidata.records import fingerprint
from hoidata.records.store_writer import read_shard_skips

BUILD_FILE = "build.json"


def check_build_file(out: Path, config: dict, keys: list[str], inputs: dict) -> None:
    """Pin a new store folder to ``config``, the record ``keys`` and the ``inputs``' fingerprints (writes
    ``build.json``); refuse to resume into a store built with other settings, frames or inputs (it would mix
    records), naming the first difference."""
    spec = {"config": config, "keys_sha256": hashlib.sha256("\n".join(keys).encode()).hexdigest(),
            "frames": len(keys), "schema_version": schema.SCHEMA_VERSION, "inputs": inputs}
    spec = json.loads(json.dumps(spec))
    path = Path(out) / BUILD_FILE
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
        Path(out).mkdir(parents=True, exist_ok=True)
        write_json_atomic(path, spec)


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
