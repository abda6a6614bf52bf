"""Where each record lies in its shard: byte spans from the tar headers, for reading records in any order.

A shard stores each record's members contiguously (:mod:`hoidata.store.shards`), so one record is one byte range:
from its first member's header to the end of its last member's data, padded to the 512-byte tar block. The index
lists keys and shards but no offsets; :func:`record_spans` finds them from the shard's headers, checked against the
index's keys, and :func:`hoidata.store.read_record` reads one record back from its span.

Cost: a local shard is walked header by header, seeking past the data (one small read per member, about 10 µs);
a remote shard has no cheap header walk (one request per member would be millions for a large store), so it is
read once from start to end as one stream, the bytes of one sequential pass.
"""

from __future__ import annotations

import tarfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.store.codec import is_record_key
from hoidata.store.remote import RemoteFile, open_stream


def _padded(size: int) -> int:
    """``size`` rounded up to whole tar blocks."""
    return -(-size // tarfile.BLOCKSIZE) * tarfile.BLOCKSIZE


def _walk(tar: tarfile.TarFile, keys: Sequence[str], path, members: list | None = None) -> np.ndarray:
    """(n, 2) int64 [offset, length] of the records of an opened shard, compared with the index's ``keys``; with
    ``members`` (a list), each record's [(member name, data offset, size), ...] is appended to it, in order."""
    spans = np.zeros((len(keys), 2), np.int64)
    row, current, end = -1, None, 0
    for info in tar:
        key, _, member = info.name.partition(".")
        if not info.isreg() or not member or not is_record_key(key):
            raise DataError(path, info.name, "not a <key>.<member> file")
        if key != current:
            if row >= 0:
                spans[row, 1] = end - spans[row, 0]
            row += 1
            if row >= len(keys) or keys[row] != key:
                there = repr(keys[row]) if row < len(keys) else "no record"
                raise DataError(path, key, f"record {row} of the shard, the index has {there} there (the key appears "
                                           "twice, or the shard was replaced: hoidata verify checks the whole store)")
            current, spans[row, 0] = key, info.offset
            if members is not None:
                members.append([])
        if members is not None:
            members[-1].append((member, info.offset_data, info.size))
        end = info.offset_data + _padded(info.size)
    if row >= 0:
        spans[row, 1] = end - spans[row, 0]
    if row + 1 != len(keys):
        raise DataError(path, None, f"{row + 1} records, the index says {len(keys)}: the shard is truncated or "
                                    "damaged (hoidata verify checks the whole store)")
    return spans


def record_spans(path, keys: Sequence[str], size: int | None = None, members: list | None = None) -> np.ndarray:
    """(n, 2) int64 array: each record's byte offset in the shard and its length (whole tar blocks), in order.

    ``path``: a local shard or a RemoteFile; ``keys``: the index's keys of the shard, in order (a record missing,
    foreign or out of order is a DataError naming the shard and the key); ``size``: the bytes the index gives
    (remote reads stop there); ``members``: a list to which each record's members are appended, as
    [(member name, data offset, size), ...] (what the index files of other loaders list: the wids descriptor's
    names, DALI's per-member offsets).
    """
    try:
        if isinstance(path, RemoteFile):
            with open_stream(path, size) as stream:
                return _walk(tarfile.open(fileobj=stream, mode="r|"), keys, path, members)
        with open(Path(path), "rb") as file:
            return _walk(tarfile.open(fileobj=file, mode="r:"), keys, path, members)
    except (tarfile.TarError, EOFError) as exc:
        raise DataError(path, None, f"truncated or corrupt tar ({exc})") from None
    except OSError as exc:
        raise DataError(path, None, f"cannot read the shard ({exc.strerror or exc})") from None
