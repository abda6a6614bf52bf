"""Where a store lives and what in its folder is not part of it.

:func:`resolve_store` is the one place that decides whether a store location is local or remote;
:func:`replaced_dir` writes a folder (the index) aside and swaps it in; :func:`stale_temps` finds the leftovers of
such writes that did not finish (``index.zarr.tmp<pid>``).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

from hoidata.errors import DataError

INDEX_NAME = "index.zarr"
_REMOTE_RE = re.compile(r"^(https?|s3|gs)://", re.IGNORECASE)


def resolve_store(location) -> Path:
    """Where a store given on a command line or to a loader lives: always a local folder, for now.

    This is the one place that decides local or remote. Only an explicit ``http://``, ``https://``, ``s3://``
    or ``gs://`` URL would be remote, and remote stores are not supported yet: such a URL is a DataError.
    Anything else is a local path, whatever it looks like: a folder named ``pipe:cmd`` or ``s3:x`` is just a
    folder, and no part of the project hands a store path to a URL opener (webdataset's ``pipe:`` runs a shell).
    """
    text = os.fspath(location)
    if _REMOTE_RE.match(text):
        raise DataError(text, None, "remote stores (http://, https://, s3://, gs://) are not supported yet; "
                                    "copy the store to a local folder")
    return Path(text)


_TEMP_RE = re.compile(rf"^{re.escape(INDEX_NAME)}\.(tmp|old)(\d+)$")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def stale_temps(store_dir) -> list[Path]:
    """Leftover ``index.zarr.tmp<pid>`` / ``.old<pid>`` folders of index writes that did not finish.

    Those of processes still running on this machine are not listed (they may be writing right now).
    """
    found = []
    for path in sorted(Path(store_dir).glob(f"{INDEX_NAME}.*")):
        match = _TEMP_RE.match(path.name)
        if match and (int(match.group(2)) == os.getpid() or not _pid_alive(int(match.group(2)))):
            found.append(path)
    return found


def remove_stale_temps(store_dir) -> None:
    """Remove :func:`stale_temps` (a killed or failed index write of any process leaves nothing behind)."""
    for path in stale_temps(store_dir):
        shutil.rmtree(path, ignore_errors=True)


@contextlib.contextmanager
def replaced_dir(where: Path) -> Iterator[Path]:
    """Yield a per-process temporary folder next to ``where``; when the block ends it replaces ``where``.

    Per-process names (``<name>.tmp<pid>``), so two ``--part`` jobs finishing together never share one; stale
    leftovers of dead processes are removed first. On any error (a full disk, a kill signal) the temporary
    folder is removed and the previous ``where``, if any, stays in place.
    """
    tmp, old = where.with_name(f"{where.name}.tmp{os.getpid()}"), where.with_name(f"{where.name}.old{os.getpid()}")
    remove_stale_temps(where.parent)
    try:
        yield tmp
        if where.exists():  # a directory cannot be renamed over a non-empty one: move the old one aside first
            os.replace(where, old)
        os.replace(tmp, where)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not where.exists():
            os.replace(old, where)
        raise
    shutil.rmtree(old, ignore_errors=True)
