"""The store: records as deterministic WebDataset tar shards plus a zarr v3 index, and their readers.

A store folder holds::

    shard-000000.tar   records in order, each record's members in schema order (see hoidata.schema)
    shard-000000.json  sidecar: the shard's ShardInfo, written right after the shard appears (resume)
    ...
    index.zarr/        zarr v3 group (write_index): labels, shard list, object meshes, provenance;
                       its layout and code live in :mod:`hoidata.store_index`, re-exported here

A build plans its records as fixed runs of ``records_per_shard``; after an interruption it asks
:func:`completed_shards` which shards are already good, rewrites only the others with
:func:`write_shard` (or streams a straight run through :class:`ShardWriter`) and ends with
:func:`write_index`. Nothing half-written ever carries a final name: shards are written to
``<name>.tmp`` and renamed, the index to ``index.zarr.tmp``.

Readers trust nothing: member names, sizes, decoded shapes and dtypes and every meta field are checked,
and a problem is a :class:`~hoidata.errors.DataError` naming the shard file and the record key.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tarfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np

from hoidata.errors import DataError
from hoidata.schema import (
    HEATMAP,
    IMG,
    MEMBERS,
    META,
    META_FIELDS,
    META_TYPES,
    NO_PART,
    SCHEMA_VERSION,
    SDF,
    SDF_COLUMNS,
    SDF_DTYPE,
    SEG,
    check_key,
)

# the index half of the store, re-exported: callers use store.write_index, store.read_index, ...
from hoidata.store_index import (  # noqa: F401
    INDEX_FORMAT,
    INDEX_LABELS,
    INDEX_NAME,
    LABEL_CHUNK_ROWS,
    ShardInfo,
    StoreIndex,
    _open_index,
    index_labels,
    read_index,
    shard_name,
    to_jsonable,
    write_index,
)

JPEG_QUALITY = 95
PNG_COMPRESSION = 3  # pinned so the bytes do not depend on OpenCV's default
MAX_MEMBER_BYTES = 64 << 20  # refuse absurd members before reading them into memory
MAX_IMAGE_SIDE = 4096  # refuse absurd image headers before decoding (decompression bombs)
KEY = "__key__"  # the record key in decoded records, as WebDataset names it
N_PARTS = 16  # hand part labels 0..15 in sdf.npy's last column
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------------------------------
# records


def _check_key(key, where) -> None:
    """schema.check_key, as a DataError naming ``where`` and the field "key"."""
    try:
        check_key(key)
    except ValueError as exc:
        raise DataError(where, "key", str(exc)) from None


def _is_key(key) -> bool:
    """Whether ``key`` passes schema.check_key."""
    try:
        check_key(key)
    except ValueError:
        return False
    return True


def _check_images(where, key, img, seg, hm) -> None:
    """img (S, S, 3) uint8; seg and hm (S // 2, S // 2) uint8."""
    if not (isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.ndim == 3
            and img.shape[2] == 3 and img.shape[0] == img.shape[1] >= 2):
        raise DataError(where, _field(key, IMG), f"expected square (S, S, 3) uint8, got {_describe(img)}")
    half = img.shape[0] // 2
    for member, arr in ((SEG, seg), (HEATMAP, hm)):
        if not (isinstance(arr, np.ndarray) and arr.dtype == np.uint8 and arr.shape == (half, half)):
            raise DataError(where, _field(key, member), f"expected ({half}, {half}) uint8, got {_describe(arr)}")


def _check_sdf(where, key, sdf) -> None:
    """int16 (N, 6) with part labels in -1..15."""
    width = len(SDF_COLUMNS)
    if not (isinstance(sdf, np.ndarray) and sdf.dtype == SDF_DTYPE and sdf.ndim == 2 and sdf.shape[1] == width):
        want = f"{np.dtype(SDF_DTYPE).name} (N, {width})"
        raise DataError(where, _field(key, SDF), f"expected {want}, got {_describe(sdf)}")
    part = sdf[:, -1]
    if part.size and (part.min() < NO_PART or part.max() >= N_PARTS):
        raise DataError(where, _field(key, SDF), f"part labels must lie in {NO_PART}..{N_PARTS - 1}")


def _field(key, member: str) -> str:
    """The tar member name ``<key>.<member>`` an error refers to (just the member when the key is unknown)."""
    return member if key is None else f"{key}.{member}"


def _describe(arr) -> str:
    return f"{arr.dtype} {arr.shape}" if isinstance(arr, np.ndarray) else type(arr).__name__


def _check_meta(meta, where, key, n_sdf: int) -> dict:
    """Check a JSON-level meta dict against META_FIELDS; return it with shaped fields as numpy arrays."""
    name = _field(key, META)
    if not isinstance(meta, dict):
        raise DataError(where, name, f"expected a JSON object, got {type(meta).__name__}")
    # the version first: a record of another schema version differs in its fields too
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION or isinstance(version, bool):
        raise DataError(where, name, f"'schema_version': {version!r}, this reader knows {SCHEMA_VERSION}")
    missing, extra = sorted(set(META_FIELDS) - set(meta)), sorted(set(meta) - set(META_FIELDS))
    if missing or extra:
        raise DataError(where, name, f"missing fields {missing}, unexpected fields {extra}")
    out = {}
    for field_name, (shape, _) in META_FIELDS.items():
        value = meta[field_name]
        if shape is None:
            want = META_TYPES.get(field_name)
            # bool is an int in Python; a flag where a number belongs (or back) is still wrong
            if want is not None and (not isinstance(value, want) or (want is int and isinstance(value, bool))):
                raise DataError(where, name, f"{field_name!r}: expected {want.__name__}, got {type(value).__name__}")
            out[field_name] = value
            continue
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise DataError(where, name, f"{field_name!r}: expected numbers of shape {shape}") from None
        if arr.shape != shape or not np.isfinite(arr).all():
            raise DataError(where, name, f"{field_name!r}: expected finite numbers of shape {shape}, got {arr.shape}")
        out[field_name] = arr
    if key is not None and out["key"] != key:
        raise DataError(where, name, f"'key': {out['key']!r} differs from the record key")
    counts = out["sdf_counts"]
    if (counts < 0).any() or (counts != np.round(counts)).any() or counts.sum() != n_sdf:
        raise DataError(where, name, f"'sdf_counts': {counts.tolist()} must be counts summing to {n_sdf} rows")
    out["sdf_counts"] = counts.astype(np.int64)
    return out


def encode_record(key: str, img: np.ndarray, seg: np.ndarray, heatmap: np.ndarray, sdf: np.ndarray,
                  meta: dict) -> dict[str, bytes]:
    """Arrays and labels -> {member name: bytes}; the same inputs always give the same bytes.

    img is RGB. meta must hold every META_FIELDS field (numpy values allowed); it is checked exactly as a
    reader would check it, so a record that encodes also decodes.
    """
    _check_key(key, None)
    _check_images(None, key, img, seg, heatmap)
    _check_sdf(None, key, sdf)
    plain = to_jsonable(meta, None, _field(key, META))
    _check_meta(plain, None, key, len(sdf))
    members = {IMG: _imencode(".jpg", np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])}
    for member, arr in ((SEG, seg), (HEATMAP, heatmap)):
        members[member] = _imencode(".png", np.ascontiguousarray(arr), [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(sdf), allow_pickle=False)  # C order, so the header is always the same
    members[SDF] = buf.getvalue()
    # sorted keys and fixed separators: byte-identical JSON for equal labels
    text = json.dumps(plain, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    members[META] = text.encode()
    return {member: members[member] for member in MEMBERS}


def _imencode(ext: str, arr: np.ndarray, params: list[int]) -> bytes:
    ok, buf = cv2.imencode(ext, arr, params)
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {arr.shape} {arr.dtype} image as {ext}")
    return buf.tobytes()


def _image_size(data: bytes, member: str) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR or a JPEG's SOF header without decoding; None if not found."""
    if member != IMG:
        if data[:8] == _PNG_MAGIC and data[12:16] == b"IHDR" and len(data) >= 24:
            return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        return None
    pos = 2 if data[:2] == b"\xff\xd8" else len(data)
    while pos + 9 <= len(data) and data[pos] == 0xFF:
        marker, length = data[pos + 1], int.from_bytes(data[pos + 2:pos + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame, not DHT/JPG/DAC
            return int.from_bytes(data[pos + 7:pos + 9], "big"), int.from_bytes(data[pos + 5:pos + 7], "big")
        pos += 2 + length
    return None


def _decode_image(data: bytes, where, key, member: str) -> np.ndarray:
    """JPEG -> RGB (H, W, 3) uint8, PNG -> (H, W) uint8; the header is checked before decoding."""
    size = _image_size(data, member)
    kind = "JPEG" if member == IMG else "8-bit grey PNG"
    if size is None or not 0 < max(size) <= MAX_IMAGE_SIDE:
        raise DataError(where, _field(key, member), f"not a {kind} of at most {MAX_IMAGE_SIDE} px (header: {size})")
    flag = cv2.IMREAD_COLOR if member == IMG else cv2.IMREAD_UNCHANGED
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    if arr is None:
        raise DataError(where, _field(key, member), f"OpenCV cannot decode this {kind}")
    return np.ascontiguousarray(arr[..., ::-1]) if member == IMG else arr


def _decode_sdf(data: bytes, where, key) -> np.ndarray:
    try:
        return np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:  # allow_pickle=False: an object array is refused here
        raise DataError(where, _field(key, SDF), f"not a readable .npy array ({exc})") from None


def decode_record(members: dict[str, bytes], where: str) -> dict:
    """{member name: bytes} (plus an optional ``__key__``, as WebDataset samples have) -> decoded record.

    Returns {"__key__": key, IMG: RGB uint8, SEG: uint8, HEATMAP: uint8, SDF: int16 (N, 6), META: dict}
    with META's shaped fields as numpy arrays. Other ``__*__`` entries (``__url__``...) are ignored.
    Any deviation from the schema raises DataError naming ``where`` (the shard) and the key/member.
    """
    key = members.get(KEY)
    if key is not None and not isinstance(key, str):
        raise DataError(where, KEY, f"expected a string, got {type(key).__name__}")
    given = {name for name in members if not (name.startswith("__") and name.endswith("__"))}
    if given != set(MEMBERS):
        raise DataError(where, key, f"members {sorted(given)}, expected exactly {list(MEMBERS)}")
    for name in MEMBERS:
        if not isinstance(members[name], (bytes, bytearray, memoryview)) or len(members[name]) > MAX_MEMBER_BYTES:
            raise DataError(where, _field(key, name), f"expected at most {MAX_MEMBER_BYTES} bytes")
    img = _decode_image(members[IMG], where, key, IMG)
    seg = _decode_image(members[SEG], where, key, SEG)
    hm = _decode_image(members[HEATMAP], where, key, HEATMAP)
    _check_images(where, key, img, seg, hm)
    sdf = _decode_sdf(members[SDF], where, key)
    _check_sdf(where, key, sdf)
    try:
        plain = json.loads(bytes(members[META]).decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:  # RecursionError: absurdly nested JSON
        raise DataError(where, _field(key, META), f"not UTF-8 JSON ({type(exc).__name__})") from None
    meta = _check_meta(plain, where, key, len(sdf))
    return {KEY: meta["key"], IMG: img, SEG: seg, HEATMAP: hm, SDF: sdf, META: meta}


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
        self.tmp = self.path.with_name(self.path.name + ".tmp")
        self._file = open(self.tmp, "wb")
        self._hash = _HashingWriter(self._file)
        self._tar = tarfile.open(fileobj=self._hash, mode="w", format=tarfile.PAX_FORMAT)
        self.keys: list[str] = []

    def add(self, key: str, members: dict[str, bytes]) -> None:
        _check_members_to_write(key, members)
        for member in MEMBERS:  # schema order, whatever order the dict has
            data = bytes(members[member])
            info = tarfile.TarInfo(f"{key}.{member}")
            info.size, info.mtime, info.mode, info.type = len(data), 0, 0o644, tarfile.REGTYPE
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            self._tar.addfile(info, io.BytesIO(data))
        self.keys.append(key)

    def finish(self) -> ShardInfo:
        self._tar.close()  # end-of-archive blocks and padding to the 10 KiB record size
        self._file.flush()
        os.fsync(self._file.fileno())  # the content is on disk before the name says "complete"
        self._file.close()
        os.replace(self.tmp, self.path)
        info = ShardInfo(self.number, self.path.name, len(self.keys), self._hash.sha256.hexdigest(),
                         self._hash.size, self.keys[0], self.keys[-1])
        _write_json_atomic(self.path.with_name(sidecar_name(self.number)), info.to_dict())
        return info

    def abort(self) -> None:
        self._file.close()
        self.tmp.unlink(missing_ok=True)


def _check_members_to_write(key: str, members: dict[str, bytes]) -> None:
    """A record to write: a valid key and bytes for exactly the schema's members."""
    _check_key(key, None)
    if set(members) != set(MEMBERS) or not all(isinstance(v, (bytes, bytearray, memoryview)) for v in members.values()):
        raise DataError(None, key, f"expected bytes for exactly {list(MEMBERS)}, got {sorted(members)}")


def _write_json_atomic(path: Path, value) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(value, sort_keys=True, indent=1) + "\n")
    os.replace(tmp, path)


def write_shard(store_dir, number: int, records: Iterable[tuple[str, dict[str, bytes]]]) -> ShardInfo:
    """Write one complete shard from (key, members) pairs: the unit of work of a resumable build."""
    store_dir = Path(store_dir)
    store_dir.mkdir(parents=True, exist_ok=True)
    shard = _OpenShard(store_dir, number)
    try:
        for key, members in records:
            shard.add(key, members)
        if not shard.keys:
            raise ValueError(f"shard {number}: no records")
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


def _check_tar_end(file, offset: int, path) -> None:
    """tarfile stops silently at a damaged header: only zeros (>= 2 blocks) may follow the last member."""
    size = os.fstat(file.fileno()).st_size
    file.seek(offset)
    clean = size - offset >= 2 * tarfile.BLOCKSIZE
    while clean and (chunk := file.read(1 << 20)):
        clean = not chunk.strip(b"\0")
    if not clean:
        raise DataError(path, None, f"the tar stream breaks off at byte {offset} of {size}: truncated or corrupt")


def read_shard_members(path) -> Iterator[dict[str, bytes]]:
    """Raw records of one shard, in order: {"__key__": key, member name: bytes}, names not yet checked."""
    with open(path, "rb") as file:
        try:
            tar = tarfile.open(fileobj=file, mode="r:")  # "r:" -- never a compressed stream
        except tarfile.TarError as exc:
            raise DataError(path, None, f"not a tar file ({exc})") from None
        record, seen = None, set()
        try:
            for info in tar:
                key, _, member = info.name.partition(".")
                if not info.isreg() or not _is_key(key) or not member or info.size > MAX_MEMBER_BYTES:
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
        _check_tar_end(file, tar.offset, path)
        if record is not None:
            yield record


def _shard_paths(source) -> list[Path]:
    """A store folder (its index's shard list, else every shard-*.tar), one shard file, or a list of them."""
    if isinstance(source, (str, os.PathLike)):
        source = Path(source)
        if not source.is_dir():
            return [source]
        if (source / INDEX_NAME).exists():
            return [source / s.name for s in _open_index(source)[2]]
        return sorted(source.glob("shard-*.tar"))  # zero-padded numbers: name order is shard order
    return [Path(p) for p in source]


def iter_records(source) -> Iterator[dict]:
    """Decode every record of a store folder or of the given shard files, in order (see decode_record)."""
    for path in _shard_paths(source):
        for members in read_shard_members(path):
            yield decode_record(members, str(path))


# Verification and resume live in store_verify; imported last because they build on everything above.
from hoidata.store_verify import (  # noqa: E402,F401
    MAX_LABEL_PROBLEMS,
    VerifyReport,
    completed_shards,
    file_digest,
    read_sidecar,
    verify_store,
)
