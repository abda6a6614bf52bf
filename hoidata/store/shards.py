"""Shards: records as deterministic WebDataset tar files, written atomically, read back strictly.

A store folder holds::

    shard-000000.tar   records in order, each record's members in schema order (see hoidata.schema)
    shard-000000.json  sidecar: the shard's ShardInfo, written right after the shard appears (resume)
    ...
    index.zarr/        zarr v3 group (:mod:`hoidata.store.index`): labels, shard list, meshes, provenance

A build plans its records as fixed runs of ``records_per_shard``; after an interruption it asks
:func:`hoidata.store.verify.completed_shards` which shards are already good, rewrites only the others
with :func:`write_shard` (or streams a straight run through :class:`ShardWriter`) and ends with
:func:`hoidata.store.index.write_index`. Nothing half-written ever carries a final name: shards are
written to ``<name>.<host>-<pid>.tmp`` and renamed.

Reading is one sequential pass over a byte stream (:class:`_ShardBytes` under ``tarfile``'s stream mode), the
same for a local file and for a remote one (:mod:`hoidata.store.remote`), so every check applies to both.
"""

from __future__ import annotations

import hashlib
import io
import os
import tarfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

from hoidata.atomic import write_json_atomic
from hoidata.errors import DataError, naming_os_errors
from hoidata.schema import MEMBERS, WRITE_ORDER, kind_of_members
from hoidata.store.codec import (
    KEY,
    MAX_MEMBER_BYTES,
    check_record_key,
    decode_record,
    is_record_key,
)
from hoidata.store.index import ShardInfo, open_index, shard_name
from hoidata.store.paths import INDEX_NAME, local_store, resolve_store, writer_token
from hoidata.store.remote import UNKNOWN_SIZE, RemoteFile, RemoteStore, open_stream, read_range, remote_sizes

# --------------------------------------------------------------------------------------------------
# shards


def sidecar_name(number: int) -> str:
    """File name of shard ``number``'s sidecar: ``shard-%06d.json``."""
    return f"shard-{number:06d}.json"


class _HashingWriter:
    """File wrapper that hashes and counts what tarfile writes, so a shard is never read back to hash it."""

    def __init__(self, file):
        self._file, self.sha256, self.size = file, hashlib.sha256(), 0

    def write(self, data) -> int:
        self._file.write(data)
        self.sha256.update(data)
        self.size += len(data)
        return len(data)

    def tell(self) -> int:
        return self.size


class _OpenShard:
    """One shard being written under ``<name>.tmp``; ``finish`` renames it into place and writes the sidecar.

    tarfile is used directly, not webdataset's TarWriter: that one stamps the current time (a float,
    which forces an extra PAX header per member) and a "bigdata" owner unless told otherwise, and sorts
    members alphabetically rather than in schema order. Here every header field is pinned (mtime 0,
    uid/gid 0, empty owner names, mode 0o644), so equal records give byte-identical shards.
    """

    def __init__(self, store_dir: Path, number: int):
        self.number, self.path = number, store_dir / shard_name(number)
        self.tmp = self.path.with_name(f"{self.path.name}.{writer_token()}.tmp")  # one per writer (paths.writer_token)
        self._file = open(self.tmp, "wb")
        self._hash = _HashingWriter(self._file)
        self._tar = tarfile.open(fileobj=self._hash, mode="w", format=tarfile.PAX_FORMAT)
        self.keys: list[str] = []

    def add(self, key: str, members: dict[str, bytes]) -> None:
        _check_members_to_write(key, members)
        for member in WRITE_ORDER:  # schema order, whatever order the dict has
            if member not in members:  # a record kind without this member
                continue
            data = bytes(members[member])
            info = tarfile.TarInfo(f"{key}.{member}")
            info.size, info.mtime, info.mode, info.type = len(data), 0, 0o644, tarfile.REGTYPE
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            with naming_os_errors(self.path):  # a full disk's write() error names no file
                self._tar.addfile(info, io.BytesIO(data))
        self.keys.append(key)

    def finish(self) -> ShardInfo:
        with naming_os_errors(self.path):
            self._tar.close()  # end-of-archive blocks and padding to the 10 KiB record size
            self._file.flush()
            os.fsync(self._file.fileno())  # the content is on disk before the name says "complete"
            self._file.close()
            os.replace(self.tmp, self.path)
        first, last = (self.keys[0], self.keys[-1]) if self.keys else (None, None)
        info = ShardInfo(self.number, self.path.name, len(self.keys), self._hash.sha256.hexdigest(),
                         self._hash.size, first, last)
        write_json_atomic(self.path.with_name(sidecar_name(self.number)), info.to_dict())
        return info

    def abort(self) -> None:
        try:
            self._file.close()  # flushes: on a full disk it fails again, and the first error is the one to report
        except OSError:
            pass
        self.tmp.unlink(missing_ok=True)


