"""Where a store lives and what in its folder is not part of it.

:func:`resolve_store` is the one place that decides whether a store location is local or remote;
:func:`local_folder` / :func:`local_store` refuse a URL where a command needs a folder; :func:`replaced_dir` writes a folder
(the index) aside and swaps it in; :func:`stale_temps` finds the leftovers of such writes that did not finish
(``index.zarr.tmp<pid>``); :func:`index_lock` serialises the processes that finish one store's index.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

from hoidata.errors import DataError
from hoidata.store.remote import RemoteStore, url_authority

INDEX_NAME = "index.zarr"
LOCK_NAME = "index.lock"  # not index.zarr.*: those names are the index and its temporary folders


def resolve_store(location) -> Path | RemoteStore:
    """Where a store given on a command line or to a loader lives: a local folder, or a :class:`RemoteStore`.

    This is the one place that decides local or remote. Only a ``str`` that is an explicit ``http://``,
    ``https://``, ``s3://`` or ``gs://`` URL (with a host) is remote. Anything else is a local path, whatever
    it looks like: a ``Path`` is never parsed, and a folder named ``pipe:cmd``, ``s3:x`` or ``http:x`` is just a
    folder. No part of the project hands a store location to webdataset's URL opener (its ``pipe:`` runs a shell).
    """
    if isinstance(location, RemoteStore):
        return location
    if isinstance(location, str) and url_authority(location) is not None:
        return RemoteStore(location)
    return Path(os.fspath(location))


def refuse_repeated_stores(stores, what: str, hint: str = "") -> None:
    """A store named twice in one list (``--shards a a``, also spelled ``./a`` and ``a/``, through a link, or as one
    URL with another query) is a DataError naming it and ``what`` (the option), before anything is read: it would
    be read, trained on or scored twice. ``stores``: what :func:`resolve_store` returns; ``hint``: what to do."""
    seen: dict = {}
    for store in stores:
        key = store.base if isinstance(store, RemoteStore) else Path(store).resolve()
        if key in seen:
            raise DataError(store, None, f"{what} names this store twice (also as {seen[key]}); give each store "
                                         f"once{hint}")
        seen[key] = store


# text that names a URL, not a folder: any scheme:// (also ones no loader reads: ftp://, file://, gs:///x), and the
# store schemes with one slash (a typo of one): Path() would squash them into a folder named 'http:' or 's3:'
_URL_LIKE = re.compile(r"^(?:[A-Za-z][A-Za-z0-9+.-]+://|(?:https?|s3|gs):/)", re.IGNORECASE)


def local_folder(location, what: str) -> Path:
    """The local folder a command writes or reads (``what`` names the option, e.g. ``"build-sdf --out"``). Text
    that names a URL (see ``_URL_LIKE``) is a DataError naming it, raised before anything is written, so a URL
    never becomes a local folder named ``http:`` or ``s3:``. A ``Path``, and a name like ``s3:x`` or
    ``pipe:cmd`` (no slash after the colon), is a folder, as :func:`resolve_store` has it."""
    if isinstance(location, RemoteStore):
        location = location.url
    if isinstance(location, str) and (_URL_LIKE.match(location) or url_authority(location) is not None):
        raise DataError(location, None, f"{what} needs a local path, not a URL; remote stores are read by the "
                                        "training and evaluation loaders only (copy the store to a local store "
                                        "folder first)")
    return Path(os.fspath(location))


def local_store(location, what: str) -> Path:
    """:func:`resolve_store` for commands that need a local folder (``what`` names the command): a URL is a
    DataError saying so (:func:`local_folder`)."""
    return local_folder(location, what)


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


def writer_token() -> str:
    """``<host>-<pid>``: names a temporary file after the process writing it, so two processes writing the same
    shard (a part rerun while the first run is still alive, on any node of a shared filesystem) never share one."""
    import socket

    return f"{socket.gethostname()}-{os.getpid()}"


def is_stale_token(token: str) -> bool:
    """Whether the writer a :func:`writer_token` names is gone: a process of this host that no longer runs.
    A writer on another host cannot be checked from here and counts as alive (its leftover, if it died, is only
    disk space; ``hoidata verify`` lists it)."""
    import socket

    host, _, pid = token.rpartition("-")
    return host == socket.gethostname() and pid.isdigit() and (int(pid) == os.getpid() or not _pid_alive(int(pid)))


@contextlib.contextmanager
def index_lock(store_dir) -> Iterator[None]:
    """Hold an exclusive lock on ``store_dir``'s index for the block, so the processes that finish one store (array
    tasks on any node, a rerun part, the launcher) write its index one after the other.

    A POSIX record lock (``fcntl.lockf``) on ``index.lock``: the kernel releases it when the process ends, so
    a killed holder leaves no stale lock, and network filesystems (NFS, Lustre mounted with ``flock``, GPFS)
    honour it across nodes. The lock file stays (removing it would let two processes lock different files).
    Where the filesystem has no locks, the block runs unlocked, with a note on stderr.
    """
    import errno
    import fcntl
    import sys

    import stat

    path = Path(store_dir) / LOCK_NAME
    try:  # never through a link planted at the lock's name: it would create or lock a file elsewhere
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)  # the umask applies
    except OSError as exc:
        if exc.errno != errno.ELOOP:
            raise
        raise DataError(path, None, "is a symbolic link; the index lock must be a plain file of the store folder "
                                    "(remove the link; nothing was written)") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise DataError(path, None, "is not a plain file; remove it (nothing was written)")
    try:
        try:
            fcntl.lockf(fd, fcntl.LOCK_EX)
        except OSError as exc:
            if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                raise
            print(f"note: {path}: this filesystem has no file locks; finishing the index unlocked", file=sys.stderr)
        yield
    finally:
        os.close(fd)  # releases the lock

