"""Reading http(s) store files: sizes by HEAD and shards in bounded blocks, each request under an idle timeout.

Why not one streamed GET: a shard is consumed at the training pace, and a GET held open for the whole shard fails
when the consumer is slow (aiohttp's default 300 s *total* timeout, or the server's own idle limit) and hangs for
minutes when the server stalls. Here every request reads one block (:data:`BLOCK_SIZE`) with an HTTP range
request, as fast as the server sends it; a dropped or stalled connection is resumed at the byte offset where it
broke off; a failure without any progress is retried a bounded number of times with backoff. There is no cap on
the total time of a read that makes progress, only a minimum throughput while a request is being read
(:class:`~hoidata.store.remoteopts.Throughput`): a server that trickles fails like one that stalls.

Servers that ignore ``Range`` (200 with the whole body) or encode the body (``Content-Encoding``) are read as one
stream from the start instead, which is also resumed (the bytes before the offset are read again and dropped). An
encoded range answer (an object store holding gzip-encoded files ranges over the encoded bytes) is dropped and the
file asked for whole from then on: the ranges of an encoded body cannot be decoded one by one.
A size the server does not state (no ``Content-Length``, chunked, or encoded) is :data:`UNKNOWN_SIZE`, never
"missing"; the shard reader then checks the byte count against the index.

All requests go through fsspec's HTTP filesystem (its event loop and aiohttp session, so they work in forked
DataLoader workers and share connections with zarr's index reads), with :class:`RemoteOptions` as its timeouts.
"""

from __future__ import annotations

import asyncio
import math
import re
from collections import deque

from hoidata.errors import DataError
from hoidata.store.remoteopts import RemoteOptions, Throughput, TooSlow, storage_options

__all__ = ["BLOCK_SIZE", "UNKNOWN_SIZE", "HttpReader", "RemoteOptions", "http_sizes", "storage_options"]

UNKNOWN_SIZE = -1  # a served file whose size the server does not state (missing files are None)
BLOCK_SIZE = 8 << 20  # bytes per range request: one request never waits on the consumer
RETRY_STATUS = (408, 429, 502, 503, 504)  # a busy or restarting server: worth another try
CONCURRENT_SIZES = 16  # HEAD requests in flight at once


def http_filesystem(options: RemoteOptions):
    """fsspec's HTTP filesystem (one per process and options) with ``options`` as its timeouts."""
    import fsspec

    return fsspec.filesystem("http", **storage_options("http", options))


def _retryable(exc: BaseException) -> bool:
    import aiohttp

    return isinstance(exc, (asyncio.TimeoutError, aiohttp.ClientPayloadError, aiohttp.ServerDisconnectedError,
                            aiohttp.ClientOSError, ConnectionError, _Busy, TooSlow))


class _Busy(Exception):
    """A retryable HTTP status (RETRY_STATUS)."""


def _describe(exc: BaseException, options: RemoteOptions) -> str:
    """What went wrong with a request, in words, naming the setting that bounds it."""
    import aiohttp

    name = type(exc).__name__
    if isinstance(exc, (_Busy, TooSlow)):
        return str(exc)
    if isinstance(exc, aiohttp.TooManyRedirects):
        return f"more than {len(exc.history)} redirects (a redirect loop?)"
    if isinstance(exc, aiohttp.ClientConnectorError) and not isinstance(exc, asyncio.TimeoutError):
        return f"cannot connect ({exc.os_error.strerror or exc.os_error})" if exc.os_error else "cannot connect"
    if "Connect" in name and isinstance(exc, asyncio.TimeoutError):
        return f"no connection within {options.connect_timeout:g} s (HOIDATA_REMOTE_CONNECT_TIMEOUT)"
    if isinstance(exc, asyncio.TimeoutError):
        return f"the server sent nothing for {options.read_timeout:g} s (HOIDATA_REMOTE_READ_TIMEOUT)"
    if isinstance(exc, (aiohttp.ClientPayloadError, aiohttp.ServerDisconnectedError, ConnectionError)):
        return "the connection was closed before the response was complete"
    text = str(exc).strip().splitlines()
    return f"{name}: {text[0]}" if text and text[0] else name


def _encoded(headers) -> bool:
    """Whether a response's body is encoded (gzip, br, ...): its lengths and ranges count encoded bytes."""
    return headers.get("Content-Encoding", "identity").strip().lower() not in ("identity", "")


def stated_size(status: int, headers) -> int:
    """The size of a file from a 200 / 206 response's headers, or UNKNOWN_SIZE where the server does not state
    it (no Content-Length, chunked, or a Content-Encoding: the length then counts encoded bytes)."""
    if _encoded(headers):
        return UNKNOWN_SIZE
    if status == 206:
        total = headers.get("Content-Range", "").rpartition("/")[2].strip()
        return int(total) if total.isdigit() else UNKNOWN_SIZE
    length = headers.get("Content-Length", "").strip()
    return int(length) if length.isdigit() else UNKNOWN_SIZE