def _check_members_to_write(key: str, members: dict[str, bytes]) -> None:
    """A record to write: a valid key and bytes for exactly the members of a record kind (schema.RECORD_KINDS)."""
    check_record_key(key, None)
    if kind_of_members(members) is None or not all(isinstance(v, (bytes, bytearray, memoryview))
                                                  for v in members.values()):
        raise DataError(None, key, f"expected bytes for exactly {list(MEMBERS)} (or another record kind's members), "
                                   f"got {sorted(members)}")


def write_shard(store_dir, number: int, records: Iterable[tuple[str, dict[str, bytes]]]) -> ShardInfo:
    """Write one complete shard from (key, members) pairs: the unit of work of a resumable build.

    No records gives an empty shard (a valid tar holding nothing, count 0): a planned shard whose frames were
    all skipped still exists, is counted and is indexed, so shard numbers stay 0..S-1.
    """
    store_dir = Path(store_dir)
    store_dir.mkdir(parents=True, exist_ok=True)
    shard = _OpenShard(store_dir, number)
    try:
        for key, members in records:
            shard.add(key, members)
        return shard.finish()
    except BaseException:
        shard.abort()
        raise


class ShardWriter:
    """Streams records, in order, into shards of ``records_per_shard`` records each.

    ``add`` returns the ShardInfo of a shard it just completed (else None); ``close`` finishes the last,
    partial shard and returns every shard written. Used as a context manager, an exception discards the
    unfinished shard instead of completing it.
    """

    def __init__(self, store_dir, records_per_shard: int, first_shard: int = 0):
        if records_per_shard < 1:
            raise ValueError(f"records_per_shard must be >= 1, got {records_per_shard}")
        self.store_dir = Path(store_dir)
        self.store_dir.mkdir(parents=True, exist_ok=True)
        self.records_per_shard, self.next_shard = records_per_shard, first_shard
        self.shards: list[ShardInfo] = []
        self._open: _OpenShard | None = None

    def add(self, key: str, members: dict[str, bytes]) -> ShardInfo | None:
        if self._open is None:
            self._open = _OpenShard(self.store_dir, self.next_shard)
        self._open.add(key, members)
        return self._finish() if len(self._open.keys) == self.records_per_shard else None

    def _finish(self) -> ShardInfo:
        shard, self._open = self._open, None
        info = shard.finish()
        self.shards.append(info)
        self.next_shard += 1
        return info

    def close(self) -> list[ShardInfo]:
        if self._open is not None and self._open.keys:
            self._finish()
        self.abort()  # an opened shard whose first record was refused
        return list(self.shards)

    def abort(self) -> None:
        """Drop the unfinished shard (its .tmp file); completed shards stay."""
        if self._open is not None:
            self._open.abort()
            self._open = None

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# --------------------------------------------------------------------------------------------------
# reading, verification, resume


class _ShardBytes:
    """The bytes of one shard, read once from the start: counts them, remembers where the last non-zero byte was
    and never reads past ``limit`` (the size the file or the index gives), whatever a server sends."""

    def __init__(self, file, limit: int | None, digest=None):  # limit None: to the end of the stream
        self.file, self.limit, self.offset, self.last_data, self.digest = file, limit, 0, -1, digest

    def read(self, n: int = -1) -> bytes:
        room = (1 << 62) if self.limit is None else self.limit - self.offset
        n = room if n is None or n < 0 or n > room else n
        chunk = self.file.read(n) if n > 0 else b""
        data = len(chunk.rstrip(b"\0"))
        if data:
            self.last_data = self.offset + data - 1
        self.offset += len(chunk)
        if self.digest is not None:
            self.digest.update(chunk)
        return chunk


