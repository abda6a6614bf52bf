"""The index files other loaders read, written beside a store's shards from the shards' own tar headers.

- ``shardindex.json``: the dataset descriptor of ``wids`` (webdataset's indexed reader): ``wids_version`` 1 and one
  entry per shard, its URL relative to the descriptor, its record count and size in bytes;
- ``shard-%06d.idx``: the index NVIDIA DALI's ``fn.readers.webdataset`` reads (``index_paths``), in the v1.2 text of
  DALI's ``wds2idx``: ``v1.2 <records>``, then a line per record listing each member as ``<member> <data offset>
  <size> <tar name>``. An empty shard gets none: DALI refuses an index of 0 records (and reads a phantom record from
  an empty tar without one), so the DALI recipe leaves such shards out (docs/other-loaders.md).

Megatron-Energon's ``.nv-meta/`` and ``*.tar.idx`` are written by its own ``energon prepare``; the shards are
read, never changed. Every file here is written atomically and depends only on the shards, so a rebuilt store
gets the same bytes. The member offsets come from one header walk per shard (:func:`hoidata.store.record_spans`),
checked against the index's keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata.atomic import write_atomic, write_json_atomic
from hoidata.errors import DataError
from hoidata.reading import parse_json, read_span
from hoidata.schema import META
from hoidata.store.index import ShardInfo, StoreIndex
from hoidata.store.spans import record_spans

WIDS_DESCRIPTOR = "shardindex.json"
WIDS_VERSION = 1
DALI_INDEX_VERSION = "v1.2"
TAR_NAME_FIELD = 100  # bytes of the ustar name field: wids' tar reader reads nothing else (no PAX long names)


def dali_index_name(number: int) -> str:
    """File name of shard ``number``'s DALI index: ``shard-%06d.idx`` (where ``wds2idx`` puts it by default)."""
    return f"shard-{number:06d}.idx"


@dataclass(frozen=True)
class ShardMembers:
    """One shard's records as its tar headers say: ``spans`` (n, 2) [offset, length] per record (whole tar blocks),
    ``members`` per record [(member name, data offset, size), ...] in tar order."""

    info: ShardInfo
    keys: list[str]
    spans: np.ndarray
    members: list[list[tuple[str, int, int]]]

    def tar_names(self):
        """Every member's name in the tar, ``<key>.<member>``, in order."""
        for key, record in zip(self.keys, self.members):
            for member, _, _ in record:
                yield f"{key}.{member}"


def store_members(store_dir, index: StoreIndex) -> list[ShardMembers]:
    """Every shard's records and members, from one header walk per shard (sizes and keys checked against the
    index: a shard replaced or damaged since is a DataError naming it)."""
    out = []
    for info in index.shards:
        keys = index.keys[index.shard_rows(info.number)]
        members: list = []
        spans = record_spans(Path(store_dir) / info.name, keys, info.size, members)
        out.append(ShardMembers(info, list(keys), spans, members))
    return out


def record_metas(store_dir, shards: list[ShardMembers]) -> list[dict]:
    """Each record's ``meta.json``, parsed, in store order: one read at its offset per record."""
    metas = []
    for shard in shards:
        path = Path(store_dir) / shard.info.name
        for key, record in zip(shard.keys, shard.members):
            where = {member: (offset, size) for member, offset, size in record}
            if META not in where:
                raise DataError(path, f"{key}.{META}", "no such member")
            offset, size = where[META]
            metas.append(parse_json(read_span(path, offset, size, f"{key}.{META}"), path, f"{key}.{META}"))
    return metas


def long_tar_names(shards: list[ShardMembers]) -> list[tuple[str, str]]:
    """(shard name, member name) of every member whose tar name is longer than the 100-byte ustar name field."""
    return [(s.info.name, name) for s in shards for name in s.tar_names() if len(name.encode()) > TAR_NAME_FIELD]


def wids_descriptor(shards: list[ShardMembers], name: str, where) -> dict:
    """The ``shardindex.json`` of a store: shard URLs relative to it, counts and sizes. A member name over 100
    bytes is a DataError naming the shard and the member: wids' tar reader takes the name from the 100-byte field
    alone and would split or merge records."""
    long = long_tar_names(shards)
    if long:
        shard, member = long[0]
        raise DataError(where, member, f"in {shard}: its tar name is {len(member.encode())} bytes, longer than the "
                                       f"{TAR_NAME_FIELD}-byte name field wids' tar reader reads (it ignores the PAX "
                                       f"header that holds the full name), so wids would mis-group the records "
                                       f"({len(long)} such names); {WIDS_DESCRIPTOR} not written")
    return {"wids_version": WIDS_VERSION, "name": name,
            "shardlist": [{"url": s.info.name, "nsamples": s.info.count, "filesize": s.info.size} for s in shards]}


def dali_index(shard: ShardMembers) -> str | None:
    """DALI's index text of one shard (None for an empty shard, which DALI cannot index)."""
    if not shard.info.count:
        return None
    lines = [f"{DALI_INDEX_VERSION} {shard.info.count}"]
    for key, record in zip(shard.keys, shard.members):
        lines.append(" ".join(f"{member} {offset} {size} {key}.{member}" for member, offset, size in record))
    return "\n".join(lines) + "\n"


def write_loader_files(store_dir, shards: list[ShardMembers], name: str) -> list[str]:
    """Write ``shardindex.json`` and each non-empty shard's DALI index into the store; returns notes (the reason
    ``shardindex.json`` was not written, if it was not)."""
    store_dir, notes = Path(store_dir), []
    try:
        write_json_atomic(store_dir / WIDS_DESCRIPTOR, wids_descriptor(shards, name, store_dir / WIDS_DESCRIPTOR))
    except DataError as exc:
        (store_dir / WIDS_DESCRIPTOR).unlink(missing_ok=True)  # one from an earlier build would describe other names
        notes.append(str(exc))
    for shard in shards:
        text = dali_index(shard)
        path = store_dir / dali_index_name(shard.info.number)
        if text is None:
            path.unlink(missing_ok=True)
            continue
        write_atomic(path, text.encode())
    return notes
