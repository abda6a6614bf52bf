"""Writing an export's files: every file goes to ``<name>.tmp`` first and is renamed, so nothing under a final
name is ever half written (a killed export leaves only ``.tmp`` files, which the next run overwrites; a failed write
removes its own, and an OSError without a file name, ENOSPC from a write, gets the file's)."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hoidata.errors import naming_os_errors


@contextlib.contextmanager
def _via_tmp(path: Path) -> Iterator[Path]:
    """Yield ``<path>.tmp`` to write; renamed to ``path`` when the block succeeds, removed when it fails."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with naming_os_errors(path):
            yield tmp
            os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: Path, value, indent=None) -> None:
    """JSON (compact unless ``indent``) written via ``<path>.tmp``."""
    separators = (",", ":") if indent is None else None
    with _via_tmp(path) as tmp:
        tmp.write_text(json.dumps(value, indent=indent, separators=separators, allow_nan=False) + "\n")


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """An uncompressed ``.npz`` (as cnpy writes AlignSDF's) via ``<path>.tmp``."""
    with _via_tmp(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A Wavefront OBJ of a triangle mesh (``v`` lines with exact float reprs, 1-based ``f`` lines) via ``.tmp``."""
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, np.float64).tolist()]
    lines += [f"f {a} {b} {c}" for a, b, c in (np.asarray(faces, np.int64) + 1).tolist()]
    with _via_tmp(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def write_coco(path: Path, entries, split: str) -> int:
    """Stream ``{"images": [...], "annotations": [...]}`` of one split's entries to ``path`` (via ``.tmp``).

    ``entries()`` is called twice (images, then annotations), so only one chunk's manifest is in memory.
    Returns the number of annotations.
    """
    count = 0
    with _via_tmp(path) as tmp, open(tmp, "w") as f:
        for member in ("images", "annotations"):
            f.write(("{" if member == "images" else ", ") + json.dumps(member) + ": [")
            first = True
            for e in entries():
                if e["split"] != split:
                    continue
                f.write(("" if first else ", ") + json.dumps(e["image" if member == "images" else "annotation"],
                                                              separators=(",", ":"), allow_nan=False))
                first = False
                count += member == "annotations"
            f.write("]")
        f.write("}\n")
    return count


def link(target: Path, path: Path) -> bool:
    """Make ``path`` a symbolic link to ``target`` unless something is already there; True if made."""
    if path.exists() or path.is_symlink() or Path(target).resolve() == path.resolve():
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    path.symlink_to(Path(target).resolve(), target_is_directory=Path(target).is_dir())
    return True