def _check_tar_end(data: _ShardBytes, end: int, path) -> None:
    """tarfile stops silently at a damaged header: only zeros (>= 2 blocks) may follow the last member, up to the
    shard's size."""
    while data.read(1 << 20):
        pass
    if data.last_data >= end or data.offset - end < 2 * tarfile.BLOCKSIZE:
        raise DataError(path, None, f"the tar stream breaks off at byte {end} of {data.offset}: truncated or corrupt")
    if data.limit is not None and data.offset != data.limit:
        raise DataError(path, None, f"{data.offset} bytes read, expected exactly {data.limit}: truncated or replaced")
    if data.limit is not None and data.file.read(1):
        raise DataError(path, None, f"longer than the {data.limit} bytes expected: replaced or damaged")


def _members(data: _ShardBytes, path) -> Iterator[dict[str, bytes]]:
    """Raw records of one shard stream, in order (see read_shard_members)."""
    try:
        # "r|": a plain tar stream, never compressed. 64 KiB reads: tarfile's stream keeps the unread rest of its
        # last read and copies it on every member read, so a 1 MiB buffer cost 0.6 ms a record against 0.2 here
        tar = tarfile.open(fileobj=data, mode="r|", bufsize=1 << 16)
    except tarfile.TarError as exc:
        raise DataError(path, None, f"not a tar file ({exc})") from None
    record, seen = None, set()
    try:
        for info in tar:
            key, _, member = info.name.partition(".")
            if not info.isreg() or not is_record_key(key) or not member or info.size > MAX_MEMBER_BYTES:
                raise DataError(path, info.name, f"not a <key>.<member> file of at most {MAX_MEMBER_BYTES} bytes")
            if record is None or key != record[KEY]:
                if record is not None:
                    yield record
                if key in seen:
                    raise DataError(path, key, "the key appears twice (records must be unique and contiguous)")
                seen.add(key)
                record = {KEY: key}
            if member in record:
                raise DataError(path, info.name, "the member appears twice")
            record[member] = tar.extractfile(info).read()
    except (tarfile.TarError, EOFError) as exc:
        key = None if record is None else record[KEY]
        raise DataError(path, key, f"truncated or corrupt tar ({exc})") from None
    _check_tar_end(data, tar.offset, path)
    if record is not None:
        yield record


def read_shard_members(path, size: int | None = None, digest=None) -> Iterator[dict[str, bytes]]:
    """Raw records of one shard, in order: {"__key__": key, member name: bytes}, names not yet checked.

    ``path``: a local file or a :class:`~hoidata.store.remote.RemoteFile`; ``size``: the bytes to expect (default:
    the file's own size). Member sizes are checked before a member is read, so a hostile shard cannot make the
    reader allocate more than MAX_MEMBER_BYTES; nothing past ``size`` is read. ``digest`` (a hashlib object), if
    given, is updated with every byte of the file (so one pass reads and hashes it).
    """
    if isinstance(path, RemoteFile):
        if size is None:
            size = remote_sizes([path])[0]
            if size is None:
                raise DataError(path, None, "missing (no such file at this URL)")
        size = None if size == UNKNOWN_SIZE else size  # not stated by the server: read to the end, counting
        with open_stream(path, size) as file:
            yield from _members(_ShardBytes(file, size, digest), path)
        return
    with open(path, "rb") as file:
        yield from _members(_ShardBytes(file, os.fstat(file.fileno()).st_size if size is None else size, digest), path)


def record_member(members: dict, name: str, path) -> bytes:
    """Member ``name`` of one raw record (:func:`read_shard_members`); absent is a DataError naming the record."""
    if name not in members:
        raise DataError(path, f"{members.get('__key__')}.{name}", "member missing")
    return members[name]


def shard_source(location, name: str):
    """A shard of a store (a folder or a :class:`~hoidata.store.remote.RemoteStore`): its Path or RemoteFile."""
    location = resolve_store(location)
    return location.file(name) if isinstance(location, RemoteStore) else location / name


def shard_sizes(sources: Sequence) -> list[int | None]:
    """The size in bytes of each shard source (None where there is no such file, UNKNOWN_SIZE where a server
    serves it without stating one); remote ones asked concurrently."""
    remote = [s for s in sources if isinstance(s, RemoteFile)]
    sizes = dict(zip(remote, remote_sizes(remote)))
    return [sizes[s] if isinstance(s, RemoteFile) else (s.stat().st_size if Path(s).is_file() else None)
            for s in sources]