async def _attempts(url: str, options: RemoteOptions, request):
    """``await request()`` with up to ``options.retries`` more attempts after a retryable failure; the last
    failure is a DataError naming ``url``."""
    failures = 0
    while True:
        try:
            return await request()
        except DataError:
            raise
        except Exception as exc:  # noqa: BLE001 - aiohttp's and the OS's errors: sorted right here
            failures += 1
            if not _retryable(exc) or failures > options.retries:
                tries = f" ({failures} attempts)" if failures > 1 else ""
                raise DataError(url, None, f"cannot read: {_describe(exc, options)}{tries}") from None
            await asyncio.sleep(options.backoff(failures))


def _check_status(url: str, status: int, reason: str | None) -> None:
    if status in RETRY_STATUS:
        raise _Busy(f"HTTP {status} {reason or ''}".strip())
    if status >= 400:
        raise DataError(url, None, f"cannot read (HTTP {status}{' ' + reason if reason else ''})")


async def _size(fs, url: str, options: RemoteOptions) -> int | None:
    async def head():
        session = await fs.set_session()
        # identity: the size of the bytes themselves, not of a compressed body
        async with session.head(fs.encode_url(url), allow_redirects=True,
                                headers={"Accept-Encoding": "identity"}) as resp:
            if resp.status in (404, 410):
                return None
            if resp.status not in (405, 501):  # a server without HEAD: ask a GET's headers below
                _check_status(url, resp.status, resp.reason)
                return stated_size(resp.status, resp.headers)
        async with session.get(fs.encode_url(url), headers={"Accept-Encoding": "identity"}) as resp:
            if resp.status in (404, 410):
                return None
            _check_status(url, resp.status, resp.reason)
            return stated_size(resp.status, resp.headers)

    return await _attempts(url, options, head)


def http_sizes(urls: list[str], options: RemoteOptions | None = None) -> list[int | None]:
    """Each URL's size in bytes: None where the server says there is no such file (404/410), UNKNOWN_SIZE where
    it does not state one. Asked concurrently; any other failure is a DataError naming the URL."""
    from fsspec.asyn import sync

    options = options or RemoteOptions.from_env()
    fs = http_filesystem(options)
    gate = None

    async def one(url):
        async with gate:
            return await _size(fs, url, options)

    async def every():
        nonlocal gate
        gate = asyncio.Semaphore(CONCURRENT_SIZES)
        return await asyncio.gather(*(one(u) for u in urls))

    return list(sync(fs.loop, every))


_RANGE_RE = re.compile(r"^\s*bytes\s+(\d+)-(\d+)/(\d+|\*)\s*$", re.IGNORECASE)


class _Chunks(list):
    """Received bytes, chunk by chunk as they came (no copy into one buffer), and their count."""

    size = 0

    def append(self, chunk: bytes) -> None:
        super().append(chunk)
        self.size += len(chunk)


