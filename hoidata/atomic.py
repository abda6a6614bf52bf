"""Atomic file writes for every result the project writes: a file appears whole under its name, or not at all.

Each write goes to a unique temporary name in the same folder (``.<name>.<random>.tmp``, so two processes
writing the same file never share one) and is renamed over the target. The file gets the permissions an
ordinary ``open(path, "w")`` would give it (0666 minus the umask, usually 0644), not the 0600 of a
``tempfile`` file: reports, pictures, result files and checkpoints are meant to be read by others.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from hoidata.errors import naming_os_errors


def _umask() -> int:
    """The process umask, read without changing it where Linux says it (else set and restored at once)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; when the block ends without error it is renamed to ``path``.

    For writers that want a file name (``torch.save``, ``savefig``); on error the temporary file is removed, and an
    OSError without a file name (ENOSPC from a write) gets ``path``'s (:func:`hoidata.errors.naming_os_errors`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with naming_os_errors(path):  # a full disk's errno names no file: name the one being written
            os.fchmod(fd, 0o666 & ~_umask())
            os.close(fd)
            yield Path(tmp)
            os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """Yield a binary file to write; when the block ends without error it is flushed, synced to the disk and
    renamed to ``path`` (so a full disk is found before the rename, and a file already at ``path`` stays whole
    until then). An error removes the temporary file and names ``path``, as :func:`atomic_path` does."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        yield f
        f.flush()
        os.fsync(f.fileno())


def write_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see the module docstring); returns ``path``."""
    with atomic_file(path) as f:
        f.write(data)
    return Path(path)


def append_whole(path: str | os.PathLike, data: bytes) -> None:
    """Append ``data`` to ``path`` (created when missing, with the umask's permissions) whole or not at all.

    For logs that grow by rows (a training run's ``metrics.csv``): a write that fails part way (a full disk, a file
    size limit) is cut back to the file's length before it, so the log never ends in half a row, and the error
    names ``path`` (:func:`hoidata.errors.naming_os_errors`)."""
    path = Path(path)
    with naming_os_errors(path):
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            start = os.fstat(fd).st_size
            view = memoryview(data)
            try:
                while view:
                    view = view[os.write(fd, view):]
            except OSError:
                with contextlib.suppress(OSError):  # the write's own error is the one to report
                    os.ftruncate(fd, start)
                raise
        finally:
            os.close(fd)


def write_json_atomic(path: str | os.PathLike, value) -> Path:
    """``value`` as indented JSON with sorted keys, written atomically."""
    return write_atomic(path, (json.dumps(value, sort_keys=True, indent=1) + "\n").encode())
