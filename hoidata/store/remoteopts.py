"""Settings of remote reads (:class:`RemoteOptions`: timeouts, retries, the minimum throughput), how they become
fsspec's arguments (:func:`storage_options`), and the throughput guard of one request (:class:`Throughput`).

The settings come from environment variables (``HOIDATA_REMOTE_*``, docs/stores.md), so they reach every
DataLoader worker, torchrun rank and Slurm task without a flag.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

from hoidata.errors import DataError


@dataclass(frozen=True)
class RemoteOptions:
    """How long a remote read waits and how often it tries again (environment variables, see docs/stores.md).

    connect_timeout: seconds to open a connection. read_timeout: seconds without a single byte from the server
    (before the headers or within a body) after which a request counts as stalled. retries: further attempts of a
    request that failed without delivering a byte (a request that delivers bytes resets the count); between
    attempts the reader waits 0.5 s, 1 s, 2 s ... but never longer than ``read_timeout``. Defaults: a server that
    stalls is reported 3 x 15 s + 1.5 s after it stopped, or one idle timeout more (61.5 s) when the request it
    stalled in had delivered bytes: about a minute. min_rate, rate_window: a request whose server sends fewer than
    ``min_rate`` bytes per second over ``rate_window`` seconds counts as failed, like a stall (a trickle that keeps
    every idle timeout from firing would otherwise never end); 0 turns the guard off.
    """

    connect_timeout: float = 10.0
    read_timeout: float = 15.0
    retries: int = 2
    min_rate: float = 1024.0  # bytes per second
    rate_window: float = 60.0  # seconds

    ENV = {"connect_timeout": "HOIDATA_REMOTE_CONNECT_TIMEOUT", "read_timeout": "HOIDATA_REMOTE_READ_TIMEOUT",
           "retries": "HOIDATA_REMOTE_RETRIES", "min_rate": "HOIDATA_REMOTE_MIN_RATE",
           "rate_window": "HOIDATA_REMOTE_RATE_WINDOW"}
    MAY_BE_ZERO = ("retries", "min_rate")

    @classmethod
    def from_env(cls) -> RemoteOptions:
        """The options set by ``HOIDATA_REMOTE_CONNECT_TIMEOUT``, ``HOIDATA_REMOTE_READ_TIMEOUT``,
        ``HOIDATA_REMOTE_RATE_WINDOW`` (seconds, > 0), ``HOIDATA_REMOTE_RETRIES`` (a whole number >= 0) and
        ``HOIDATA_REMOTE_MIN_RATE`` (bytes per second, >= 0); unset ones keep their defaults. A bad value is one
        DataError naming the variable."""
        values = {}
        for field, name in cls.ENV.items():
            text = os.environ.get(name, "").strip()
            if not text:
                continue
            try:
                value = int(text) if field == "retries" else float(text)
            except ValueError:
                value = None
            if value is None or not math.isfinite(value) or value < 0 or (field not in cls.MAY_BE_ZERO and value == 0):
                want = ("a whole number >= 0" if field == "retries" else "bytes per second >= 0 (0: off)"
                        if field == "min_rate" else "a number of seconds > 0")
                raise DataError(name, None, f"expected {want}, got {text!r}")
            values[field] = value
        return cls(**values)

    def backoff(self, failures: int) -> float:
        """Seconds to wait before attempt ``failures + 1``."""
        return min(0.5 * 2 ** (failures - 1), self.read_timeout)


class TooSlow(Exception):
    """A request whose server sent less than the minimum throughput (:class:`Throughput`)."""


class Throughput:
    """The minimum-throughput guard of one file's requests: ``feed(n)`` for every ``n`` bytes received raises
    :class:`TooSlow` once a window of ``options.rate_window`` seconds has passed with fewer than
    ``options.min_rate`` bytes per second in it; then (and after a window fast enough) the next window starts.

    Only the time requests are being read counts (between :meth:`resume` and :meth:`pause`): a consumer that pauses
    between blocks is not the server's pace, and a server that breaks every connection after a few bytes is
    measured across its requests. The check runs as bytes arrive; a server that sends nothing at all is the idle
    timeout's case.
    """

    def __init__(self, options: RemoteOptions):
        self.options = options
        self.active, self.bytes, self.mark = 0.0, 0, None  # read time and bytes of this window; resumed at

    def resume(self) -> None:
        self.mark = time.monotonic()

    def pause(self) -> None:
        if self.mark is not None:
            self.active += time.monotonic() - self.mark
            self.mark = None

    def feed(self, n: int) -> None:
        self.bytes += n
        if not self.options.min_rate or self.mark is None:
            return
        now = time.monotonic()
        elapsed = self.active + now - self.mark
        if elapsed < self.options.rate_window:
            return
        sent = self.bytes
        self.active, self.bytes, self.mark = 0.0, 0, now  # the next window starts (also for the next attempt)
        if sent < self.options.min_rate * elapsed:
            raise TooSlow(f"the server sent {sent} bytes in {elapsed:.3g} s ({sent / elapsed:.3g} B/s, under the "
                          f"{self.options.min_rate:g} B/s of HOIDATA_REMOTE_MIN_RATE over "
                          f"HOIDATA_REMOTE_RATE_WINDOW={self.options.rate_window:g} s)")


def storage_options(scheme: str, options: RemoteOptions, query: str = "") -> dict:
    """fsspec keyword arguments for ``scheme`` with ``options`` as its timeouts. http(s): aiohttp's timeouts with
    no total cap (aiohttp's default is 300 s for the whole request, reading included), a connect timeout and an
    idle-read timeout; ``query`` (a store URL's query) is sent with every request, since zarr joins names onto the
    URL's path. s3://: botocore's connect/read timeouts and attempts (s3fs's ``config_kwargs``); gs://: aiohttp's
    timeouts for each request (gcsfs's ``requests_timeout``: gcsfs passes it to every request, so a session-wide
    timeout would be replaced by its default of none at all)."""
    import aiohttp

    timeout = aiohttp.ClientTimeout(total=None, connect=None, sock_connect=options.connect_timeout,
                                    sock_read=options.read_timeout)
    if scheme == "s3":
        return {"config_kwargs": {"connect_timeout": options.connect_timeout, "read_timeout": options.read_timeout,
                                  "retries": {"max_attempts": options.retries + 1}}}
    if scheme == "gs":
        return {"requests_timeout": timeout}
    return {"client_kwargs": {"timeout": timeout}, **({"params": _query_pairs(query)} if query else {})}


def _query_pairs(query: str) -> list[tuple[str, str]]:
    from urllib.parse import parse_qsl

    return parse_qsl(query, keep_blank_values=True)