class HttpReader:
    """One http(s) file read once from its start (``read(n)``, ``close()``), block by block (see the module).

    url: the file's URL (user info and query as given). options: timeouts and retries (default: from the
    environment). size: the size the caller expects, for messages only. start, stop: read bytes [start, stop) only
    (one record of a shard: requests never ask past ``stop``; default the whole file). Any failure is one DataError
    naming the URL, what happened and the byte it happened at.
    """

    def __init__(self, url: str, options: RemoteOptions | None = None, size: int | None = None, start: int = 0,
                 stop: int | None = None):
        self.url, self.options, self.size, self.stop = url, options or RemoteOptions.from_env(), size, stop
        self.fs = http_filesystem(self.options)
        self.offset = start  # the next byte of the file to receive
        self._chunks, self._pos = deque(), 0  # received, not yet read (a block at most); position in the first
        self._stream, self._skip = None, 0  # the open 200 response of a server that ignores Range; bytes to drop
        self._end = False  # the end of the file was seen
        self._whole = False  # ask for the whole file, not a range (the server encodes its ranges)
        self._slow = 0  # requests in a row that ended under the minimum throughput
        self._pace = Throughput(self.options)

    def read(self, n: int = -1) -> bytes:
        want = math.inf if n is None or n < 0 else n
        parts, got = [], 0
        while got < want:
            if not self._chunks:
                if self._end:
                    break
                self._chunks.extend(self._next_block())
                continue
            chunk = self._chunks[0]
            take = int(min(want - got, len(chunk) - self._pos))
            parts.append(chunk[self._pos:self._pos + take])
            self._pos, got = self._pos + take, got + take
            if self._pos == len(chunk):
                self._chunks.popleft()
                self._pos = 0
        return b"".join(parts)

    def _next_block(self) -> list[bytes]:
        """The next bytes of the file as received ([] at its end): one block, or what arrived before a failure."""
        import time

        from fsspec.asyn import sync

        failures = 0
        while True:
            got = _Chunks()
            try:
                sync(self.fs.loop, self._fetch, got)
                self._slow = 0
                if got or self._end:
                    break
                raise DataError(self.url, None, f"cannot read: an empty response{self._where()}")
            except DataError:
                raise
            except Exception as exc:  # noqa: BLE001 - aiohttp's and the OS's errors: sorted right here
                slow = isinstance(exc, TooSlow)  # a failed attempt even though it delivered bytes
                if got and not slow:  # progress: hand it on; the next block resumes at the new offset
                    break
                if slow:
                    self._slow += 1
                failures = self._slow if slow else failures + 1
                if not _retryable(exc) or failures > self.options.retries:
                    tries = f" ({failures} attempts)" if failures > 1 else ""
                    raise DataError(self.url, None, f"cannot read: {_describe(exc, self.options)}"
                                                    f"{self._where(got.size)}{tries}") from None
                time.sleep(self.options.backoff(failures))
                if got:  # what arrived is kept; the next request resumes after it
                    break
        self.offset += got.size
        return got

    def _where(self, more: int = 0) -> str:
        """`` at byte N of SIZE``: where the read stands (``more`` bytes past the offset), for messages."""
        return f" at byte {self.offset + more}" + (f" of {self.size}" if self.size is not None and self.size >= 0
                                                   else "")

    async def _fetch(self, got: _Chunks) -> None:
        """Append the next block to ``got`` (a range request, or the open stream of a server without ranges)."""
        self._pace.resume()
        try:
            if self._stream is None:
                session = await self.fs.set_session()
                headers = {"Accept-Encoding": "identity"}
                if not self._whole:
                    headers["Range"] = f"bytes={self.offset}-{self.offset + self._room() - 1}"
                resp = await session.get(self.fs.encode_url(self.url), headers=headers)
                if resp.status == 206 and _encoded(resp.headers):  # a range of encoded bytes: ask for the whole
                    resp.close()
                    self._whole = True
                    del headers["Range"]
                    resp = await session.get(self.fs.encode_url(self.url), headers=headers)
                if resp.status != 206:
                    self._stream, self._skip = resp, self.offset  # closed below on any error
                    if resp.status == 416:  # nothing at or past the offset: the file ends there
                        self._end = True
                        return await self._close_stream()
                    if resp.status in (404, 410):
                        raise DataError(self.url, None, "missing (no such file at this URL)")
                    _check_status(self.url, resp.status, resp.reason)
                    return await self._read_stream(got)  # 200: the whole file from byte 0, read on in order
                async with resp:
                    await self._read_range(resp, got)
                return None
            return await self._read_stream(got)
        except BaseException:
            await self._close_stream()
            raise
        finally:
            self._pace.pause()

    async def _read_range(self, resp, got: _Chunks) -> None:
        match = _RANGE_RE.match(resp.headers.get("Content-Range", ""))
        if match is None or int(match.group(1)) != self.offset:
            raise DataError(self.url, None, f"cannot read: asked for bytes from {self.offset}, the server answered "
                                            f"Content-Range {resp.headers.get('Content-Range')!r}")
        asked = min(self._room(), int(match.group(2)) - self.offset + 1)
        async for chunk in resp.content.iter_any():
            got.append(chunk)
            self._pace.feed(len(chunk))
            if got.size > asked:  # a body without a length that goes on: memory stays bounded by the block
                raise DataError(self.url, None, f"cannot read: the server sent more than the {asked} bytes of "
                                                f"its Content-Range{self._where()}")
        total = match.group(3)
        if total.isdigit() and self.offset + got.size >= int(total) or self.offset + got.size == self.stop:
            self._end = True

    def _room(self) -> int:
        """Bytes the next block may hold: BLOCK_SIZE, or fewer before ``stop``."""
        return BLOCK_SIZE if self.stop is None else max(1, min(BLOCK_SIZE, self.stop - self.offset))

    async def _read_stream(self, got: _Chunks) -> None:
        content = self._stream.content
        while self._skip:  # received before the connection broke: read again and dropped
            chunk = await content.read(min(self._skip, 1 << 20))
            if not chunk:
                break
            self._skip -= len(chunk)
            self._pace.feed(len(chunk))
        room = self._room()
        while got.size < room:
            chunk = await content.read(room - got.size)
            if chunk:
                got.append(chunk)
                self._pace.feed(len(chunk))
            if not chunk or self.offset + got.size == self.stop:
                self._end = True
                await self._close_stream()
                return

    async def _close_stream(self) -> None:
        if self._stream is not None:
            self._stream.close()  # drops the connection: the rest of the body is never read
            self._stream = None

    def close(self) -> None:
        if self._stream is not None:
            from fsspec.asyn import sync

            try:
                sync(self.fs.loop, self._close_stream)
            except Exception:  # noqa: BLE001 - nothing more to read; a failing close changes nothing
                pass

    def __enter__(self) -> HttpReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
