"""Remote reads against misbehaving servers (issue 25, item 1): a loopback HTTP server (127.0.0.1, started and stopped
here) whose first path segment picks a behaviour: stalls before the headers or mid-body, connections dropped
mid-body, a slow but steady trickle, no Content-Length / chunked / gzip-encoded bodies, Range ignored. The reader
(hoidata.store.httpread) must finish every read a healthy server can serve, resume a dropped one at its byte offset,
and report a stalled server as one line naming the URL within the configured timeouts (sub-second here)."""

from __future__ import annotations

import base64
import gzip
import http.server
import os
import re
import shutil
import socket
import sys
import threading
from pathlib import Path
from urllib.parse import parse_qs, unquote

import pytest

from hoidata import store
from hoidata.errors import DataError
from hoidata.store.httpread import UNKNOWN_SIZE, HttpReader, RemoteOptions, http_sizes, storage_options

pytestmark = pytest.mark.slow  # loopback HTTP servers that stall, drop and trickle

pytest.importorskip("aiohttp")
pytest.importorskip("fsspec")

DROP_AFTER = 3000  # bytes the "drop" server sends of each response before closing the connection
AUTH = "Basic " + base64.b64encode(b"alice:s3cr3t").decode()
TOKEN = "tok=s%2Fcr%2Bt"  # what the "token" server wants as the query of every request


