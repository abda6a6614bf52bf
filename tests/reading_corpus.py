"""The damaged-file corpus of tests/test_reading_corpus.py: one list of damages (:data:`DAMAGES`), each made from a
reader's valid file by :func:`damage`, and the machinery that places a file (or a container member) for a reader.

A damage that makes no sense for a format (a number turned into a string, in a JPEG) is left out for it; every
other damage is fed to every reader.
"""

from __future__ import annotations

import io
import json
import re
import tarfile
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DAMAGES = ("missing", "folder", "empty", "random", "not_utf8", "truncated", "deep_json", "string_number",
           "bool_number", "nan_number", "bad_crc", "duplicate")
TYPED = ("string_number", "bool_number", "nan_number")
CONTENT = tuple(d for d in DAMAGES if d not in ("missing", "folder"))  # damages of the bytes, not of the path
TEXT_KINDS = {"json", "yaml", "toml", "text", "csv", "obj"}
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def first_number(data: bytes) -> tuple[int, int] | None:
    """(start, end) of the first number token outside a quoted string and not inside a word, or None."""
    i, in_string = 0, False
    while i < len(data):
        c = data[i:i + 1]
        if in_string:
            i += 2 if c == b"\\" else 1
            in_string = in_string and c != b'"'
            continue
        if c == b'"':
            in_string = True
        elif (c.isdigit() or (c == b"-" and data[i + 1:i + 2].isdigit())) and not (
                i and (data[i - 1:i].isalnum() or data[i - 1:i] in b"_./-")):
            m = _NUMBER.match(data, i)
            if m and not data[m.end():m.end() + 1].isalpha():
                return m.start(), m.end()
            i = m.end() if m else i + 1
            continue
        elif c.isalnum():
            while i < len(data) and (data[i:i + 1].isalnum() or data[i:i + 1] in b"_./-"):
                i += 1
            continue
        i += 1
    return None


def _typed_text(data: bytes, kind: str, how: str) -> bytes | None:
    where = first_number(data)
    if where is None:
        return None
    token = data[where[0]:where[1]]
    new = {"string_number": b'"' + token + b'"', "bool_number": b"true",
           "nan_number": b"nan" if kind in ("toml", "csv") else b"NaN"}[how]
    return data[:where[0]] + new + data[where[1]:]


def _typed_arrays(arrays: dict, how: str) -> dict | None:
    """The arrays with the first float one turned into strings / booleans / holding a NaN."""
    name = next((k for k, v in arrays.items() if v.dtype.kind == "f"), None)
    if name is None:
        name = next((k for k, v in arrays.items() if v.dtype.kind in "iu"), None)
        if name is None or how == "nan_number":
            return None
    arr = arrays[name]
    if how == "string_number":
        arr = arr.astype(str)
    elif how == "bool_number":
        arr = arr.astype(bool)
    else:
        arr = arr.astype(np.float64).copy()
        arr.flat[0] = np.nan
    return {**arrays, name: arr}


def _flip_in_first_member(data: bytes) -> bytes | None:
    """A zip's first member with one byte of its data changed (its CRC no longer matches)."""
    start = data.find(b"PK\x03\x04")
    if start < 0 or len(data) < start + 30:
        return None
    size = int.from_bytes(data[start + 18:start + 22], "little") or 16
    offset = start + 30 + int.from_bytes(data[start + 26:start + 28], "little") + \
        int.from_bytes(data[start + 28:start + 30], "little") + size // 2
    if offset >= len(data):
        return None
    return data[:offset] + bytes([data[offset] ^ 0x5A]) + data[offset + 1:]


def damage(name: str, valid: bytes, kind: str) -> bytes | None:
    """The bytes of damage ``name`` made from a reader's ``valid`` bytes of format ``kind``; None where the damage
    does not apply to the format ("missing" and "folder" are made by :meth:`Case.place`)."""
    rng = np.random.default_rng(44)
    if name == "empty":
        return b""
    if name == "random":
        return b"\x00" + rng.integers(0, 256, 2047, dtype=np.uint8).tobytes()
    if name == "not_utf8":
        return b"\xff\xfe\x80" + valid
    if name == "truncated":
        return valid[:max(1, len(valid) // 2)]
    if name == "deep_json":
        return b"[" * 100_000 + b"]" * 100_000
    if name in TYPED:
        if kind in TEXT_KINDS:
            return _typed_text(valid, kind, name)
        if kind in ("npz", "npy"):
            loaded = np.load(io.BytesIO(valid), allow_pickle=False)
            if kind == "npy":
                arrays = {"a": loaded}
            else:
                with loaded:
                    arrays = {k: loaded[k] for k in loaded.files}
            arrays = _typed_arrays(arrays, name)
            if arrays is None:
                return None
            buf = io.BytesIO()
            np.savez(buf, **arrays) if kind == "npz" else np.save(buf, arrays["a"])
            return buf.getvalue()
        return None
    if name == "bad_crc":
        return _flip_in_first_member(valid) if kind in ("zip", "npz", "torch") else None
    return None  # "duplicate" is a container's (Case.place)


def zip_bytes(members: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Duplicate name": the duplicate damage means it
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, data in members:
                zf.writestr(name, data)
    return buf.getvalue()


def tar_bytes(members: list[tuple[str, bytes]], fmt=tarfile.USTAR_FORMAT) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=fmt) as tar:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size, info.mtime = len(data), 0
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@dataclass
class Case:
    """One reader fed the corpus.

    ``read(path)`` reads what ``place`` put at ``path`` (a DataError is its refusal). A member case puts the
    damaged bytes into member ``member`` of a container (``container(members) -> bytes``, members in order, the
    damaged one at its place), which is then the file named in the error, beside the member. ``accepts``: damages
    the reader may take without a word (its contract is lenient there: a text list cut at a line, a cache).
    """

    name: str
    kind: str
    valid: bytes
    read: Callable[[Path], object]
    filename: str = "file"
    accepts: frozenset = frozenset()
    member: str | None = None
    others: list = field(default_factory=list)  # (name, bytes) of the container's other members
    container: Callable[[list], bytes] | None = None
    sibling: dict = field(default_factory=dict)  # other files of the folder: name -> bytes
    shows: str | None = None  # the member or field the error must name (default: the member)
    position: int | None = None  # where the member goes among ``others`` (default: the middle)
    duplicate_as: str = "other/{}"  # the second member's name (a tar's reader goes by basename; a zip's by name)

    def place(self, folder: Path, damage_name: str | None) -> Path | None:
        """Write the file (damaged by ``damage_name``; None: valid) into ``folder``; its path, or None where the
        damage does not apply."""
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in self.sibling.items():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(data)
        path = folder / self.filename
        path.parent.mkdir(parents=True, exist_ok=True)
        data = self.valid if damage_name is None else damage(damage_name, self.valid, self.kind)
        if self.member is None:
            if damage_name == "missing":
                return path
            if damage_name == "folder":
                path.mkdir()
                return path
            if data is None:
                return None
            path.write_bytes(data)
            return path
        members = list(self.others)
        if damage_name == "duplicate":
            # the valid one last: a reader where the last of a name wins would take it without a word
            members += [(self.duplicate_as.format(self.member), b'{"garbage": 1}'), (self.member, self.valid)]
        elif damage_name != "missing":
            if damage_name == "folder" or data is None:
                return None
            members.insert(len(members) // 2 if self.position is None else self.position, (self.member, data))
        path.write_bytes(self.container(members))
        return path
