"""Remote stores: a store given as an explicit ``http://``, ``https://``, ``s3://`` or ``gs://`` URL, read by fsspec.

Only :func:`hoidata.store.resolve_store` makes a :class:`RemoteStore`, and only from a ``str`` that starts with one
of those schemes; a ``Path`` or any other text is a local folder. A remote store is read, never written: its
index through zarr's fsspec store, its shard sizes with one request per shard (concurrent), and each shard as
one sequential stream (:func:`open_stream`; for http(s) a single GET, so any static file server works, without
range requests). The shard reader (:func:`hoidata.store.read_checked_shard`) applies the same checks to a stream
as to a local file: size against the index before reading, member sizes before reading a member, keys in
order, the count and the tar's end.

fsspec needs a package per scheme: aiohttp for http(s) (in the ``cluster`` extra), s3fs for ``s3://``,
gcsfs for ``gs://`` (install them yourself; credentials come from their usual environment variables and files).
Every failure -- a missing package, a missing file, a refused connection, an HTTP error -- is a DataError
naming the URL.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

from hoidata.errors import DataError

URL_RE = re.compile(r"^(https?|s3|gs)://[^/?#]+", re.IGNORECASE)  # scheme://authority (a ':' there is a port)
PACKAGES = {"http": "aiohttp", "https": "aiohttp", "s3": "s3fs", "gs": "gcsfs"}
STREAM_BLOCK = 8 << 20  # read-ahead block of s3:// and gs:// streams, bytes


def url_authority(text: str) -> str | None:
    """``scheme://authority`` of an explicit store URL, or None when ``text`` is not one."""
    match = URL_RE.match(text)
    return match.group(0) if match else None


@dataclass(frozen=True)
class RemoteFile:
    """One file of a remote store, named by its URL (what errors print)."""

    url: str

    def __str__(self) -> str:
        return self.url

    @property
    def name(self) -> str:
        return self.url.rstrip("/").rpartition("/")[2]


@dataclass(frozen=True)
class RemoteStore:
    """A store at a URL: ``RemoteStore("https://host/stores/dexycb")``; files are ``store.file("shard-000000.tar")``."""

    url: str

    def __post_init__(self):
        object.__setattr__(self, "url", self.url.rstrip("/"))
        if url_authority(self.url) is None:
            raise DataError(self.url, None, "not a store URL (expected http://, https://, s3:// or gs:// and a host)")

    def __str__(self) -> str:
        return self.url

    @property
    def name(self) -> str:
        """The last part of the URL's path (the store folder's name)."""
        return self.url.rpartition("/")[2]

    def file(self, name: str) -> RemoteFile:
        return RemoteFile(f"{self.url}/{name}")

    def resolve(self) -> RemoteStore:
        """The same store (a URL is already absolute; Path.resolve's counterpart, so callers can compare)."""
        return self


def filesystem(url: str):
    """(fsspec filesystem, path within it) for a store URL; a missing package is one line saying which."""
    scheme = url.partition("://")[0].lower()
    try:
        import fsspec

        return fsspec.core.url_to_fs(url)
    except ImportError as exc:
        raise DataError(url, None, f"reading {scheme}:// stores needs the {PACKAGES.get(scheme, '?')} package "
                                   f"(pip install {PACKAGES.get(scheme, 'fsspec')}; {exc})") from None
    except ValueError as exc:  # fsspec: an unknown or unusable protocol
        raise DataError(url, None, f"cannot read this URL ({exc})") from None


def _missing(exc: BaseException) -> bool:
    """Whether an fsspec error means "no such file" (fsspec's HTTP filesystem reports a refused connection or a
    server error as FileNotFoundError too, with the real error as its cause: that is not a missing file)."""
    cause = exc.__cause__
    return isinstance(exc, FileNotFoundError) and (cause is None or isinstance(cause, FileNotFoundError)
                                                   or getattr(cause, "status", None) in (404, 410))


def _problem(exc: BaseException) -> str:
    if _missing(exc):
        return "missing (no such file at this URL)"
    if isinstance(exc, FileNotFoundError) and exc.__cause__ is not None:
        exc = exc.__cause__
    text = str(exc).strip().splitlines()
    return f"cannot read ({type(exc).__name__}: {text[0] if text else ''})"


def remote_sizes(files: Sequence[RemoteFile]) -> list[int | None]:
    """The size in bytes of each file (None where it is missing), asked concurrently; other errors are DataErrors."""
    if not files:
        return []
    fs, _ = filesystem(files[0].url)
    paths = [filesystem(f.url)[1] for f in files]
    try:
        return [int(s) if s is not None else None for s in fs.sizes(paths)]
    except FileNotFoundError:
        pass  # some are missing: ask one by one to tell which
    except Exception as exc:  # noqa: BLE001 - aiohttp, botocore, gcsfs errors: all mean "cannot read"
        raise DataError(files[0].url, None, _problem(exc)) from None
    sizes = []
    for file, path in zip(files, paths):
        try:
            sizes.append(int(fs.size(path)))
        except Exception as exc:  # noqa: BLE001
            if not _missing(exc):
                raise DataError(file.url, None, _problem(exc)) from None
            sizes.append(None)
    return sizes


class _Stream:
    """A remote file opened for sequential reading; any read failure is a DataError naming the URL and the byte."""

    def __init__(self, file: RemoteFile):
        self.file, self.offset = file, 0
        fs, path = filesystem(file.url)
        streaming = {"block_size": 0} if file.url.lower().startswith("http") else {"block_size": STREAM_BLOCK,
                                                                                       "cache_type": "readahead"}
        try:
            self._raw = fs.open(path, "rb", **streaming)
        except Exception as exc:  # noqa: BLE001
            raise DataError(file.url, None, _problem(exc)) from None

    def read(self, n: int = -1) -> bytes:
        try:
            chunk = self._raw.read(n)
        except Exception as exc:  # noqa: BLE001
            raise DataError(self.file.url, None, f"{_problem(exc)} at byte {self.offset}") from None
        self.offset += len(chunk)
        return chunk

    def close(self) -> None:
        try:
            self._raw.close()
        except Exception:  # noqa: BLE001 - nothing more to read; a failing close changes nothing
            pass

    def __enter__(self) -> _Stream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_stream(file: RemoteFile) -> _Stream:
    """``file`` opened for one sequential pass (a context manager with ``read(n)``)."""
    return _Stream(file)