class _Handler(http.server.BaseHTTPRequestHandler):
    """Serves ``root``; misbehaves on *.tar files only (the index is served plainly) unless the mode says all."""

    protocol_version = "HTTP/1.1"
    disable_nagle_algorithm = True  # headers and body are two writes: Nagle + delayed ACKs would add 40 ms each
    root: Path
    stop: threading.Event
    log: list

    def log_message(self, *args):
        pass

    def do_HEAD(self):
        self._answer(head=True)

    def do_GET(self):
        self._answer(head=False)

    def _plain(self, code: int, body: bytes = b"") -> None:
        self.send_response(code)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body if self.command == "GET" else b"")

    def _answer(self, head: bool) -> None:
        path, _, query = self.path.partition("?")
        mode, _, rest = unquote(path).lstrip("/").partition("/")
        self.log.append((self.command, mode, rest, self.headers.get("Range")))
        if self._refused(mode, rest, query):
            return None
        file = self.root / rest
        if not file.is_file():
            return self._plain(404)
        data = file.read_bytes()
        if mode == "gziprange":  # an object store holding every file gzip-encoded: ranges count encoded bytes
            data = gzip.compress(data, mtime=0)
        kind = (mode if rest.endswith(".tar") or mode == "gziprange"
                else "stallhead" if mode == "stallindex" and "/c/" in rest else "ok")
        if kind == "stallhead":
            self.stop.wait(60)
            return None
        if kind in ("nolen", "chunked", "gzip", "norange", "cutnorange", "trickleall"):
            return self._whole(kind, data, head)
        status, body, first = 200, data, 0
        ranged = self.headers.get("Range", "").removeprefix("bytes=").split("-")
        if len(ranged) == 2 and ranged[0].isdigit():
            first = int(ranged[0])
            last = min(int(ranged[1]) if ranged[1] else len(data) - 1, len(data) - 1)
            if first >= len(data):
                return self._plain(416)
            status, body = 206, data[first:last + 1]
        self.send_response(status)
        if kind == "flood":  # a chunked range answer that sends far more than its Content-Range says
            return self._chunked(body * 4, head, f"bytes {first}-{last}/{len(data)}")
        self.send_header("Content-Length", str(len(body)))
        if kind == "gziprange":
            self.send_header("Content-Encoding", "gzip")
        if status == 206:
            self.send_header("Content-Range", f"bytes {first}-{last}/{len(data)}")
        self.end_headers()
        if head:
            return None
        if kind == "stallbody":  # half of the first answer, then nothing; nothing at all after that
            self.wfile.write(body[: len(body) // 2] if first == 0 else b"")
            self.wfile.flush()
            self.stop.wait(60)
        elif kind == "drop":  # the connection breaks after DROP_AFTER bytes of every response
            self.wfile.write(body[:DROP_AFTER])
            self.close_connection = True
        elif kind == "trickle":
            self._trickle(body)
        elif kind == "slow":  # steady, 1 KiB every 20 ms: far longer in all than the idle timeout
            for start in range(0, len(body), 1024):
                self.wfile.write(body[start:start + 1024])
                self.wfile.flush()
                self.stop.wait(0.02)
        else:
            self.wfile.write(body)
        return None

    def _refused(self, mode: str, rest: str, query: str) -> bool:
        """Answer without the file where the mode says so: no token or password, busy, redirected."""
        fresh = sum(entry[1:3] == (mode, rest) for entry in self.log) == 1  # the first request for this file
        if mode == "token" and parse_qs(query) != parse_qs(TOKEN):
            self._plain(403)
        elif mode == "auth" and self.headers.get("Authorization") != AUTH:
            self._plain(401)
        elif mode == "busy" or (mode == "busyonce" and fresh):
            self._plain(503, b"try again later")
        elif mode in ("loop", "moved"):  # a redirect to itself, or to the same file in "ok" mode
            self.send_response(302)
            self.send_header("Location", self.path if mode == "loop" else f"/ok/{rest}")
            self.send_header("Content-Length", "0")
            self.end_headers()
        else:
            return False
        return True

    def _whole(self, kind: str, data: bytes, head: bool) -> None:
        """The whole file with status 200 whatever the Range header says; sized, close-delimited, chunked or
        gzip-encoded; "cutnorange" announces the whole file and closes after half of it."""
        self.send_response(200)
        body = gzip.compress(data) if kind == "gzip" else data
        if kind == "gzip":
            self.send_header("Content-Encoding", "gzip")
        if kind in ("gzip", "norange", "cutnorange", "trickleall"):
            self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        self.close_connection = True
        if kind == "chunked":
            return self._chunked(body, head)
        self.end_headers()
        if kind == "trickleall" and not head:
            self._trickle(body)
        elif not head:
            self.wfile.write(body[: len(body) // 2] if kind == "cutnorange" else body)
        return None

    def _trickle(self, body: bytes) -> None:
        """``body`` at 1 byte per 50 ms (20 B/s): never idle long enough for the 0.4 s read timeout."""
        for start in range(len(body)):
            if self.stop.wait(0.05):
                return
            self.wfile.write(body[start:start + 1])
            self.wfile.flush()

    def _chunked(self, body: bytes, head: bool, content_range: str | None = None) -> None:
        """The rest of a response (status sent) with ``body`` in chunked transfer encoding: no Content-Length."""
        self.send_header("Transfer-Encoding", "chunked")
        if content_range:
            self.send_header("Content-Range", content_range)
        self.end_headers()
        if head:
            return
        for start in range(0, len(body), 4000):
            piece = body[start:start + 4000]
            self.wfile.write(b"%x\r\n%s\r\n" % (len(piece), piece))
        self.wfile.write(b"0\r\n\r\n")


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):  # a client that gave up on a stalled answer
        pass


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """(served folder, base URL, request log); the server stops, and its stalled answers end, after the module."""
    root = tmp_path_factory.mktemp("evil")
    handler = type("Handler", (_Handler,), {"root": root, "stop": threading.Event(), "log": []})
    srv = _Server(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield root, f"http://127.0.0.1:{srv.server_address[1]}", handler.log
    handler.stop.set()
    srv.shutdown()
    srv.server_close()
    thread.join(timeout=10)


@pytest.fixture
def quick(monkeypatch):
    """Sub-second timeouts, a 1 s throughput window, one retry, and small blocks, so every stall, trickle and
    resume here takes a moment (and every healthy read shows the guard does not fire on it)."""
    monkeypatch.setenv("HOIDATA_REMOTE_CONNECT_TIMEOUT", "2")
    monkeypatch.setenv("HOIDATA_REMOTE_RATE_WINDOW", "1")
    monkeypatch.setenv("HOIDATA_REMOTE_READ_TIMEOUT", "0.4")
    monkeypatch.setenv("HOIDATA_REMOTE_RETRIES", "1")
    monkeypatch.setattr("hoidata.store.httpread.BLOCK_SIZE", 16 << 10)


@pytest.fixture(scope="module")
def blob(server):
    """A 100 kB file of random bytes on the server: (its bytes, its path below the modes)."""
    data = os.urandom(100_000)
    (server[0] / "blob.tar").write_bytes(data)
    return data, "blob.tar"


def _finishes(work, seconds: float = 60):
    """``work()``'s result or exception, run in a thread: a read that hangs fails the test instead of the suite."""
    out = {}

    def run():
        try:
            out["value"] = work()
        except BaseException as exc:  # noqa: BLE001 - handed back to the test
            out["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), "the remote read hung"
    if "error" in out:
        raise out["error"]
    return out["value"]


def _read_all(url: str, size: int | None = None) -> bytes:
    reader = HttpReader(url, size=size)
    try:
        return _finishes(lambda: reader.read())
    finally:
        reader.close()


def test_no_total_time_cap_only_connect_and_idle_read_timeouts(monkeypatch):
    # aiohttp's default ClientTimeout is 300 s for the whole request, reading included: never used here
    timeout = storage_options("http", RemoteOptions())["client_kwargs"]["timeout"]
    assert timeout.total is None and timeout.connect is None
    assert (timeout.sock_connect, timeout.sock_read) == (RemoteOptions.connect_timeout, RemoteOptions.read_timeout)
    # gcsfs hands its requests_timeout to every request (None there would mean no timeout at all); s3fs: botocore
    assert storage_options("gs", RemoteOptions()) == {"requests_timeout": timeout}
    assert storage_options("s3", RemoteOptions(retries=4))["config_kwargs"] == {
        "connect_timeout": 10.0, "read_timeout": 15.0, "retries": {"max_attempts": 5}}
    stall = RemoteOptions()  # a stalled server is reported within about a minute, also after a partial block
    assert (stall.retries + 2) * stall.read_timeout + sum(stall.backoff(i + 1) for i in range(stall.retries)) <= 65
    monkeypatch.setenv("HOIDATA_REMOTE_READ_TIMEOUT", "7.5")
    monkeypatch.setenv("HOIDATA_REMOTE_RETRIES", "0")
    assert RemoteOptions.from_env() == RemoteOptions(read_timeout=7.5, retries=0)
    monkeypatch.setenv("HOIDATA_REMOTE_MIN_RATE", "0")  # 0: the throughput guard is off
    monkeypatch.setenv("HOIDATA_REMOTE_RATE_WINDOW", "2.5")
    assert RemoteOptions.from_env() == RemoteOptions(read_timeout=7.5, retries=0, min_rate=0, rate_window=2.5)
    assert (RemoteOptions.min_rate, RemoteOptions.rate_window) == (1024, 60)  # the defaults: under 1 KiB/s for 60 s
    for name, bad in (("HOIDATA_REMOTE_READ_TIMEOUT", "0"), ("HOIDATA_REMOTE_CONNECT_TIMEOUT", "soon"),
                      ("HOIDATA_REMOTE_RETRIES", "1.5"), ("HOIDATA_REMOTE_READ_TIMEOUT", "inf"),
                      ("HOIDATA_REMOTE_MIN_RATE", "-1"), ("HOIDATA_REMOTE_RATE_WINDOW", "0")):
        monkeypatch.setenv(name, bad)
        with pytest.raises(DataError, match=f"^{name}: expected"):
            RemoteOptions.from_env()
        monkeypatch.delenv(name)


@pytest.mark.parametrize("mode", ["ok", "slow", "drop", "busyonce", "moved", "norange", "nolen", "chunked", "gzip",
                                  "gziprange"])
def test_a_healthy_server_is_read_whole_whatever_its_pace_and_framing(server, blob, quick, mode):
    """Slow: 100 kB at 1 KiB per 20 ms takes ~2 s, five times the 0.4 s idle timeout; drop: every response breaks
    after 3000 bytes, so the read resumes ~34 times; busyonce: 503 on the first request, then served; moved: a 302
    to the file in "ok" mode; gziprange: every answer gzip-encoded, ranges over the encoded bytes (an object store
    holding gzip files), so the file is asked for whole; the others answer 200 with the whole body, whatever the
    Range."""
    _, base, log = server
    data, name = blob
    start = len(log)
    assert _read_all(f"{base}/{mode}/{name}", len(data)) == data
    ranges = [r for method, m, _, r in log[start:] if method == "GET" and m == mode]
    if mode == "drop":  # each request asks for the bytes after the last one received
        offsets = [int(r.removeprefix("bytes=").split("-")[0]) for r in ranges]
        assert offsets[:3] == [0, DROP_AFTER, 2 * DROP_AFTER] and offsets == sorted(set(offsets))
    if mode == "ok":  # bounded blocks: no request asks for more than one block
        assert len(ranges) == -(-len(data) // (16 << 10)) and all(r.startswith("bytes=") for r in ranges)


@pytest.mark.parametrize("mode, size", [("ok", 100_000), ("norange", 6 << 20)])
def test_a_slow_consumer_never_times_out_a_healthy_server(server, quick, mode, size):
    """The consumer (a slow training step) pauses longer than the idle timeout between reads: in blocks (ok), each
    request is over before the pause; on one open stream (norange, larger than the socket buffers) aiohttp stops
    its idle clock while its buffer is full."""
    data = os.urandom(size)
    (server[0] / f"big-{mode}.tar").write_bytes(data)
    reader, got = HttpReader(f"{server[1]}/{mode}/big-{mode}.tar"), []
    piece = max(size // 5, 16 << 10)

    def consume():
        while chunk := reader.read(piece):
            got.append(chunk)
            threading.Event().wait(0.6)  # > HOIDATA_REMOTE_READ_TIMEOUT=0.4
        return b"".join(got)

    try:
        assert _finishes(consume) == data
    finally:
        reader.close()


@pytest.mark.parametrize("mode, what, arrived", [
    ("stallhead", "the server sent nothing for 0.4 s (HOIDATA_REMOTE_READ_TIMEOUT)", 0),
    ("stallbody", "the server sent nothing for 0.4 s (HOIDATA_REMOTE_READ_TIMEOUT)", (16 << 10) // 2),
    ("cutnorange", "the connection was closed before the response was complete", 50_000),
    ("busy", "HTTP 503 Service Unavailable", 0),
    ("loop", "more than 10 redirects", 0),
    ("flood", "the server sent more than the 16384 bytes of its Content-Range", 0)])
def test_a_stalled_or_breaking_server_is_one_line_naming_the_url(server, blob, quick, mode, what, arrived):
    """After a retry (not for a redirect loop or a flood: trying again changes nothing), the line says where it
    broke off; a range answer longer than its Content-Range is cut at the block (memory stays bounded)."""
    _, base, _ = server
    data, name = blob
    url = f"{base}/{mode}/{name}"
    with pytest.raises(DataError) as err:
        _read_all(url, len(data))
    line = str(err.value)
    assert line.startswith(f"{url}: cannot read: {what}") and "\n" not in line, line
    tries = "" if mode in ("loop", "flood") else " (2 attempts)"
    assert line.endswith(f"at byte {arrived} of {len(data)}{tries}"), line


@pytest.mark.parametrize("mode", ["trickle", "trickleall"])
def test_a_trickling_server_is_one_line_naming_the_url_and_its_rate(server, blob, quick, mode):
    """1 byte per 50 ms, in range answers (trickle) or one whole answer (trickleall): the 0.4 s idle timeout never
    fires and the 100 kB would take 83 minutes. Under the minimum throughput (1024 B/s over the 1 s window set here)
    a request fails like a stall: the bytes it brought are kept, it is tried once more, then one line."""
    _, base, log = server
    data, name = blob
    url = f"{base}/{mode}/{name}"
    start = len(log)
    with pytest.raises(DataError) as err:
        _read_all(url, len(data))
    line = str(err.value)
    rate = (r"the server sent \d+ bytes in [\d.]+ s \([\d.]+ B/s, under the 1024 B/s of HOIDATA_REMOTE_MIN_RATE over "
            r"HOIDATA_REMOTE_RATE_WINDOW=1 s\)")
    where = rf" at byte [1-9]\d* of {len(data)} \(2 attempts\)"  # the bytes that arrived were kept
    assert re.fullmatch(rf"{re.escape(url)}: cannot read: {rate}{where}", line), line
    assert len([entry for entry in log[start:] if entry[0] == "GET"]) == 2


def test_the_throughput_guard_counts_only_the_time_requests_are_read(monkeypatch):
    from hoidata.store.remoteopts import Throughput, TooSlow

    clock = [0.0]
    monkeypatch.setattr("hoidata.store.remoteopts.time.monotonic", lambda: clock[0])
    pace = Throughput(RemoteOptions(min_rate=100, rate_window=1))
    pace.resume()
    clock[0] = 0.6
    pace.feed(10)
    pace.pause()
    clock[0] = 500.0  # the consumer's pause between two requests: not the server's pace
    pace.resume()
    clock[0] = 500.3
    pace.feed(10)  # 20 bytes in 0.9 s of reading: the window is not over yet
    clock[0] = 500.5
    with pytest.raises(TooSlow, match=r"^the server sent 30 bytes in 1.1 s \(27.3 B/s, under the 100 B/s"):
        pace.feed(10)
    clock[0] = 501.0
    pace.feed(200)  # a new window: 200 bytes in 0.5 s, not over yet
    clock[0] = 501.6
    pace.feed(0)  # 200 bytes in 1.1 s: fast enough, the next window starts
    off = Throughput(RemoteOptions(min_rate=0, rate_window=1))
    off.resume()
    clock[0] = 1e6
    off.feed(1)  # min_rate 0: never too slow


def test_a_stalled_head_is_one_line_naming_the_url(server, blob, quick):
    _, base, _ = server
    url = f"{base}/stallhead/{blob[1]}"
    with pytest.raises(DataError, match=r"cannot read: the server sent nothing for 0.4 s .*\(2 attempts\)") as err:
        _finishes(lambda: http_sizes([f"{base}/ok/{blob[1]}", url]))
    assert str(err.value).startswith(url)


def test_a_stalled_index_read_is_one_line_naming_the_url(server, tiny_store_two_shards, quick):
    if not (server[0] / "store").exists():
        _publish(server, tiny_store_two_shards, "store")
    url = f"{server[1]}/stallindex/store"  # zarr.json answers, every chunk of the index stalls
    with pytest.raises(DataError, match="Timeout") as err:
        _finishes(lambda: store.read_index(url))
    assert str(err.value).startswith(f"{url}/index.zarr: ") and "\n" not in str(err.value)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="relies on Linux dropping SYNs to a full backlog")
def test_a_server_that_never_accepts_is_one_line_within_the_connect_timeout(quick, monkeypatch):
    monkeypatch.setenv("HOIDATA_REMOTE_CONNECT_TIMEOUT", "0.3")
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)  # never accepted; once the queue is full the kernel drops new SYNs: connect() waits
        url = f"http://127.0.0.1:{listener.getsockname()[1]}/store/shard-000000.tar"
        fillers = [socket.socket() for _ in range(3)]
        for sock in fillers:
            sock.setblocking(False)
            sock.connect_ex(listener.getsockname())
        try:
            with pytest.raises(DataError) as err:
                _finishes(lambda: http_sizes([url]))
        finally:
            for sock in fillers:
                sock.close()
    assert str(err.value) == (f"{url}: cannot read: no connection within 0.3 s (HOIDATA_REMOTE_CONNECT_TIMEOUT) "
                              "(2 attempts)")


def test_sizes_the_server_does_not_state_are_unknown_not_missing(server, blob, quick):
    _, base, _ = server
    data, name = blob
    modes = ["ok", "norange", "nolen", "chunked", "gzip", "gziprange"]
    sizes = http_sizes([f"{base}/{m}/{name}" for m in modes] + [f"{base}/ok/no-such.tar"])
    assert sizes == [len(data), len(data), UNKNOWN_SIZE, UNKNOWN_SIZE, UNKNOWN_SIZE, UNKNOWN_SIZE, None]


def _publish(server, source: Path, name: str) -> Path:
    shutil.copytree(source, server[0] / name)
    return server[0] / name


@pytest.mark.parametrize("mode", ["nolen", "chunked", "gzip", "gziprange", "drop"])
def test_a_store_served_without_sizes_or_with_drops_reads_as_its_folder(server, tiny_store_two_shards, quick, mode):
    from hoisdf.data.shards import store_shards

    if not (server[0] / "store").exists():
        _publish(server, tiny_store_two_shards, "store")
    url = f"{server[1]}/{mode}/store"
    index, expected = _finishes(lambda: store_shards(url))  # no shard is "missing"
    local = store.read_index(tiny_store_two_shards)
    assert index.keys == local.keys
    for source, (keys, size) in expected.items():
        records = list(store.read_checked_shard(source, keys, size))
        assert [r["__key__"] for r in records] == list(keys)
        assert [r["__key__"] for r in store.read_shard_members(source)] == list(keys)  # no size given: to the end


@pytest.mark.parametrize("mode", ["chunked", "gziprange"])
@pytest.mark.parametrize("change, problem", [(lambda b: b[:-2048], ": {} bytes read, expected exactly {}"),
                                             (lambda b: b + bytes(4096), ": longer than the {1} bytes expected")],
                         ids=["cut", "lengthened"])
def test_an_unsized_shard_is_counted_against_the_index(server, tiny_store_two_shards, quick, change, problem, mode,
                                                       request):
    """Served chunked (no Content-Length) or gzip-encoded (its sizes count encoded bytes), a cut or lengthened shard
    is still one error line naming its URL: the decoded bytes are counted against the index."""
    name = f"resized-{request.node.callspec.id}"
    folder = _publish(server, tiny_store_two_shards, name)
    shard = folder / "shard-000001.tar"
    shard.write_bytes(change(shard.read_bytes()))  # the index keeps the old size
    index = store.read_index(tiny_store_two_shards)
    info = index.shards[1]
    source = store.shard_source(f"{server[1]}/{mode}/{name}", info.name)
    with pytest.raises(DataError) as err:
        _finishes(lambda: list(store.read_checked_shard(source, index.keys[index.shard_rows(1)], info.size)))
    line = str(err.value)
    assert line.startswith(f"{server[1]}/{mode}/{name}/shard-000001.tar") and "\n" not in line, line
    assert problem.format(info.size - 2048, info.size) in line, line