def read_checked_shard(path, expected_keys: Sequence[str], expected_size: int | None = None) -> Iterator[dict[str, bytes]]:
    """:func:`read_shard_members` compared with what the index says the shard holds, as the training loader reads.

    ``path``: a local file or a RemoteFile (:func:`shard_source`). The file's size is checked before anything is
    read, then every record's key, in order, and at the end the count: a shard cut at a record boundary, zeroed,
    holding a duplicate, foreign or missing record is a DataError naming the shard (and the key). Member sizes
    are checked before a member is read (see read_shard_members), so a hostile shard cannot make the reader
    allocate more than MAX_MEMBER_BYTES.
    """
    path = path if isinstance(path, RemoteFile) else Path(path)
    try:
        size = shard_sizes([path])[0]
    except OSError as exc:
        raise DataError(path, None, f"cannot read the shard ({exc.strerror or exc})") from None
    if size is None:
        raise DataError(path, None, "missing (hoidata verify checks the whole store)")
    if size == UNKNOWN_SIZE:  # a server that does not state it: the reader counts the bytes against the index
        size = expected_size if expected_size is not None else UNKNOWN_SIZE
    elif expected_size is not None and size != expected_size:
        raise DataError(path, None, f"{size} bytes, the index says {expected_size}: the shard is truncated, "
                                    "damaged or replaced (hoidata verify checks the whole store)")
    count = 0
    for members in read_shard_members(path, size):
        key = members[KEY]
        if count >= len(expected_keys) or key != expected_keys[count]:
            there = repr(expected_keys[count]) if count < len(expected_keys) else "no record"
            raise DataError(path, key, f"record {count} of the shard, the index has {there} there")
        count += 1
        yield members
    if count != len(expected_keys):
        raise DataError(path, None, f"{count} records, the index says {len(expected_keys)}: the shard is "
                                    "truncated or damaged (hoidata verify checks the whole store)")


def read_record(path, key: str, offset: int, length: int) -> dict[str, bytes]:
    """One record's raw members ({"__key__": key, member name: bytes}), read at its byte span in a shard
    (:func:`hoidata.store.spans.record_spans`): one ``pread`` of a local file, one range read of a RemoteFile.

    The span is parsed as the shard reader parses a whole shard (member names and sizes checked before a member is
    read); anything but exactly the record ``key`` there is a DataError naming the shard and the key.
    """
    if isinstance(path, RemoteFile):
        data = read_range(path, offset, length)
    else:
        path = Path(path)
        try:
            with open(path, "rb") as file:
                data = os.pread(file.fileno(), length, offset)
        except OSError as exc:
            raise DataError(path, key, f"cannot read the shard ({exc.strerror or exc})") from None
        if len(data) != length:
            raise DataError(path, key, f"{len(data)} bytes from byte {offset}, expected {length}: the shard is "
                                       "truncated or replaced (hoidata verify checks the whole store)")
    data += bytes(2 * tarfile.BLOCKSIZE)  # the end-of-archive blocks, so that the span reads as a whole tar
    records = list(_members(_ShardBytes(io.BytesIO(data), len(data)), path))
    if [r[KEY] for r in records] != [key]:
        raise DataError(path, key, f"bytes {offset}-{offset + length} hold {[r[KEY] for r in records]}, not this "
                                   "record: the shard was replaced (hoidata verify checks the whole store)")
    return records[0]


def _shard_paths(source) -> list[Path]:
    """A store folder (its index's shard list, else every shard-*.tar), one shard file, or a list of them."""
    if isinstance(source, (str, os.PathLike)):
        source = local_store(source, "reading every record")
        if not source.is_dir():
            return [source]
        if (source / INDEX_NAME).exists():
            return [source / s.name for s in open_index(source)[2]]
        return sorted(source.glob("shard-*.tar"))  # zero-padded numbers: name order is shard order
    return [Path(p) for p in source]


def iter_records(source) -> Iterator[dict]:
    """Decode every record of a store folder or of the given shard files, in order (see decode_record)."""
    for path in _shard_paths(source):
        for members in read_shard_members(path):
            yield decode_record(members, str(path))
