"""Remote stores: a store given as an explicit ``http://``, ``https://``, ``s3://`` or ``gs://`` URL, read by fsspec.

Only :func:`hoidata.store.resolve_store` makes a :class:`RemoteStore`, and only from a ``str`` that starts with one
of those schemes; a ``Path`` or any other text is a local folder. A remote store is read, never written: its
index through zarr's fsspec store, its shard sizes with one request per shard (concurrent), and each shard as
one sequential stream (:func:`open_stream`; for http(s) in bounded range-request blocks that resume where a
connection broke, :mod:`hoidata.store.httpread`; any static file server works, with or without range requests).
Timeouts and retries: :class:`~hoidata.store.httpread.RemoteOptions` (environment variables). The shard reader
(:func:`hoidata.store.read_checked_shard`) applies the same checks to a stream as to a local file: size against
the index before reading, member sizes before reading a member, keys in order, the count and the tar's end.

fsspec needs a package per scheme: aiohttp for http(s) (in the ``cluster`` extra), s3fs for ``s3://``,
gcsfs for ``gs://`` (install them yourself; credentials come from their usual environment variables and files).
Every failure -- a missing package, a missing file, a refused connection, an HTTP error, a stalled server -- is a
DataError naming the URL. A URL prints with its user info and query values masked
(:func:`hoidata.errors.redact_urls`), so a password never reaches an error line, a run's ``config.json`` or a
result file. An http(s) store URL may carry a query (a token): file names join its path and every request sends
the query. A fragment (``#...``) is never sent to a server, so a store URL with one is refused, as is a query on
``s3://`` / ``gs://``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

from hoidata.errors import DataError, redact_urls
from hoidata.store.httpread import UNKNOWN_SIZE, HttpReader, RemoteOptions, http_sizes, storage_options

# scheme://authority: for http(s) [user info@]host[:port] (a ':' after the host is a port); for s3/gs a bucket,
# whose name has no ':' (so in 's3://bucket:2' the ':2' is a store weight, hoisdf.train.parse_store)
URL_RE = re.compile(r"^(?:(https?)://(?:[^/?#@\s]*@)?(?:\[[^\]/?#]*\]|[^/?#:@\[\]\s]+)(?::\d*)?"
                    r"|(s3|gs)://[^/?#:@\s]+)", re.IGNORECASE)
PACKAGES = {"http": "aiohttp", "https": "aiohttp", "s3": "s3fs", "gs": "gcsfs"}
STREAM_BLOCK = 8 << 20  # read-ahead block of s3:// and gs:// streams, bytes


def url_authority(text: str) -> str | None:
    """``scheme://authority`` of an explicit store URL, or None when ``text`` is not one."""
    match = URL_RE.match(text)
    return match.group(0) if match else None


def _scheme(url: str) -> str:
    return url.partition("://")[0].lower()


def _is_http(url: str) -> bool:
    return _scheme(url) in ("http", "https")


@dataclass(frozen=True, repr=False)  # repr too masks the URL's secrets (a list of them prints by repr)
class RemoteFile:
    """One file of a remote store, named by its URL (what errors print)."""

    url: str  # as requests need it: user info and query included

    def __str__(self) -> str:
        return redact_urls(self.url)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self)!r})"

    @property
    def name(self) -> str:
        return self.url.partition("?")[0].rstrip("/").rpartition("/")[2]


@dataclass(frozen=True, repr=False)  # repr too masks the URL's secrets (a list of them prints by repr)
class RemoteStore:
    """A store at a URL: ``RemoteStore("https://host/stores/dexycb")``; files are ``store.file("shard-000000.tar")``."""

    url: str  # as requests need it: user info and query included; str() masks them

    def __post_init__(self):
        base, query = self._split(self.url)
        object.__setattr__(self, "url", base + (f"?{query}" if query else ""))

    @staticmethod
    def _split(url: str) -> tuple[str, str]:
        """(the URL up to its path, without a trailing '/'; its query) of a valid store URL, else a DataError."""
        authority = url_authority(url)
        if authority is None or url[len(authority):len(authority) + 1] not in ("", "/", "?", "#"):
            raise DataError(url, None, "not a store URL (expected http://, https://, s3:// or gs://, a host or "
                                       "bucket, then the path)")
        if "#" in url:
            raise DataError(url, None, "a store URL cannot have a fragment ('#...': it is never sent to the server)")
        base, _, query = url.partition("?")
        if query and not _is_http(url):
            raise DataError(url, None, f"a {_scheme(url)}:// store URL takes no query ('?...')")
        return base.rstrip("/"), query

    def __str__(self) -> str:
        return redact_urls(self.url)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self)!r})"

    @property
    def base(self) -> str:
        """The URL without its query."""
        return self.url.partition("?")[0]

    @property
    def query(self) -> str:
        return self.url.partition("?")[2]

    @property
    def name(self) -> str:
        """The last part of the URL's path (the store folder's name)."""
        return self.base.rpartition("/")[2]

    def file(self, name: str) -> RemoteFile:
        """The store's file ``name`` (a path below the store): joined onto the URL's path, the query kept."""
        return RemoteFile(f"{self.base}/{name}" + (f"?{self.query}" if self.query else ""))

    def resolve(self) -> RemoteStore:
        """The same store (a URL is already absolute; Path.resolve's counterpart, so callers can compare)."""
        return self


