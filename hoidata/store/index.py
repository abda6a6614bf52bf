"""The store's zarr v3 index (``index.zarr``) and the shard entries it lists; :mod:`hoidata.store` builds on it.

Layout::

    index.zarr/        zarr v3 group (write_index):
      zarr.json          attributes: hoidata_index (layout version), schema_version, n_records,
                         shards [{number, name, count, sha256, size, first_key, last_key}],
                         label_columns, objects, skipped [{frame_id, reason, path}], config,
                         provenance {..., git commit as given, hoidata_version},
                         checksums {array path: array_digest} (a lost chunk would read as fill values)
      labels/<column>    one row per record in shard order, chunked along rows: key and other text
                         (variable-length UTF-8), shard int32, joints_3d (N, 21, 3) float32, ...
      objects/<name>/vertices (V, 3) float32, objects/<name>/faces (F, 3) int32

The index is written to ``index.zarr.tmp<pid>`` and renamed, so a half-written index is never taken for a
complete one. Every name here is re-exported by :mod:`hoidata.store`, which is where callers import them.
This module imports nothing from :mod:`hoidata.store` (no import cycle): the shard entry
(:class:`ShardInfo`) and :func:`to_jsonable`, which both modules use, live here.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata.errors import DataError, naming_os_errors
from hoidata.schema import META_FIELDS, META_TYPES, RECORD_KINDS, SCHEMA_VERSION, check_key
from hoidata.store.paths import INDEX_NAME, replaced_dir, resolve_store
from hoidata.store.remote import RemoteStore, remote_sizes, zarr_source

INDEX_FORMAT = 1  # layout version of index.zarr, recorded as the attribute "hoidata_index"
LABEL_CHUNK_ROWS = 32768
# columns every index holds besides "key" and "shard": name -> dtype; shapes from META_FIELDS
INDEX_LABELS = {name: np.float32 for name in ("joints_3d", "joints_2d", "K", "hand_root", "mano_pose", "mano_betas",
                                              "mano_transl", "object_pose", "hand_box", "object_box")}
INDEX_LABELS["object_id"] = np.int16
INDEX_LABELS["sample_index"] = np.int64  # the toolkit's id of a DexYCB sample (-1 elsewhere)
# label columns some record kind lacks: such rows hold NaN (sdf_counts: 0, 0, 0 -- the record has no SDF rows)
ABSENT_IN_SOME_KIND = frozenset(f for _, fields in RECORD_KINDS.values() for f in META_FIELDS if f not in fields)
_NODE_RE = re.compile(r"^(?!__)[A-Za-z0-9_\-.]+$")  # a zarr node name that is not "." or ".."


# --------------------------------------------------------------------------------------------------
# shared by the shard writer and the index


def to_jsonable(value, where, name: str):
    """numpy arrays/scalars and paths -> plain JSON values; anything else JSON cannot hold is an error."""
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise DataError(where, name, "dictionary keys must be strings")
        return {k: to_jsonable(v, where, f"{name}.{k}") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v, where, name) for v in value]
    if isinstance(value, np.ndarray):
        # numbers: tolist() gives plain values at once; only floats can be non-finite (the element path says which)
        fast = value.dtype.kind in "biu" or (value.dtype.kind == "f" and np.isfinite(value).all())
        return value.tolist() if fast else to_jsonable(value.tolist(), where, name)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if isinstance(value, float) and not np.isfinite(value):
        raise DataError(where, name, f"non-finite number {value} (JSON cannot hold it)")
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    raise DataError(where, name, f"cannot store a {type(value).__name__} as JSON")


def array_digest(arr: np.ndarray) -> str:
    """sha256 of an index array's values, the same for what write_index stores and what read_index gets back
    (text as NUL-separated UTF-8, numbers as their bytes, with dtype and shape)."""
    arr = np.asarray(arr)
    digest = hashlib.sha256()
    if arr.dtype.kind in "TUSO":
        digest.update(f"text{arr.shape}".encode())
        digest.update("\0".join(str(v) for v in arr.ravel().tolist()).encode("utf-8", "surrogatepass"))
    else:
        digest.update(f"{arr.dtype.str}{arr.shape}".encode())
        digest.update(np.ascontiguousarray(arr).tobytes())
    return digest.hexdigest()


def shard_name(number: int) -> str:
    """File name of shard ``number``: ``shard-%06d.tar``."""
    return f"shard-{number:06d}.tar"


@dataclass(frozen=True)
class ShardInfo:
    """One shard as written. A *planned* shard (for completed_shards) may leave sha256, size and keys None."""

    number: int
    name: str
    count: int
    sha256: str | None = None
    size: int | None = None
    first_key: str | None = None
    last_key: str | None = None

    def to_dict(self) -> dict:
        return {"number": self.number, "name": self.name, "count": self.count, "sha256": self.sha256,
                "size": self.size, "first_key": self.first_key, "last_key": self.last_key}

    @classmethod
    def from_dict(cls, value, where) -> ShardInfo:
        """Parse a written (complete) shard entry, checking every field."""
        if not isinstance(value, dict):
            raise DataError(where, "shards", f"expected an object per shard, got {type(value).__name__}")
        types = {"number": int, "name": str, "count": int, "sha256": str, "size": int,
                 "first_key": str, "last_key": str}
        empty = value.get("count") == 0  # every frame of the shard was skipped: no first or last key
        for name, want in types.items():
            if empty and name in ("first_key", "last_key") and value.get(name) is None:
                continue
            if not isinstance(value.get(name), want) or isinstance(value.get(name), bool):
                raise DataError(where, f"shards.{name}", f"expected {want.__name__}, got {value.get(name)!r}")
        info = cls(**{name: value.get(name) for name in types})
        consistent = info.name == shard_name(info.number) and info.count >= 0 and info.size >= 0
        if not consistent or not re.fullmatch(r"[0-9a-f]{64}", info.sha256):
            raise DataError(where, f"shards.{info.name}", f"inconsistent entry {value}")
        return info


# --------------------------------------------------------------------------------------------------
# writing


def _absent_value(name: str, shape):
    """What a column holds for a record whose kind lacks the field: NaN, or no SDF rows for sdf_counts."""
    return np.zeros(shape, np.int64) if name == "sdf_counts" else np.full(shape, np.nan)


def index_labels(metas: Sequence[dict]) -> dict[str, np.ndarray]:
    """Per-record meta dicts -> the label columns for write_index: every META_FIELDS field but the
    schema version and the free-form source, shaped fields stacked (float32; sdf_counts int32). A field a
    record's kind lacks (schema.RECORD_KINDS) is NaN in its row (sdf_counts 0, 0, 0)."""
    columns = {}
    for name, (shape, _) in META_FIELDS.items():
        if name in ("schema_version", "source"):
            continue
        values = [meta[name] if name in meta else _absent_value(name, shape) for meta in metas]
        if META_TYPES.get(name) is str:
            columns[name] = np.array(values, dtype=np.dtypes.StringDType())
        elif shape is None:
            columns[name] = np.array(values, dtype=INDEX_LABELS.get(name, None))
        else:
            dtype = np.int32 if name == "sdf_counts" else INDEX_LABELS.get(name, np.float32)
            columns[name] = np.array(values, dtype=dtype).reshape((len(values), *shape))
    return columns


