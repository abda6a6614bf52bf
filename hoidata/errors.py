"""One error type for bad input files, so every message names the file and the field; and how CLIs report them.

Every command line of the project (``hoidata``, ``python -m hoisdf.train``/``evaluate``/``toy``) runs its work
through :func:`run_cli`: an error the user can act on (a :class:`DataError`, a bad value, a full or read-only
disk, a worker that could not start) becomes one ``error:`` line and exit code 2; ``--debug`` shows the
traceback instead. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
from collections.abc import Iterator

# a URL's user info (``scheme://user:password@``, up to the authority's last '@': a password may hold a raw one) and
# its query's values (presigned signatures, tokens): secrets. ``scheme:/`` too: a URL squashed by Path() into a
# folder name (``--mano http://u:pw@h/x`` reads as the folder ``http:/u:pw@h/x``) still carries them.
_USERINFO = re.compile(r"(?i)\b([a-z][a-z0-9+.-]*:/{1,3})[^/?#\s]+@")
_QUERY = re.compile(r"(?i)(\b[a-z][a-z0-9+.-]*:/{1,3}[^\s?#]*\?)([^\s#]*?)(?=[\s#'\"]|: |:$|$)")
_VALUE = re.compile(r"=[^&;]*")


def redact_urls(text: str) -> str:
    """``text`` with the secrets of every URL in it masked: its user info (``http://alice:pw@host`` ->
    ``http://***@host``) and the value of every query parameter (``?X-Amz-Signature=abc`` ->
    ``?X-Amz-Signature=***``). Every value, not a list of known names: presigned and shared-access URLs spread
    their secret over parameters whose names vary by provider (``X-Amz-Signature``, ``X-Amz-Credential``,
    ``X-Amz-Security-Token``, ``X-Goog-Signature``, ``X-Goog-Credential``, ``sig``, ``se``, ``token``, ``key``,
    ``access_token``, ``Signature``, ``Policy``, ``Key-Pair-Id``, ...), and a store URL has no other use for a query;
    the names stay, so a line still says what was sent.

    The one redaction of the project: error lines (every :class:`DataError` and :func:`run_cli`'s line), and
    whatever records a store (a run's ``config.json``, evaluation results) go through it.
    """
    text = _USERINFO.sub(r"\1***@", text)
    return _QUERY.sub(lambda m: m.group(1) + _VALUE.sub("=***", m.group(2)), text)


class DataError(ValueError):
    """A file the user gave us is missing, malformed or inconsistent.

    The message always starts with the file path, then the field (key, member, column) that is
    wrong, then what is wrong with it, e.g. ``MANO_RIGHT.pkl: 'posedirs': expected shape (778, 3, 135), got (778, 3)``.
    DataErrors survive pickling (worker processes send them to the parent as they are).
    """

    def __init__(self, path: str | os.PathLike | object | None, field: str | None, problem: str):
        # a path, or what names a remote file (a RemoteFile prints its URL); never parsed here
        self.path = None if path is None else os.fspath(path) if isinstance(path, (str, os.PathLike)) else str(path)
        self.field = field
        self.problem = problem
        parts = [p for p in (self.path, None if field is None else repr(field)) if p]
        super().__init__(redact_urls(": ".join(parts + [problem])))  # a URL's password never reaches a message

    def __reduce__(self):
        return type(self), (self.path, self.field, self.problem)


@contextlib.contextmanager
def naming_os_errors(path: str | os.PathLike) -> Iterator[None]:
    """Give an OSError raised in the block without a file name the ``path`` being written.

    ``open()`` and ``os.*`` calls name their file, but the errno of ``write()``, ``flush()``, ``fsync()`` and
    ``close()`` (ENOSPC on a full disk, EIO, EDQUOT) carries none, so the one-line report would be just "No space
    left on device". Every place that writes a result wraps its writing in this, naming the file the user
    asked for (not its temporary name). The new error keeps the errno (so its subclass) and chains the original.
    """
    try:
        yield
    except OSError as err:
        if err.filename is not None or err.filename2 is not None:
            raise
        reason = err.strerror or str(err) or type(err).__name__
        raise OSError(err.errno, reason, os.fspath(path)) from err


@contextlib.contextmanager
def decoding(path: str | os.PathLike, what: str) -> Iterator[None]:
    """Turn whatever a decoder raises on one file's bytes into a DataError naming the file: that frame's skip.

    Decoders answer damaged bytes with their own exception types, and those change between versions (OpenCV 5's
    ``imdecode`` raises ``cv2.error`` on an empty buffer where 4.x returned None; numpy's npz reader gives
    ``zlib.error``, ``BadZipFile``, ``EOFError`` or ``ValueError``; trimesh many more). Wrapping only the decoding
    call keeps a bug elsewhere a traceback. DataError passes through unchanged.
    """
    try:
        yield
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001 - any decoder failure on these bytes is the file's problem
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = f"{type(exc).__name__}: {lines[-1][:200]}" if lines else type(exc).__name__
        raise DataError(path, None, f"cannot decode {what} ({detail})") from exc


class WorkerError(DataError):
    """A worker process could not start or died (a missing package, no GL, out of memory); see hoidata.engine.pool."""


def user_message(exc: BaseException) -> str | None:
    """The one-line message of an error the user can act on, or None for a bug (which keeps its traceback).

    DataError and ValueError: their text; OSError (disk full, read-only folder, permission): the file and the
    system's reason; MemoryError: "out of memory"; ImportError: the missing package.
    """
    if isinstance(exc, (DataError, ValueError)):
        lines = [line for line in str(exc).splitlines() if line.strip()]
        return lines[0] if lines else type(exc).__name__
    if isinstance(exc, OSError):
        reason = exc.strerror or str(exc) or type(exc).__name__
        names = [os.fspath(n) for n in (exc.filename, exc.filename2) if n is not None]
        return ": ".join([" -> ".join(names), reason] if names else [reason])
    if isinstance(exc, MemoryError):
        return "out of memory" + (f" ({exc})" if str(exc) else "")
    if isinstance(exc, ImportError):  # an install without a package (or its system library, e.g. EGL)
        return f"cannot import a required package: {exc}"
    return None


def run_cli(prog: str, work, debug: bool = False) -> int:
    """``work()``'s exit code; a user error (see :func:`user_message`) prints ``PROG: error: ...`` (just
    ``error: ...`` when ``prog`` is empty) and gives 2. With ``debug`` the exception propagates with its traceback.
    """
    try:
        return work()
    except Exception as exc:  # noqa: BLE001 - sorted into user errors and bugs right here
        message = user_message(exc)
        if debug or message is None:
            raise
        print(f"{prog + ': ' if prog else ''}error: {redact_urls(message)}", file=sys.stderr)
        return 2
