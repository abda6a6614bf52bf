"""train.shuffle = "global" (issue 31, item 2): one uniform permutation per epoch over every record of every store,
partitioned between ranks and workers, deterministic per seed, exact on resume, read locally and over http.

The epoch plan and its split are pure functions (fast tests); the loader, the trainer's resume and the http reads
use a toy store (slow tests)."""

from __future__ import annotations

import functools
import http.server
import threading
from math import comb

import numpy as np
import pytest
import torch

from hoidata import store
from hoidata.errors import DataError
from hoisdf.config import load_train_config
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.global_shuffle import epoch_plan, rank_batches, store_counts


def _split(plan, batch, world, workers, start=0):
    """{(rank, worker): its batches' (store, row) pairs}, as GlobalShuffle.__iter__ splits them."""
    return {(r, w): rank_batches(plan, batch, r, world)[start:][w::workers] for r in range(world) for w in range(workers)}


def test_every_record_once_per_epoch_across_ranks_and_workers():
    for world, workers in [(1, 1), (1, 2), (2, 2)]:
        plan = epoch_plan([30, 18], [1.0, 1.0], 48, seed=3, epoch=0)
        parts = _split(plan, 4, world, workers)
        pairs = np.concatenate([p.reshape(-1, 2) for p in parts.values()])
        assert len(pairs) == 48 and len({tuple(p) for p in pairs}) == 48  # 48 = 2 ranks x 6 batches x 4
        assert sorted(pairs[pairs[:, 0] == 1, 1].tolist()) == list(range(18))
        per_rank = [sum(len(parts[r, w]) for w in range(workers)) for r in range(world)]
        assert per_rank == [48 // (4 * world)] * world  # equal batches on every rank (DDP)


def test_the_remainder_is_dropped_and_differs_between_epochs():
    """50 records, batch 4, 2 ranks: 6 batches each, the last 2 records of each epoch's permutation left out."""
    dropped = []
    for epoch in range(4):
        plan = epoch_plan([50], [1.0], 50, seed=0, epoch=epoch)
        seen = np.concatenate([rank_batches(plan, 4, r, 2).reshape(-1, 2) for r in range(2)])
        assert len(seen) == 48 and len(np.unique(seen[:, 1])) == 48
        dropped.append(frozenset(set(range(50)) - set(seen[:, 1].tolist())))
    assert len(set(dropped)) > 1


def test_deterministic_per_seed_and_different_across_epochs_and_seeds():
    a = epoch_plan([40, 25], [1.0, 0.6], 55, seed=7, epoch=2)
    assert np.array_equal(a, epoch_plan([40, 25], [1.0, 0.6], 55, seed=7, epoch=2))
    assert not np.array_equal(a, epoch_plan([40, 25], [1.0, 0.6], 55, seed=7, epoch=3))
    assert not np.array_equal(a, epoch_plan([40, 25], [1.0, 0.6], 55, seed=8, epoch=2))


def test_weights_are_records_per_epoch():
    """Weight 1: every record once; 0.6: a fresh 60 % of the store each epoch; 2: every record twice."""
    assert store_counts([40, 25, 10], [1.0, 0.6, 2.0], 75).tolist() == [40, 15, 20]
    assert store_counts([3, 3], [1.0, 1.0], 5).sum() == 5  # an explicit epoch length is shared out exactly
    subsets = []
    for epoch in range(3):
        plan = epoch_plan([40, 25, 10], [1.0, 0.6, 2.0], 75, seed=0, epoch=epoch)
        assert sorted(plan[plan[:, 0] == 0, 1].tolist()) == list(range(40))
        second = plan[plan[:, 0] == 1, 1]
        assert len(second) == len(set(second.tolist())) == 15
        assert sorted(plan[plan[:, 0] == 2, 1].tolist()) == sorted(list(range(10)) * 2)
        subsets.append(frozenset(second.tolist()))
    assert len(set(subsets)) == 3


def _expected_distinct(groups: list[int], batch: int) -> float:
    """Mean distinct groups in a batch drawn without replacement from a uniform permutation, exactly."""
    n = sum(groups)
    return sum(1 - comb(n - g, batch) / comb(n, batch) for g in groups)


def test_batches_mix_groups_as_a_uniform_permutation():
    """The issue's toy store: 564 records stored as 48 sequence-camera groups of 11-12 consecutive rows, batch 22,
    2 ranks x 2 workers: distinct groups per batch match a uniform permutation's 18.0 (the stream gave 11.0)."""
    sizes = [12] * 36 + [11] * 12
    group = np.repeat(np.arange(48), sizes)
    expected = _expected_distinct(sizes, 22)
    assert abs(expected - 18.06) < 0.01  # the issue quotes 18.0
    counts = []
    for epoch in range(20):
        plan = epoch_plan([564], [1.0], 564, seed=0, epoch=epoch)
        for part in _split(plan, 22, 2, 2).values():
            counts += [len(np.unique(group[b[:, 1]])) for b in part]
    # 480 batches; the count's standard deviation is about 1.3, so the mean's is about 0.06
    assert abs(np.mean(counts) - expected) < 0.3, (np.mean(counts), expected)


def test_resume_starts_at_the_batch_it_stopped_before():
    plan = epoch_plan([64], [1.0], 64, seed=1, epoch=5)
    full, resumed = _split(plan, 4, 1, 2), _split(plan, 4, 1, 2, start=3)
    order = [b for i in range(8) for b in (full[0, 0][i:i + 1], full[0, 1][i:i + 1]) if len(b)]
    order_resumed = [b for i in range(8) for b in (resumed[0, 0][i:i + 1], resumed[0, 1][i:i + 1]) if len(b)]
    assert len(order) == 16 and all(np.array_equal(a, b) for a, b in zip(order[3:], order_resumed, strict=True))


def test_the_setting_is_checked_and_the_presets_choose_it():
    assert load_train_config("toy").train.shuffle == "stream"  # the main job's figures were made so
    for name in ("dexycb", "dexycb_full", "ho3d", "ho3d_render"):
        assert load_train_config(name).train.shuffle == "global", name
    with pytest.raises(DataError, match="train.shuffle"):
        load_train_config("toy", ['train.shuffle="buffer"'])
    with pytest.raises(ValueError, match="training only"):
        build_dataset([StoreSpec("unused")], 2, training=False, shuffle="global")


def test_an_epoch_without_a_batch_per_rank_is_one_line_naming_the_setting():
    from hoisdf.data.global_shuffle import GlobalShuffle, RecordTable

    table = RecordTable([], np.zeros(3, np.int32), ["a", "b", "c"], np.zeros((3, 2), np.int64))
    data = GlobalShuffle([table], [1.0], 4, 3, 0, None, None, None)
    with pytest.raises(DataError, match="'train.epoch_samples': an epoch of 3 records holds no batch of 4"):
        len(data)


# --------------------------------------------------------------------------------------------------
# through the loader, on a store


def _dataset(path, **kw):
    return build_dataset([StoreSpec(path)], 4, n_hand=8, n_object=8, shuffle="global", progress=False, **kw)


def _keys(batches) -> list[list[str]]:
    return [b["key"] for b in batches]


def _same(a: list[dict], b: list[dict]) -> bool:
    """Equal batches: keys, and every tensor (NaN where NaN: a project crop's upstream-crop entries)."""
    return _keys(a) == _keys(b) and all(np.array_equal(x[k].numpy(), y[k].numpy(), equal_nan=x[k].is_floating_point())
                                        for x, y in zip(a, b) for k in x if k != "key")


@pytest.mark.slow
def test_the_loader_reads_every_record_once_in_every_layout(tiny_store_two_shards, monkeypatch):
    """16 records in 2 shards, batch 4: one process, 2 workers, 2 simulated DDP ranks x 2 workers."""
    every = store.read_index(tiny_store_two_shards).keys
    one = _keys(make_loader(_dataset(tiny_store_two_shards), 0))
    two = _keys(make_loader(_dataset(tiny_store_two_shards), 2))
    assert one == two and sorted(k for b in one for k in b) == sorted(every)
    ranks = []
    for rank in (0, 1):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        data = _dataset(tiny_store_two_shards)
        ranks.append(_keys(make_loader(data, 2)))
        assert len(ranks[-1]) == len(data) == 2
    assert sorted(k for r in ranks for b in r for k in b) == sorted(every)


@pytest.mark.slow
def test_the_loader_is_deterministic_per_seed_and_epoch(tiny_store_two_shards):
    def epoch_batches(seed, epoch, start=0):
        data = _dataset(tiny_store_two_shards, seed=seed)
        assert data.set_epoch(epoch, start=start) == 0  # it seeks: the caller skips nothing
        return list(make_loader(data, 2))

    a, b = epoch_batches(0, 1), epoch_batches(0, 1)
    assert _same(a, b)
    assert _keys(epoch_batches(0, 2)) != _keys(a) and _keys(epoch_batches(1, 1)) != _keys(a)
    resumed = epoch_batches(0, 1, start=1)
    assert len(resumed) == 3 and _same(resumed, a[1:])


@pytest.mark.slow
def test_a_replaced_shard_is_an_error_naming_it(tiny_store_two_shards, tmp_path):
    import shutil

    copy = tmp_path / "store"
    shutil.copytree(tiny_store_two_shards, copy)
    data = _dataset(copy)
    shard = copy / "shard-000000.tar"
    index = store.read_index(copy)
    spans = store.record_spans(shard, index.keys[index.shard_rows(0)])
    raw = bytearray(shard.read_bytes())
    first, second = (slice(int(o), int(o + n)) for o, n in spans[:2])
    raw[first.start:first.start + 512] = raw[second.start:second.start + 512]  # record 0's header names record 1
    shard.write_bytes(bytes(raw))
    with pytest.raises(DataError, match="shard-000000.tar"):
        list(make_loader(data, 0))
    with pytest.raises(DataError, match="record 0 of the shard"):
        store.record_spans(shard, index.keys[index.shard_rows(0)])


class _RangeHandler(http.server.SimpleHTTPRequestHandler):
    """Serves a folder with Range support (206), logging every GET's Range header."""

    protocol_version = "HTTP/1.1"
    log: list
    ranges: bool  # False: a server that ignores Range and sends the whole file (200)

    def log_message(self, *args):
        pass

    def do_GET(self):
        path = self.translate_path(self.path.partition("?")[0])
        try:
            data = open(path, "rb").read()
        except OSError:
            self.send_error(404)
            return
        ranged = self.headers.get("Range", "").removeprefix("bytes=").split("-")
        self.log.append((self.path, self.headers.get("Range")))
        first, last = 0, len(data) - 1
        ranged = self.ranges and self.headers.get("Range") and ranged
        if ranged and len(ranged) == 2 and ranged[0].isdigit():
            first, last = int(ranged[0]), min(int(ranged[1] or last), last)
        self.send_response(206 if ranged else 200)
        self.send_header("Content-Length", str(last - first + 1))
        if ranged:
            self.send_header("Content-Range", f"bytes {first}-{last}/{len(data)}")
        self.end_headers()
        self.wfile.write(data[first:last + 1])


@pytest.mark.slow
@pytest.mark.parametrize("ranges", [True, False])
def test_a_remote_store_gives_the_local_batches_one_range_request_per_record(tiny_store_two_shards, ranges):
    """From a Range-capable server, each record is one request for exactly its span; from one that ignores Range,
    the same batches (each record read from the file's start up to its end)."""
    pytest.importorskip("aiohttp")
    log = []
    handler = type("Handler", (_RangeHandler,), {"log": log, "ranges": ranges})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                             functools.partial(handler, directory=str(tiny_store_two_shards.parent)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/{tiny_store_two_shards.name}"
        remote = _dataset(url)
        log.clear()
        remote.set_epoch(3)
        got = list(make_loader(remote, 0))
        local = _dataset(tiny_store_two_shards)
        local.set_epoch(3)
        want = list(make_loader(local, 0))
    finally:
        server.shutdown()
        server.server_close()
    assert _same(got, want)
    shard_gets = [r for p, r in log if p.endswith(".tar")]
    spans = {(int(o), int(o + n - 1)) for t in remote.tables for o, n in t.spans}
    assert len(shard_gets) == 16 and all(r is not None for r in shard_gets)  # one request per record, no more
    if not ranges:
        return
    assert {tuple(int(v) for v in r.removeprefix("bytes=").split("-")) for r in shard_gets} == spans


@pytest.mark.slow
def test_the_trainer_resumes_mid_epoch_exactly(tiny_store_two_shards, mano_dir, tmp_path):
    """3 + 3 steps equal 6 (8 batches an epoch): the same weights, and the resumed run trains on the batches the
    uninterrupted one trained on, starting at batch 3 of the epoch."""
    from hoidata.hand import load_mano
    from hoisdf.training.trainer import Trainer

    mano = load_mano(mano_dir, side="right")
    tiny = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
            "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
            "model.token_hidden=[48]", "model.hand_queries=16", "model.object_queries=8", "model.grid_resolution=8",
            "train.batch_size=2", "train.workers=0", "train.lr=1e-3", "train.val_every=0", "train.record_keys=true",
            'train.shuffle="global"']

    def trainer(run, steps):
        torch.manual_seed(0)
        cfg = load_train_config(None, tiny + [f"train.max_steps={steps}"])
        return Trainer(cfg, [StoreSpec(tiny_store_two_shards)], mano, run, torch.device("cpu"))

    full = trainer(tmp_path / "full", 6)
    full.fit(progress_bar=False)
    trainer(tmp_path / "split", 3).fit(progress_bar=False)
    second = trainer(tmp_path / "split", 6)
    payload = torch.load(tmp_path / "split" / "checkpoints" / "last.pt", weights_only=True)
    assert payload["progress"] == {"epoch": 0, "step": 3, "global_step": 3}
    second.fit(second.load(payload), progress_bar=False)
    keys = [(tmp_path / run / "keys-rank0.txt").read_text().split() for run in ("full", "split")]
    assert len(keys[0]) == 12 and keys[0] == keys[1]
    a, b = full.model.state_dict(), second.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a), [k for k in a if not torch.equal(a[k], b[k])][:5]