def _column(name: str, values, n: int, where) -> np.ndarray:
    """One label column, checked: n rows; strings as variable-length UTF-8; required ones cast and shaped."""
    if not re.fullmatch(r"[A-Za-z0-9_]+", name) or name == "shard":
        raise DataError(where, f"labels.{name}", "bad or reserved column name")
    arr = np.asarray(values)
    if arr.dtype.kind in "OUT":
        if not all(isinstance(v, str) for v in arr.ravel().tolist()):
            raise DataError(where, f"labels.{name}", "a text column must hold only strings")
        # StringDType, not '<U': zarr 3.1 stores '<U' as fixed-length UTF-32, a type without a v3 spec
        arr = arr.astype(np.dtypes.StringDType())
    elif arr.dtype.kind not in "biuf":
        raise DataError(where, f"labels.{name}", f"unsupported dtype {arr.dtype}")
    if name in INDEX_LABELS:
        shape, dtype = (n, *(META_FIELDS[name][0] or ())), np.dtype(INDEX_LABELS[name])
        if arr.shape != shape or arr.dtype.kind not in "biuf":
            raise DataError(where, f"labels.{name}", f"expected numbers of shape {shape}, got {arr.dtype} {arr.shape}")
        cast = arr.astype(dtype)
        if dtype.kind in "iu" and not np.array_equal(cast, arr):
            raise DataError(where, f"labels.{name}", f"values do not fit {dtype.name}")
        arr = cast
    if arr.ndim == 0 or len(arr) != n:
        raise DataError(where, f"labels.{name}", f"expected {n} rows, got shape {arr.shape}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all() and (name not in ABSENT_IN_SOME_KIND or np.isinf(arr).any()):
        raise DataError(where, f"labels.{name}", "non-finite values")
    return arr


def _check_kinds(columns: dict[str, np.ndarray], where) -> None:
    """The kind column names record kinds; a row's label is NaN exactly where its kind lacks the field."""
    kinds = columns["kind"]
    unknown = sorted(set(kinds.tolist()) - set(RECORD_KINDS))
    if unknown:
        raise DataError(where, "labels.kind", f"unknown record kinds {unknown}; expected {sorted(RECORD_KINDS)}")
    for name, arr in columns.items():
        if name not in ABSENT_IN_SOME_KIND or arr.dtype.kind != "f":
            continue
        lacking = np.array([name not in RECORD_KINDS[k][1] for k in kinds.tolist()], bool)
        nan = np.isnan(arr.reshape(len(arr), -1))
        if nan[lacking].size and not nan[lacking].all() or nan[~lacking].any():
            raise DataError(where, f"labels.{name}", "NaN only, and only, in rows whose record kind lacks the field")


def _check_keys(keys: list[str], n: int, where) -> None:
    """The key column: n unique record keys (schema.check_key)."""
    try:
        for key in keys:
            check_key(key)
    except ValueError:
        raise DataError(where, "labels.key", "keys must be unique record keys") from None
    if len(set(keys)) != n:
        raise DataError(where, "labels.key", "keys must be unique record keys")


def _check_index_inputs(shards_info, labels: dict, where) -> tuple[list[ShardInfo], dict[str, np.ndarray]]:
    """Shards complete and numbered 0..S-1; labels one row per record; keys unique and matching the shards."""
    shards = [ShardInfo.from_dict(s.to_dict() if isinstance(s, ShardInfo) else s, where) for s in shards_info]
    if [s.number for s in shards] != list(range(len(shards))):
        raise DataError(where, "shards", f"expected shards numbered 0..{len(shards) - 1} in order")
    n = sum(s.count for s in shards)
    missing = sorted({"key", "kind", *INDEX_LABELS} - set(labels))
    if missing:
        raise DataError(where, "labels", f"missing columns {missing}")
    columns = {name: _column(name, values, n, where) for name, values in labels.items()}
    _check_kinds(columns, where)
    keys = columns["key"].tolist()
    _check_keys(keys, n, where)
    start = 0
    for s in shards:
        if s.count and (keys[start], keys[start + s.count - 1]) != (s.first_key, s.last_key):
            raise DataError(where, f"shards.{s.name}", "first/last key differ from the key column")
        start += s.count
    columns["shard"] = np.repeat(np.arange(len(shards), dtype=np.int32), [s.count for s in shards])
    return shards, columns


def _skip_entry(skip, where) -> dict:
    """A Skip (hoidata.datasets.frame), a (frame_id, reason, path) tuple or a dict -> a plain dict; a known
    toolkit ``sample_index`` (>= 0) of the skipped frame is kept."""
    if isinstance(skip, dict):
        values = (skip.get("frame_id"), skip.get("reason"), skip.get("path", ""))
        sample = skip.get("sample_index", -1)
    elif hasattr(skip, "frame_id"):
        values = (skip.frame_id, skip.reason, getattr(skip, "path", ""))
        sample = getattr(skip, "sample_index", -1)
    else:
        values, sample = tuple(skip), -1
    if len(values) != 3:
        raise DataError(where, "skipped", f"expected (frame_id, reason, path), got {skip!r}")
    if not isinstance(sample, (int, np.integer)) or isinstance(sample, bool):
        raise DataError(where, "skipped", f"sample_index must be an integer, got {sample!r}")
    entry = {"frame_id": str(values[0]), "reason": str(values[1]), "path": os.fspath(values[2] or "")}
    return {**entry, "sample_index": int(sample)} if sample >= 0 else entry


def _write_meshes(group, object_meshes: dict, where) -> dict[str, str]:
    """Each object's mesh, checked, as objects/<name>/vertices (float32) and objects/<name>/faces (int32);
    returns their array_digest checksums."""
    checksums = {}
    for name, (vertices, faces) in object_meshes.items():
        vertices, faces = np.asarray(vertices, np.float32), np.asarray(faces)
        if not _NODE_RE.match(name) or name in (".", ".."):
            raise DataError(where, f"objects.{name}", "object names may hold letters, digits, '_', '-' and '.'")
        bad_faces = faces.dtype.kind not in "iu" or faces.size and (faces.min() < 0 or faces.max() >= len(vertices))
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or bad_faces:
            raise DataError(where, f"objects.{name}", "expected (V, 3) vertices and (F, 3) faces indexing them")
        faces = faces.astype(np.int32)
        group.create_array(f"objects/{name}/vertices", data=vertices)
        group.create_array(f"objects/{name}/faces", data=faces)
        checksums[f"objects/{name}/vertices"], checksums[f"objects/{name}/faces"] = array_digest(vertices), array_digest(faces)
    return checksums


def write_index(store_dir, shards_info: Sequence[ShardInfo | dict], labels: dict[str, np.ndarray],
                object_meshes: dict[str, tuple[np.ndarray, np.ndarray]], skipped: Sequence, config: dict,
                provenance: dict) -> Path:
    """Write ``store_dir/index.zarr`` (see the module docstring for the layout) and return its path.

    labels: one row per record in shard order: "key" plus every INDEX_LABELS column, any further numeric
    or text columns (index_labels builds them from meta dicts). The "shard" column is derived here.
    provenance gets "hoidata_version"; put the git commit in it. The index is written to
    ``index.zarr.tmp<pid>`` and renamed, so a half-written index is never taken for a complete one.
    """
    import zarr  # optional dependency (the "store" extra): only index users need it

    from hoidata import __version__

    store_dir = Path(store_dir)
    where = store_dir / INDEX_NAME
    shards, columns = _check_index_inputs(shards_info, labels, where)
    attrs = {"hoidata_index": INDEX_FORMAT, "schema_version": SCHEMA_VERSION, "n_records": len(columns["key"]),
             "shards": [s.to_dict() for s in shards], "label_columns": sorted(columns),
             "objects": sorted(object_meshes), "skipped": [_skip_entry(s, where) for s in skipped],
             "config": to_jsonable(config, where, "config"),
             "provenance": to_jsonable({**provenance, "hoidata_version": __version__}, where, "provenance")}
    with naming_os_errors(where), replaced_dir(where) as tmp:  # zarr's write errors name no file
        group = zarr.open_group(tmp, mode="w", zarr_format=3)
        checksums = {}
        for name, arr in columns.items():
            rows = max(1, min(len(arr), LABEL_CHUNK_ROWS))
            group.create_array(f"labels/{name}", data=arr, chunks=(rows, *arr.shape[1:]))
            checksums[f"labels/{name}"] = array_digest(arr)
        checksums.update(_write_meshes(group, object_meshes, where))
        group.attrs.update({**attrs, "checksums": checksums})
    return where


# --------------------------------------------------------------------------------------------------
# reading


@dataclass
class StoreIndex:
    """What index.zarr holds, loaded (``path``: the index folder, or its RemoteFile for a remote store). labels: every column by name (text as numpy str), with "key" and
    "shard" (the shard number of each row); objects: name -> (vertices (V, 3) float32, faces (F, 3) int32)."""

    path: Path
    keys: list[str]
    labels: dict[str, np.ndarray]
    shards: list[ShardInfo]
    objects: dict[str, tuple[np.ndarray, np.ndarray]]
    skipped: list[dict]
    config: dict
    provenance: dict
    schema_version: int

    def shard_rows(self, number: int) -> slice:
        """The rows of shard ``number`` in the label columns."""
        start = sum(s.count for s in self.shards[:number])
        return slice(start, start + self.shards[number].count)


def open_index(store_dir):
    """Open index.zarr and check its attributes; returns (group, attrs, shards, path)."""
    import zarr

    location = resolve_store(store_dir)
    remote = isinstance(location, RemoteStore)  # read through zarr's fsspec store; errors name the URL
    path = location.file(INDEX_NAME) if remote else location / INDEX_NAME
    if not (remote_sizes([location.file(f"{INDEX_NAME}/zarr.json")])[0] is not None if remote
            else (path / "zarr.json").is_file()):
        raise DataError(path, None, "missing (the build did not finish, or this is not a store folder)")
    try:
        url, options = zarr_source(path) if remote else (path, None)  # a URL's query goes as a request parameter
        group = zarr.open_group(url, mode="r", zarr_format=3, storage_options=options)
        attrs = group.attrs.asdict()
    except Exception as exc:  # zarr raises many types for a damaged store; all mean the same here
        raise DataError(path, None, f"not a readable zarr v3 group ({type(exc).__name__}: {exc})") from None
    if attrs.get("hoidata_index") != INDEX_FORMAT:
        raise DataError(path, "hoidata_index", f"{attrs.get('hoidata_index')!r}, this reader knows {INDEX_FORMAT}")
    if attrs.get("schema_version") != SCHEMA_VERSION:
        raise DataError(path, "schema_version", f"{attrs.get('schema_version')!r}: the store's records are of another "
                                                f"schema than this reader's ({SCHEMA_VERSION}); rebuild it into a new folder")
    types = {"schema_version": int, "n_records": int, "shards": list, "label_columns": list, "objects": list,
             "skipped": list, "config": dict, "provenance": dict}
    for name, want in types.items():
        if not isinstance(attrs.get(name), want):
            raise DataError(path, name, f"expected {want.__name__}, got {type(attrs.get(name)).__name__}")
    shards = [ShardInfo.from_dict(s, path) for s in attrs["shards"]]
    if [s.number for s in shards] != list(range(len(shards))) or sum(s.count for s in shards) != attrs["n_records"]:
        raise DataError(path, "shards", "shards must be numbered 0..S-1 and their counts sum to n_records")
    return group, attrs, shards, path


def _read_array(group, name: str, path, checksums: dict | None = None) -> np.ndarray:
    """One array of the index, read whole and compared with its checksum (indexes written since checksums
    exist); variable-length text comes back as numpy '<U'. zarr returns fill values for a chunk file that
    is missing, so without the checksum a lost chunk would read as zeros."""
    try:
        arr = group[name][...]
    except Exception as exc:
        raise DataError(path, name, f"unreadable ({type(exc).__name__}: {exc})") from None
    # zarr returns variable-length text as numpy's StringDType; plain '<U' is what the rest of numpy expects
    # (and numpy 2.4 refuses astype(str) from StringDType, hence the list)
    arr = np.array(arr.tolist(), dtype=str).reshape(arr.shape) if arr.dtype.kind == "T" else arr
    if checksums is not None:
        if checksums.get(name) != array_digest(arr):
            raise DataError(path, name, "does not match its checksum: a chunk file is missing or damaged "
                                        "(rerunning the build into this folder rewrites the index)")
    return arr


def _read_labels(group, attrs: dict, shards: list[ShardInfo], path) -> dict[str, np.ndarray]:
    """Every label column, checked: required columns present and shaped, n rows each, shard column consistent."""
    n = attrs["n_records"]
    sums = attrs.get("checksums")
    labels = {name: _read_array(group, f"labels/{name}", path, sums) for name in attrs["label_columns"]}
    for name in ("key", "shard", "kind", *INDEX_LABELS):
        if name not in labels:
            raise DataError(path, f"labels/{name}", "missing column")
        want = (n, *(META_FIELDS[name][0] or ())) if name in INDEX_LABELS else (n,)
        if labels[name].shape != want:
            raise DataError(path, f"labels/{name}", f"expected shape {want}, got {labels[name].shape}")
    if any(arr.ndim == 0 or len(arr) != n for arr in labels.values()):
        raise DataError(path, "labels", f"every column must have {n} rows")
    expected_shard = np.repeat(np.arange(len(shards)), [s.count for s in shards])
    if not np.array_equal(labels["shard"], expected_shard):
        raise DataError(path, "labels/shard", "does not match the shard counts")
    if len(set(labels["key"].tolist())) != n:
        raise DataError(path, "labels/key", "keys are not unique")
    return labels


def _read_meshes(group, names: list, path, attrs: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The object meshes, checked: (V, 3) vertices and (F, 3) integer faces indexing them."""
    objects, sums = {}, attrs.get("checksums")
    for name in names:
        vertices = _read_array(group, f"objects/{name}/vertices", path, sums)
        faces = _read_array(group, f"objects/{name}/faces", path, sums)
        bad_faces = faces.dtype.kind not in "iu" or faces.size and (faces.min() < 0 or faces.max() >= len(vertices))
        if vertices.ndim != 2 or vertices.shape[1:] != (3,) or faces.ndim != 2 or faces.shape[1:] != (3,) or bad_faces:
            raise DataError(path, f"objects/{name}", f"not a mesh: vertices {vertices.shape}, faces {faces.shape}")
        objects[name] = (vertices, faces)
    return objects


def read_index(store_dir) -> StoreIndex:
    """Load and check ``store_dir/index.zarr``; a missing or damaged index is a DataError naming it."""
    group, attrs, shards, path = open_index(store_dir)
    labels = _read_labels(group, attrs, shards, path)
    objects = _read_meshes(group, attrs["objects"], path, attrs)
    return StoreIndex(path, labels["key"].tolist(), labels, shards, objects, attrs["skipped"], attrs["config"],
                      attrs["provenance"], attrs["schema_version"])
