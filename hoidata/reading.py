"""The one guarded door for every file a command reads: bytes bounded in size, text decoded strictly, JSON bounded
in nesting, zip / npz / tar members read under one guard. Every failure is one DataError naming the file (and the
member and field); values are checked against declared shapes by :mod:`hoidata.shapes`, images and meshes decoded
by :mod:`hoidata.reading_media`. ``tests/test_reading_corpus.py`` feeds every reader of the project one corpus of
damaged files; ``tests/test_reading.py`` fails on a file read that bypasses this door (docs/reliability.md, section 22).
"""

from __future__ import annotations

import io
import os
import re
import stat
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hoidata.errors import DataError, decoding

MAX_BYTES = 4 << 30  # any one file or member: beyond this it is refused before it is read
MAX_JSON_DEPTH = 64  # nesting of JSON arrays and objects; the deepest file of any format here nests 6
_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')  # a JSON string, escapes included
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")
_OPEN = np.zeros(256, np.int8)
_OPEN[[ord("["), ord("{")]], _OPEN[[ord("]"), ord("}")]] = 1, -1
_SCAN_BLOCK = 1 << 24


def _size_problem(size: int, limit: int, what: str) -> str:
    return f"{size:,} bytes, more than a {what} may hold ({limit:,})"


def file_size(path, what: str = "file", max_bytes: int = MAX_BYTES) -> int:
    """The size of the file at ``path``; missing, a folder or over ``max_bytes`` is a DataError naming it."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise DataError(path, None, f"{what} not found") from None
    except OSError as exc:
        raise DataError(path, None, f"cannot read the {what} ({exc.strerror or exc})") from None
    if stat.S_ISDIR(info.st_mode):
        raise DataError(path, None, f"a folder, not a {what}")
    if info.st_size > max_bytes:
        raise DataError(path, None, _size_problem(info.st_size, max_bytes, what))
    return info.st_size


def read_bytes(path, what: str = "file", max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of the file at ``path``; missing, a folder, unreadable or over ``max_bytes`` is a DataError
    naming it and ``what`` it should be."""
    file_size(path, what, max_bytes)
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)  # a file that grows (or a pipe) is bounded too
    except FileNotFoundError:
        raise DataError(path, None, f"{what} not found") from None
    except OSError as exc:
        raise DataError(path, None, f"cannot read the {what} ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise DataError(path, None, _size_problem(len(data), max_bytes, what))
    return data


def file_digest(path, what: str = "file") -> tuple[int, str]:
    """(size in bytes, sha256 hex) of the file at ``path``, read in 1 MiB blocks (never whole into memory)."""
    import hashlib

    file_size(path, what, 1 << 62)
    sha, size = hashlib.sha256(), 0
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                sha.update(chunk)
                size += len(chunk)
    except OSError as exc:
        raise DataError(path, None, f"cannot read the {what} ({exc.strerror or exc})") from None
    return size, sha.hexdigest()


def text(data: bytes, path, field: str | None = None, what: str = "text") -> str:
    """``data`` decoded as UTF-8, strictly: a byte that is not UTF-8 is a DataError naming the file, the field and
    where the byte is."""
    try:
        return bytes(data).decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise DataError(path, field, f"not UTF-8 {what}: byte 0x{data[exc.start]:02x} at offset {exc.start} "
                                     f"(line {line})") from None


def read_text(path, what: str = "text file", max_bytes: int = MAX_BYTES) -> str:
    """The text of a UTF-8 file (see :func:`read_bytes` and :func:`text`)."""
    return text(read_bytes(path, what, max_bytes), path, None, what)


def read_lines(path, what: str = "list", max_bytes: int = MAX_BYTES) -> list[str]:
    """The stripped, non-empty lines of a UTF-8 text list, in file order (a list of ids, one a line)."""
    return [line.strip() for line in read_text(path, what, max_bytes).splitlines() if line.strip()]


def too_deep(data: bytes, limit: int = MAX_JSON_DEPTH) -> bool:
    """Whether JSON ``data`` nests its arrays and objects more than ``limit`` deep (brackets inside strings not
    counted): a cheap scan that runs before the parser, whose recursion it guards. A file with no more than
    ``limit`` opening brackets in all is not scanned."""
    if data.count(b"[") + data.count(b"{") <= limit:
        return False
    if b'"' in data:
        data = _STRING.sub(b"", data)
    brackets = np.frombuffer(data.translate(None, _NOT_BRACKETS), np.uint8)
    depth = 0
    for start in range(0, len(brackets), _SCAN_BLOCK):
        steps = np.cumsum(_OPEN[brackets[start:start + _SCAN_BLOCK]], dtype=np.int64) + depth
        if int(steps.max()) > limit:
            return True
        depth = int(steps[-1])
    return False


def numbers_only(data: bytes) -> bool:
    """Whether JSON ``data`` holds nothing but numbers, arrays and objects without keys: no string, true, false or
    null anywhere. Then every leaf of its parsed value is a number (a fast path for large numeric files)."""
    return not any(token in data for token in (b'"', b"true", b"false", b"null"))


def parse_json(data: bytes | str, path, field: str | None = None, what: str = "JSON",
               max_depth: int = MAX_JSON_DEPTH):
    """The value of JSON ``data`` (bytes decoded strictly as UTF-8; ``what`` names it in that error); not UTF-8,
    not JSON or nested deeper than ``max_depth`` is a DataError naming the file and field. The caller checks the
    value's shape (:func:`hoidata.shapes.check`)."""
    import json

    raw = data if isinstance(data, (bytes, bytearray, memoryview)) else None
    source = text(raw, path, field, what) if raw is not None else data
    raw = bytes(raw) if raw is not None else source.encode("utf-8", "surrogatepass")
    if too_deep(raw, max_depth):
        raise DataError(path, field, f"not JSON this reader takes: arrays and objects nested more than {max_depth} "
                                     "deep")
    try:
        return json.loads(source)
    except RecursionError:  # only below the depth bound on a nearly exhausted stack
        raise DataError(path, field, "not JSON this reader takes: nested too deeply to read") from None
    except ValueError as exc:
        raise DataError(path, field, f"not JSON ({exc})") from None


def read_json(path, what: str = "JSON file", hint: str = "", max_bytes: int = MAX_BYTES):
    """The JSON value of the file at ``path``; a file that is missing, unreadable, too large, not UTF-8, not JSON
    or nested too deeply is one DataError naming it, ``what`` it should be and ``hint`` (what to do). The caller
    checks the value's shape."""
    try:
        return parse_json(read_bytes(path, what, max_bytes), path, None, f"JSON ({what})")
    except DataError as exc:
        if not hint:
            raise
        raise DataError(exc.path, exc.field, f"{exc.problem}; {hint}") from None


def read_table(path, what: str = "table of numbers", max_bytes: int = MAX_BYTES) -> np.ndarray:
    """A whitespace-separated table of numbers (``np.loadtxt``, float64, at least 2-D); anything else is a
    DataError naming the file."""
    import warnings

    source = read_text(path, what, max_bytes)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": an empty table, for the caller to judge
            return np.loadtxt(io.StringIO(source), dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise DataError(path, None, f"not a whitespace-separated {what} ({exc})") from None


def read_yaml(path, what: str = "YAML file", max_bytes: int = MAX_BYTES):
    """The value of a YAML file (``yaml.safe_load``: no tags that build objects); not UTF-8 or not YAML is a
    DataError naming it. The caller checks the value's shape."""
    import yaml

    source = read_text(path, what, max_bytes)
    with decoding(path, what):  # yaml.YAMLError, RecursionError on absurd nesting
        return yaml.safe_load(source)


def read_toml(path, what: str = "TOML file", max_bytes: int = 64 << 20) -> dict:
    """The tables of a TOML file; not UTF-8 or not TOML is a DataError naming it."""
    import tomllib

    source = read_text(path, what, max_bytes)
    try:
        return tomllib.loads(source)
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise DataError(path, None, f"invalid TOML: {exc}") from None


# ---------------------------------------------------------------- zip archives and .npz files

ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError, RuntimeError)


def is_zip(data_or_path) -> bool:
    """Whether a file (or its first bytes) starts as a zip archive does, even when it is cut short (a truncated
    archive has lost its end record, which :func:`zipfile.is_zipfile` looks for)."""
    head = data_or_path[:4] if isinstance(data_or_path, (bytes, bytearray)) else head_bytes(data_or_path, 4)
    return head in (b"PK\x03\x04", b"PK\x05\x06")


def head_bytes(path, count: int) -> bytes:
    """The first ``count`` bytes of a file (fewer for a shorter one; none when it cannot be read)."""
    try:
        with open(path, "rb") as f:
            return f.read(count)
    except OSError:
        return b""


def describe_head(head: bytes) -> str:
    """What a file's first bytes look like, for a message: ``it starts with '{' (JSON?)``, ``it is empty``."""
    if not head:
        return "it is empty (0 bytes)"
    if head.lstrip()[:1] in (b"{", b"["):
        return f"it starts with {head.lstrip()[:1].decode()!r} (JSON?)"
    if all(32 <= b < 127 or b in b"\t\r\n\x1b" for b in head):
        return f"it starts with {head.decode('ascii')!r} (text?)"
    return f"it starts with the bytes {head.hex(' ')}"


def open_zip(path, what: str = "zip archive", data: bytes | None = None, max_bytes: int = MAX_BYTES):
    """The zip archive at ``path`` (or in ``data``; ``path`` names it) opened: a :class:`zipfile.ZipFile` for a
    ``with`` block, its members read with :func:`zip_read`. Cut short or damaged is a DataError naming it."""
    if data is None:
        file_size(path, what, max_bytes)  # present, a file, within the bound
    try:
        return zipfile.ZipFile(io.BytesIO(data) if data is not None else path)
    except ZIP_ERRORS as exc:
        raise DataError(path, None, f"not a readable {what} (cut short or damaged: {type(exc).__name__}: "
                                    f"{exc})") from None


def zip_names(zf) -> list[str]:
    """The names of an open archive's file members (folders left out), in archive order."""
    return [i.filename for i in zf.infolist() if not i.is_dir()]


def zip_read(zf, name: str, path, max_bytes: int = MAX_BYTES) -> bytes:
    """Member ``name`` of an open archive: absent, one of two of that name, over ``max_bytes`` or failing its
    CRC is a DataError naming the archive and the member."""
    infos = [i for i in zf.infolist() if i.filename == name and not i.is_dir()]
    if not infos:
        raise DataError(path, name, "member missing")
    if len(infos) > 1:
        raise DataError(path, name, "two members of the archive have this name: which one is meant is not known")
    if infos[0].file_size > max_bytes:
        raise DataError(path, name, _size_problem(infos[0].file_size, max_bytes, "member"))
    try:
        with zf.open(infos[0]) as member:
            data = member.read(max_bytes + 1)
    except ZIP_ERRORS as exc:
        kind = "zlib.error" if isinstance(exc, zlib.error) else type(exc).__name__
        raise DataError(path, name, f"damaged member ({kind}: {exc})") from None
    if len(data) > max_bytes:
        raise DataError(path, name, _size_problem(len(data), max_bytes, "member"))
    return data


def read_zip_member(path, choose: Callable[[list[str]], str], what: str = "zip archive",
                    max_bytes: int = MAX_BYTES) -> tuple[str, bytes]:
    """(name, bytes) of the member of the zip archive at ``path`` that ``choose`` picks from the names of its file
    members (``choose`` raises a DataError when none fits); see :func:`open_zip` and :func:`zip_read`."""
    with open_zip(path, what, max_bytes=max_bytes) as zf:
        name = choose(list(dict.fromkeys(zip_names(zf))))
        return name, zip_read(zf, name, path, max_bytes)


def open_npz(path, what: str = ".npz file", max_bytes: int = MAX_BYTES, data: bytes | None = None):
    """The ``.npz`` at ``path`` (or in ``data``) opened, pickles refused: a numpy ``NpzFile`` to use in a ``with``
    block. A file that is not an npz or is cut short is a DataError naming it."""
    data = read_bytes(path, what, max_bytes) if data is None else data
    with decoding(path, what):
        npz = np.load(io.BytesIO(data), allow_pickle=False)
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise DataError(path, None, f"not a {what}: a single .npy array, not an archive of named arrays")
    return npz


def npz_array(npz, key: str, path) -> np.ndarray:
    """Member ``key`` of an open npz decoded; missing, damaged (a bad CRC, cut short) or an object array is a
    DataError naming the file and key."""
    if key not in npz.files:
        raise DataError(path, key, f"missing (the file holds {sorted(npz.files)})")
    with decoding(f"{path}: {key!r}", "array"):
        return npz[key]


def npz_header(npz, key: str, path) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of member ``key`` of an open npz from its ``.npy`` header only (not decoded)."""
    read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    with decoding(f"{path}: {key!r}", "array header"):
        with npz.zip.open(f"{key}.npy") as f:
            version = np.lib.format.read_magic(f)
            if version not in read:  # format 3.0 (utf-8 field names): decode the member instead
                value = npz[key]
                return value.shape, value.dtype
            shape, _, dtype = read[version](f)
    return tuple(shape), np.dtype(dtype)


def read_npz(path, keys: tuple[str, ...], what: str = ".npz file", max_bytes: int = MAX_BYTES,
             data: bytes | None = None) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of an ``.npz`` (from ``data`` if given), pickles refused. A file that is not an npz, cut
    short, damaged (a bad CRC), lacking a key or holding an object array is a DataError naming the file and
    key. The caller checks dtypes and shapes (:func:`hoidata.shapes.numbers`)."""
    with open_npz(path, what, max_bytes, data) as npz:
        return {key: npz_array(npz, key, path) for key in keys}


def decode_npy(data: bytes, path, field: str | None = None) -> np.ndarray:
    """One ``.npy`` array from its bytes, pickles refused; anything else is a DataError naming the file and field."""
    try:
        out = np.load(io.BytesIO(bytes(data)), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:  # allow_pickle=False: an object array is refused here
        raise DataError(path, field, f"not a readable .npy array ({exc})") from None
    if not isinstance(out, np.ndarray):
        raise DataError(path, field, "not a readable .npy array (an archive)")
    return out


# ---------------------------------------------------------------- tar files

@dataclass(frozen=True)
class TarMember:
    name: str  # as stored
    offset: int  # of its bytes in the file
    size: int


@dataclass
class TarListing:
    """The file members of a tar, found by ``key(name)``: where each lies, which keys two members share (both
    names, never silently the last) and ``truncated``: the problem that ended the listing early (the members
    before it stand)."""

    path: str
    members: dict = field(default_factory=dict)
    duplicates: dict = field(default_factory=dict)  # key -> the names of every member with that key
    truncated: str = ""

    def read(self, key: str, field: str | None = None, max_bytes: int = MAX_BYTES) -> bytes:
        """The bytes of the member of ``key``: missing, one of a duplicate or cut short is a DataError naming it."""
        shown = field or key
        if key in self.duplicates:
            names = " and ".join(repr(n) for n in self.duplicates[key])
            raise DataError(self.path, shown, f"two members of the tar are {key!r} ({names}): which one is meant "
                                              "is not known")
        member = self.members.get(key)
        if member is None:
            raise DataError(self.path, shown, "member missing")
        if member.size > max_bytes:
            raise DataError(self.path, shown, _size_problem(member.size, max_bytes, "member"))
        return read_span(self.path, member.offset, member.size, shown)


def read_span(path, offset: int, size: int, field: str | None = None) -> bytes:
    """``size`` bytes of the file at ``offset`` (a member of a tar); fewer is a DataError naming it."""
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read(size)
    except OSError as exc:
        raise DataError(path, field, f"cannot read ({exc.strerror or exc})") from None
    if len(data) != size:
        raise DataError(path, field, f"member at byte {offset} is cut short ({len(data)} of {size} bytes)")
    return data


def list_tar(path, key: Callable[[str], str | None] = lambda name: name, what: str = "tar file") -> TarListing:
    """The file members of the tar at ``path`` (headers only; links and folders are not members), under
    ``key(name)`` (None leaves a member out). A tar cut short keeps the members whose bytes are all there; an
    unreadable file raises a DataError naming it."""
    import tarfile

    out = TarListing(str(path))
    try:
        size = os.stat(path).st_size
        with tarfile.open(path, "r:") as tar:
            for info in iter(tar.next, None):
                if not info.isfile():
                    continue
                if info.offset_data + info.size > size:
                    out.truncated = f"member {info.name!r} is cut short: the tar is truncated"
                    break
                name = key(info.name)
                if name is None:
                    continue
                if name in out.members:
                    out.duplicates.setdefault(name, [out.members[name].name]).append(info.name)
                out.members[name] = TarMember(info.name, info.offset_data, info.size)
    except (tarfile.TarError, EOFError, OSError) as exc:
        if isinstance(exc, FileNotFoundError):
            raise DataError(path, None, f"{what} not found") from None
        if not out.members:
            raise DataError(path, None, f"not a readable {what} ({exc})") from None
        out.truncated = f"the tar ends early ({exc})"
    return out
