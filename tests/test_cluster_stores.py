"""Remote stores (issue 16): a store served over HTTP by a loopback server (127.0.0.1, started and stopped here)
reads, trains and evaluates with exactly the samples of its local folder, is split between ranks and workers the
same way, and keeps every check of the local loader (sizes, keys, counts, member sizes, clear errors naming the
URL). fsspec's HTTP filesystem needs aiohttp (the ``cluster`` extra); without it these tests are skipped."""

from __future__ import annotations

import functools
import http.server
import json
import shutil
import tarfile
import threading
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import torch

from hoidata import store
from hoidata.errors import DataError
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.shards import ShardStream, store_shards

pytestmark = pytest.mark.slow  # stores served over loopback HTTP, loaders with workers

pytest.importorskip("aiohttp")
pytest.importorskip("fsspec")


class _Quiet(http.server.SimpleHTTPRequestHandler):
    disable_nagle_algorithm = True  # headers and body are two writes: Nagle + delayed ACKs would add 40 ms each

    def log_message(self, *args):  # no request lines in the test output
        pass


class _Server(http.server.ThreadingHTTPServer):
    def handle_error(self, request, client_address):  # a client that stops reading early (a refused shard)
        pass


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(folder served, base URL): an HTTP server on 127.0.0.1 (a free port) in a thread, for this module only."""
    root = tmp_path_factory.mktemp("served")
    server = _Server(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(root)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield root, f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()
    thread.join(timeout=10)


def _publish(served, source: Path, name: str) -> tuple[Path, str]:
    """Copy a store folder under the served root; returns (the copy, its URL)."""
    root, base = served
    shutil.copytree(source, root / name)
    return root / name, f"{base}/{name}"


@pytest.fixture(scope="module")
def http_store(served, tiny_store_two_shards):
    return _publish(served, tiny_store_two_shards, "store")


def _samples(location, training: bool, workers: int = 0, epoch: int = 0) -> list[dict]:
    data = build_dataset([StoreSpec(location)], 4, epoch_samples=16 if training else None, n_hand=8, n_object=8,
                         training=training)
    data.set_epoch(epoch)
    return list(make_loader(data, workers))


def _same_batches(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b) and a
    for x, y in zip(a, b):
        assert x["key"] == y["key"] and x.keys() == y.keys()
        for name in x:
            if torch.is_tensor(x[name]):
                # rtol=atol=0: exact; NaN = NaN (the upstream-crop fields of a project record are NaN)
                torch.testing.assert_close(x[name], y[name], rtol=0, atol=0, equal_nan=True, msg=name)


def test_resolve_store_makes_only_explicit_url_strings_remote(tmp_path):
    assert isinstance(store.resolve_store("https://host:8000/a/b"), store.RemoteStore)
    assert store.resolve_store("HTTP://host/x").name == "x"
    for local in ("http:x", "s3:bucket/x", "pipe:curl http://x", "http:/host/x", "./https://x"):
        assert isinstance(store.resolve_store(local), Path), local
    assert isinstance(store.resolve_store(Path("gs://bucket/x")), Path)  # a Path is never parsed


@pytest.mark.parametrize("training", [False, True])
def test_an_http_store_gives_the_samples_of_its_folder(http_store, tiny_store_two_shards, training):
    _, url = http_store
    for workers, epoch in ((0, 0), (1, 1)):  # in the main process and in a DataLoader worker; two epochs
        local = _samples(tiny_store_two_shards, training, workers, epoch)
        _same_batches(_samples(url, training, workers, epoch), local)


def test_ranks_and_workers_get_the_same_shards_as_from_the_folder(http_store, tiny_store_two_shards, monkeypatch):
    _, url = http_store
    (_, remote), (_, local) = store_shards(url), store_shards(tiny_store_two_shards)
    assert [s.name for s in remote] == [Path(s).name for s in local]
    for world in (1, 2, 3):
        for rank in range(world):
            monkeypatch.setenv("RANK", str(rank))
            monkeypatch.setenv("WORLD_SIZE", str(world))
            for repeat in (False, True):
                state = type("Epoch", (), {"epoch": 3})()
                take = 6 if repeat else None
                names = [[Path(str(item["url"])).name for item, _ in zip(ShardStream(list(shards), 5, state, repeat)(),
                                                                         range(take or 10**6))]
                         for shards in (remote, local)]
                assert names[0] == names[1], (world, rank, repeat)


def test_training_and_evaluation_from_an_http_store_match_the_folder(http_store, tiny_store_two_shards, mano_dir,
                                                                      tmp_path):
    from test_faults_train import TINY

    from hoisdf.evaluate import main as evaluate
    from hoisdf.train import main as train

    _, url = http_store
    runs = {}
    for name, location in (("folder", tiny_store_two_shards), ("http", url)):
        out = tmp_path / name
        assert train(["--shards", f"{location}:1.0", "--mano", str(mano_dir), "--out", str(out), "--no-progress",
                      "--device", "cpu", *TINY, "train.max_steps=2", "train.record_keys=true"]) == 0
        assert evaluate(["--ckpt", str(tmp_path / "folder"), "--shards", str(location), "--mano", str(mano_dir),
                         "--out", str(out / "eval"), "--workers", "1", "--no-progress", "--plausibility", "0"]) == 0
        runs[name] = out
    keys = [(runs[n] / "keys-rank0.txt").read_text() for n in runs]
    assert keys[0] == keys[1] and len(keys[0].split()) == 4  # 2 steps of batch 2: the same samples
    losses = [[row for row in (runs[n] / "metrics.csv").read_text().splitlines() if ",samples_per_s," not in row]
              for n in runs]
    assert losses[0] == losses[1] and any(",total," in row for row in losses[0])  # the same steps, bit for bit
    metrics = [json.loads((runs[n] / "eval" / "metrics.json").read_text()) for n in runs]
    assert metrics[0]["samples"] == metrics[1]["samples"] == 16
    assert json.dumps(metrics[0]["overall"]) == json.dumps(metrics[1]["overall"]) and metrics[1]["stores"] == [url]
    hpe = [sorted(p.read_text() for p in (runs[n] / "eval").glob("dexycb_hpe_*.txt")) for n in runs]
    assert hpe[0] == hpe[1] and hpe[0]


def _cut(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-2048])


def _foreign(path: Path) -> None:
    from test_faults_build import _foreign_record, _rewrite_shard

    _rewrite_shard(path, _foreign_record)  # the index gets the new size and sha256: only the keys tell


@pytest.mark.parametrize("damage, match", [(_cut, "bytes, the index says"), (Path.unlink, "missing"),
                                           (_foreign, "the index has")])
def test_a_damaged_remote_shard_is_an_error_naming_its_url(served, tiny_store_two_shards, damage, match, request):
    folder, url = _publish(served, tiny_store_two_shards, f"damaged-{request.node.callspec.id}")
    damage(folder / "shard-000001.tar")
    with pytest.raises(DataError, match=match) as err:
        _samples(url, training=False, workers=1)
    assert str(err.value).startswith(f"{url}/shard-000001.tar")


def test_a_hostile_remote_member_is_refused_before_it_is_read(served, tiny_store_two_shards):
    from test_faults_build import _fix_index_entry

    folder, url = _publish(served, tiny_store_two_shards, "hostile")
    shard = folder / "shard-000000.tar"
    with tarfile.open(shard) as tar:
        first = next(m for m in tar if m.isreg())
    huge = store.MAX_MEMBER_BYTES + (1 << 20)
    info = tarfile.TarInfo(first.name)
    info.size = huge
    with open(shard, "wb") as f:  # a member beyond the limit; the file is sparse on disk, but served in full
        f.write(info.tobuf(tarfile.PAX_FORMAT))
        f.truncate(f.tell() + huge + 2048)
    _fix_index_entry(shard)
    tracemalloc.start()
    with pytest.raises(DataError, match=first.name.split(".")[0]) as err:
        _samples(url, training=False)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < huge // 4 and url in str(err.value), peak


def test_a_missing_index_or_a_dead_server_is_one_error_naming_the_url(served, tiny_store_two_shards, capsys,
                                                                      mano_dir, tmp_path):
    from hoisdf.train import main as train

    _, base = served
    with pytest.raises(DataError, match="index.zarr: missing"):
        store.read_index(f"{base}/no-such-store")
    folder, url = _publish(served, tiny_store_two_shards, "lost-chunk")
    sorted((folder / "index.zarr" / "labels" / "mirrored").rglob("c/*"))[0].unlink()
    with pytest.raises(DataError, match="labels/mirrored"):  # zarr over HTTP would read fill values: the checksum
        store.read_index(url)
    import socket

    with socket.socket() as sock:  # a port nothing listens on
        sock.bind(("127.0.0.1", 0))
        dead = f"http://127.0.0.1:{sock.getsockname()[1]}/store"
    assert train(["--shards", dead, "--mano", str(mano_dir), "--out", str(tmp_path / "run"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith(f"error: {dead}/index.zarr"), err


def test_a_store_url_weight_follows_the_path():
    from hoisdf.train import parse_store

    spec = parse_store("http://127.0.0.1:8000/stores/dexycb:0.6")
    assert spec.weight == 0.6 and str(spec.path) == "http://127.0.0.1:8000/stores/dexycb"
    assert parse_store("http://127.0.0.1:8000").weight == 1.0  # a port, not a weight
    assert str(parse_store("s3://bucket/store").path) == "s3://bucket/store"
    assert np.isclose(parse_store("gs://bucket/a/store:2").weight, 2.0)
