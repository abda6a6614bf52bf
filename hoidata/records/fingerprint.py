"""Fingerprints of what a build reads, so a resumed build refuses inputs that changed since it started.

A store is built shard by shard; a resumed build keeps the shards already written. If the MANO files, the
object models or the dataset changed in between, the kept shards and the new ones would disagree, and no
checksum would notice. ``build.json`` therefore pins, besides the settings and the frame keys:

- ``mano``: the sha256 of each MANO file in the MANO folder;
- ``models``: the sha256 of each object model the frames use (or of its whole folder, when textures matter);
- ``annotations``: one sha256 over every frame's labels as the reader returned them (which covers the label
  files, meta.yml and the calibration the reader read), paths relative to the dataset root.

Image files are too many to hash at every start. Each shard's skips file records, for every image (and
segmentation file) its frames read, the size, mtime and sha256; a resumed build compares the size and mtime
of the kept shards' files and re-hashes only those that differ (a copied or touched but unchanged file passes).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import fields
from functools import lru_cache
from pathlib import Path

import numpy as np

from hoidata import sections
from hoidata.errors import DataError
from hoidata.reading import file_digest

MANO_FILES = ("MANO_RIGHT.pkl", "MANO_LEFT.pkl")
MISSING = "missing"


def file_sha256(path: Path) -> str:
    return file_digest(path, "input file")[1]


def files(folder: Path, names) -> dict[str, str]:
    """{name: sha256 or "missing"} of the files ``folder/name``."""
    return {name: file_sha256(Path(folder) / name) if (Path(folder) / name).is_file() else MISSING for name in names}


def models(models_dir: Path, names, whole_folder: bool = False) -> dict[str, str]:
    """{object name: sha256} of each object's ``textured_simple.obj`` (``whole_folder``: of every file of its
    folder, names included, for builds that render textures)."""
    from hoidata.objects import object_mesh_path

    out = {}
    for name in sorted(names):
        folder = Path(models_dir) / name
        paths = sorted(p for p in folder.rglob("*") if p.is_file()) if whole_folder else [object_mesh_path(models_dir, name)]
        if not all(p.is_file() for p in paths) or not paths:
            out[name] = MISSING
            continue
        digest = hashlib.sha256()
        for p in paths:
            rel = p.relative_to(folder) if folder in p.parents else p.name  # HOT3D: models_dir/obj_<id>.glb
            digest.update(f"{rel}\0{file_sha256(p)}\0".encode())
        out[name] = digest.hexdigest()
    return out


def _relative(value, roots: tuple[str, ...], mark: str = "<root>") -> str:
    text = os.fspath(value)
    for root in roots:
        if text == root or text.startswith(root.rstrip(os.sep) + os.sep):
            return mark + text[len(root.rstrip(os.sep)):]
    return text


def root_spellings(root: Path) -> tuple[str, ...]:
    """The ways a frame's paths may start with the dataset folder: as given (``Path`` drops a trailing slash and
    ``./``) and resolved (absolute, links followed), longest first."""
    return tuple(sorted({os.fspath(Path(root)), os.fspath(Path(root).resolve())}, key=len, reverse=True))


def root_relative(value, root: Path):
    """``value`` (a reader's ``source`` dict, a list or a string) with every path under ``root`` written relative
    to it (``labels_000000.npz`` of ``ROOT/subject/.../labels_000000.npz``): what a record stores does not depend
    on how ``--root`` was spelled (relative, absolute, through a link) or where the dataset lives."""
    return _root_relative(value, root_spellings(root))


def _root_relative(value, roots: tuple[str, ...]):
    """:func:`root_relative` with the root's spellings resolved once, not once per string (resolving the root per
    path was 1.3 ms a frame; HOT3D's sources hold lists)."""
    if isinstance(value, dict):
        return {k: _root_relative(v, roots) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_root_relative(v, roots) for v in value)
    if isinstance(value, (str, os.PathLike)):
        text = _relative(value, roots, "")
        return text.lstrip(os.sep) if text != os.fspath(value) else text
    return value


def annotations(frames, root: Path) -> str:
    """One sha256 over every frame's fields but its in-memory pixels (arrays as float64, paths relative to root,
    also inside the ``source`` dict)."""
    roots = root_spellings(root)
    digest = hashlib.sha256()
    for frame in frames:
        for f in fields(frame):
            if f.name in ("image", "labels"):
                continue
            value = getattr(frame, f.name)
            if isinstance(value, np.ndarray):
                digest.update(np.ascontiguousarray(value, dtype=np.float64).tobytes())
            elif isinstance(value, os.PathLike):
                digest.update(_relative(value, roots).encode())
            elif isinstance(value, dict):
                digest.update(json.dumps(root_relative(value, root), sort_keys=True, default=str).encode())
            else:
                digest.update(repr(value).encode())
            digest.update(b"\0")
    return digest.hexdigest()


def _stamp(path: Path):
    try:
        st = path.stat()
        return [st.st_size, st.st_mtime_ns, _digest(os.fspath(path), st.st_size, st.st_mtime_ns)]
    except OSError:
        return MISSING


@lru_cache(maxsize=8)
def _digest(path: str, size: int, mtime_ns: int) -> str:
    """file_sha256 once per file, size and mtime in a process: HOT3D's frames all read their clip's tar."""
    return file_sha256(Path(path))


def frame_inputs(frame, root: Path) -> dict:
    """{path relative to root: [size, mtime_ns, sha256] or "missing"} of the files a record of ``frame`` reads."""
    out = {}
    for path in (None if frame.image is not None else frame.image_path, frame.segmentation_path):
        if path is None:
            continue
        path = Path(path)
        try:
            name = os.fspath(path.relative_to(root))
        except ValueError:
            name = os.fspath(path)
        out[name] = _stamp(path)
    return out


def changed_input(stamps: dict, root: Path) -> str | None:
    """The first file of ``stamps`` (see frame_inputs) that differs now, or None: size and mtime equal is
    unchanged, otherwise the content decides."""
    for name, old in stamps.items():
        path = Path(root) / name
        if old == MISSING or not path.is_file():
            if (old == MISSING) != (not path.is_file()):
                return name
            continue
        st = path.stat()
        if [st.st_size, st.st_mtime_ns] == old[:2]:
            continue
        if st.st_size != old[0] or file_sha256(path) != old[2]:
            return name
    return None


def first_difference(old, new, prefix: str = "") -> str | None:
    """The dotted key path of the first difference between two JSON values (None when equal)."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            where = f"{prefix}.{key}" if prefix else str(key)
            if key not in old or key not in new:
                return where
            found = first_difference(old[key], new[key], where)
            if found:
                return found
        return None
    return None if old == new else prefix


def current_names(spec, renamed: dict[str, str], section: str = "record"):
    """``spec`` (a ``build.json`` or ``export.json`` as read) with the settings of ``config[section]`` that were
    renamed since (``renamed``: old name -> new name) under their new names, so that a store or export started
    before a rename compares equal to the same settings today and resumes; anything else is returned as it is."""
    config = spec.get("config") if isinstance(spec, dict) else None
    table = config.get(section) if isinstance(config, dict) else None
    if not isinstance(table, dict) or not set(renamed) & set(table):
        return spec
    return {**spec, "config": {**config, section: sections.current_names(table, renamed)}}


def describe_difference(where: str, what: str = "store") -> str:
    """Plain words for a first_difference path of build.json (or an export's export.json: ``what`` "export")."""
    head, _, rest = where.partition(".")
    if head == "inputs":
        kind, _, name = rest.partition(".")
        words = {"mano": f"the MANO file {name}", "models": f"the object model {name}",
                 "annotations": "the dataset's annotations (label files, meta.yml or calibration)",
                 "grasps": "the grasp source", "backgrounds": f"the background image {name}"}
        thing = words.get(kind, f"the input {rest}") if rest else "the input fingerprints (an older hoidata?)"
        return f"{thing} changed since this {what} was started"
    if head == "config":
        return f"the setting {rest} differs from the one this {what} was started with"
    if head in ("keys_sha256", "frames"):
        return f"the selected frames differ from those this {what} was started with"
    return f"{where} differs from the one this {what} was started with"


def check_kept_inputs(read_stamps, numbers, root: Path) -> None:
    """Refuse to resume when a file that a kept shard was built from changed; read_stamps(n) -> that shard's stamps."""
    for number in numbers:
        name = changed_input(read_stamps(number), root)
        if name:
            raise DataError(Path(root) / name, None, f"changed since shard {number} of this store was built from it; "
                                                      "resuming would mix old and new records: use a new --out "
                                                      "folder (nothing was changed)")


def build_inputs(frames, root: Path, mano_dir: Path, models_dir: Path, whole_folders: bool = False) -> dict:
    """What a store's ``build.json`` (and an export's ``export.json``) pins besides settings and keys: the MANO
    files, the frames' object models (``whole_folders``: every file of their folders, for upstream's crop, which
    reads points.xyz too) and the frames' annotations."""
    return {"mano": files(mano_dir, MANO_FILES),
            "models": models(models_dir, {f.object_name for f in frames}, whole_folder=whole_folders),
            "annotations": annotations(frames, root)}