def filesystem(url: str, options: RemoteOptions | None = None):
    """(fsspec filesystem, path within it) for a store URL, with ``options`` (default: from the environment) as its
    timeouts; a missing package is one line saying which."""
    scheme = _scheme(url)
    try:
        import fsspec

        return fsspec.core.url_to_fs(url, **storage_options(scheme, options or RemoteOptions.from_env()))
    except ImportError as exc:
        raise DataError(url, None, f"reading {scheme}:// stores needs the {PACKAGES.get(scheme, '?')} package "
                                   f"(pip install {PACKAGES.get(scheme, 'fsspec')}; {exc})") from None
    except ValueError as exc:  # fsspec: an unknown or unusable protocol
        raise DataError(url, None, f"cannot read this URL ({exc})") from None


def zarr_source(file: RemoteFile) -> tuple[str, dict]:
    """(URL, storage_options) that open ``file`` (a folder of the store) with zarr: the query travels as a request
    parameter, the timeouts as for every other read."""
    base, _, query = file.url.partition("?")
    filesystem(base)  # a missing package: one line
    return base, storage_options(_scheme(base), RemoteOptions.from_env(), query)


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
    """The size in bytes of each file: None where it is missing, UNKNOWN_SIZE where the server serves it without
    stating one; asked concurrently. Other errors are DataErrors naming the URL."""
    if not files:
        return []
    if all(_is_http(f.url) for f in files):
        filesystem(files[0].url)  # a missing package: one line
        return http_sizes([f.url for f in files])
    fs, _ = filesystem(files[0].url)
    paths = [filesystem(f.url)[1] for f in files]
    try:
        return [int(s) if s is not None else UNKNOWN_SIZE for s in fs.sizes(paths)]
    except FileNotFoundError:
        pass  # some are missing: ask one by one to tell which
    except Exception as exc:  # noqa: BLE001 - botocore, gcsfs errors: all mean "cannot read"
        raise DataError(files[0].url, None, _problem(exc)) from None
    sizes = []
    for file, path in zip(files, paths):
        try:
            size = fs.size(path)
            sizes.append(int(size) if size is not None else UNKNOWN_SIZE)
        except Exception as exc:  # noqa: BLE001
            if not _missing(exc):
                raise DataError(file.url, None, _problem(exc)) from None
            sizes.append(None)
    return sizes


class _Stream:
    """An s3:// or gs:// file opened for sequential reading (s3fs / gcsfs read ahead in range requests and retry
    themselves); any read failure is a DataError naming the URL and the byte."""

    def __init__(self, file: RemoteFile):
        self.file, self.offset = file, 0
        fs, path = filesystem(file.url)
        try:
            self._raw = fs.open(path, "rb", block_size=STREAM_BLOCK, cache_type="readahead")
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


def read_range(file: RemoteFile, start: int, length: int) -> bytes:
    """Bytes ``[start, start + length)`` of ``file`` (one record of a shard): http(s) in range requests of at most
    that length, resumed and retried as every read (:class:`~hoidata.store.httpread.HttpReader`); s3:// and gs://
    in one ranged GET. Fewer bytes than asked (a file cut or replaced) is a DataError naming the URL and the byte."""
    if _is_http(file.url):
        filesystem(file.url)  # a missing package: one line
        with HttpReader(file.url, start=start, stop=start + length) as reader:
            data = reader.read(length)
    else:
        fs, path = filesystem(file.url)
        try:
            data = fs.cat_file(path, start=start, end=start + length)
        except Exception as exc:  # noqa: BLE001 - botocore, gcsfs errors: all mean "cannot read"
            raise DataError(file.url, None, f"{_problem(exc)} at byte {start}") from None
    if len(data) != length:
        raise DataError(file.url, None, f"{len(data)} bytes from byte {start}, expected {length}: the file is "
                                        "truncated or replaced (hoidata verify checks the whole store)")
    return data


def open_stream(file: RemoteFile, size: int | None = None):
    """``file`` opened for one sequential pass (a context manager with ``read(n)``); ``size``: the bytes the caller
    expects (for messages)."""
    if _is_http(file.url):
        filesystem(file.url)  # a missing package: one line
        return HttpReader(file.url, size=size)
    return _Stream(file)
