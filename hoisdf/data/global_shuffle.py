"""The global shuffle (``train.shuffle = "global"``): every epoch one uniform permutation of the epoch's records,
over every store, read record by record at its byte span in its shard.

How an epoch is made (:func:`epoch_plan`, a pure function of the store sizes, weights, epoch length, seed and
epoch):

1. store ``i`` contributes ``k_i`` records, the epoch length ``E`` shared in proportion to ``size_i * weight_i``
   (largest remainders). With the default ``E = sum(size_i * weight_i)`` that is ``size_i * weight_i``: a store's
   weight is how many times each of its records is seen per epoch. Weight 1: every record once; 0.6: a fresh
   uniform 60 % of the store's records each epoch (drawn without replacement); 2: every record twice. All weights
   1 is upstream's concatenation of the datasets.
2. the ``E`` (store, row) pairs are permuted uniformly (numpy's PCG64 seeded by (seed, epoch)).
3. :func:`rank_batches`: the permutation is cut into global batches of ``batch_size * world`` records; rank ``r``
   takes the ``r``-th slice of ``batch_size`` of each, so every rank has ``E // (batch_size * world)`` batches (as
   DDP needs) and the last ``E mod (batch_size * world)`` records of the permutation are not trained on this epoch
   (upstream's ``drop_last=True``; a different, uniformly drawn set each epoch).
4. a rank's batches ``j = start, start + 1, ...`` go to DataLoader worker ``(j - start) mod workers``: the
   DataLoader takes batches from its workers in turn, so the rank sees its batches in the same order whatever
   the number of workers, and a resumed epoch starts at batch ``start`` without reading the ones before.

Records are read by :func:`hoidata.store.read_record` at the spans :func:`hoidata.store.record_spans` found when
the dataset was built (local shards: a header walk; remote shards: one sequential read each). A remote record is
one range request; a batch's requests run concurrently (threads), so a worker waits about one round trip per
batch rather than per record.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import get_worker_info
from webdataset.utils import pytorch_worker_info

from hoidata import schema
from hoidata.errors import DataError
from hoidata.store import RemoteFile, decode_record, read_record, record_spans
from hoisdf.data.shards import errors_as_items

_EPOCH_STREAM = 3  # the RNG stream of the epoch plan (loader.py uses 1 and 2 for its own draws from the seed)
REMOTE_THREADS = 16  # concurrent range requests per worker for a remote store


def store_counts(sizes, weights, epoch_samples: int) -> np.ndarray:
    """Records each store contributes to an epoch of ``epoch_samples``: in proportion to ``size * weight``,
    rounded by largest remainders (ties to the lower store number), summing to ``epoch_samples``."""
    share = np.asarray(sizes, np.float64) * np.asarray(weights, np.float64)
    exact = epoch_samples * share / share.sum()
    counts = np.floor(exact + 1e-9).astype(np.int64)
    rest = int(epoch_samples - counts.sum())
    counts[np.argsort(-(exact - counts), kind="stable")[:max(rest, 0)]] += 1
    return counts


def epoch_plan(sizes, weights, epoch_samples: int, seed: int, epoch: int) -> np.ndarray:
    """(E, 2) int64: the epoch's (store, row) pairs in training order (see the module docstring, steps 1-2)."""
    rng = np.random.default_rng([seed, epoch, _EPOCH_STREAM])
    parts = []
    for store, (n, k) in enumerate(zip(sizes, store_counts(sizes, weights, epoch_samples))):
        full, extra = divmod(int(k), int(n))
        rows = np.concatenate([np.tile(np.arange(n), full), rng.choice(n, extra, replace=False)]).astype(np.int64)
        parts.append(np.stack([np.full(len(rows), store, np.int64), rows], axis=1))
    plan = np.concatenate(parts)
    return plan[rng.permutation(len(plan))]


def rank_batches(plan: np.ndarray, batch_size: int, rank: int, world: int) -> np.ndarray:
    """(n_batches, batch_size, 2): rank ``rank``'s batches of ``plan`` (step 3 of the module docstring)."""
    n = len(plan) // (batch_size * world)
    return plan[:n * batch_size * world].reshape(n, world, batch_size, 2)[:, rank]


@dataclass
class RecordTable:
    """Where every record of one store lies: shard sources (Path or RemoteFile), each row's shard, key and span."""

    sources: list
    shard: np.ndarray  # (n,) int32: index into sources
    keys: list[str]
    spans: np.ndarray  # (n, 2) int64: byte offset and length in the shard

    @property
    def remote(self) -> bool:
        return any(isinstance(s, RemoteFile) for s in self.sources)

    def read(self, row: int) -> dict:
        """Row ``row``'s record, decoded (the heatmap checked, not decoded, as the streaming loader does)."""
        source = self.sources[self.shard[row]]
        offset, length = self.spans[row]
        members = read_record(source, self.keys[row], int(offset), int(length))
        return decode_record(members, str(source), undecoded=(schema.HEATMAP,))


def record_table(expected: dict, name: str, progress: bool = True) -> RecordTable:
    """The RecordTable of a store from :func:`hoisdf.data.shards.store_shards`'s ``{source: (keys, size)}``: every
    shard's spans found concurrently (8 threads), with a progress bar named ``name`` when ``progress``."""
    sources = list(expected)
    with ThreadPoolExecutor(8) as pool:
        jobs = pool.map(lambda s: record_spans(s, expected[s][0], expected[s][1]), sources)
        if progress:
            from tqdm import tqdm

            jobs = tqdm(jobs, total=len(sources), desc=f"record offsets of {name}", unit="shard", leave=False)
        spans = list(jobs)
    counts = [len(expected[s][0]) for s in sources]
    return RecordTable(sources, np.repeat(np.arange(len(sources), dtype=np.int32), counts),
                       [k for s in sources for k in expected[s][0]], np.concatenate(spans))


class GlobalShuffle(torch.utils.data.IterableDataset):
    """Batches of a uniformly permuted epoch (module docstring); the interface of :class:`hoisdf.data.MixedStores`.

    ``convert``: decoded record -> per-sample arrays (the loader's SDF draw, seeded by seed, epoch and key);
    ``collate``: list of samples -> batch; ``state``: the epoch holder ``convert`` reads.
    """

    def __init__(self, tables: list[RecordTable], weights: list[float], batch_size: int, epoch_samples: int,
                 seed: int, state, convert, collate):
        self.tables, self.weights, self.batch_size = tables, list(weights), batch_size
        self.epoch_samples, self.seed, self.state = epoch_samples, seed, state
        self.convert, self.collate = convert, collate
        self.start = 0  # the first batch of the epoch to yield (a resumed epoch)
        self.num_workers = 0  # set by make_loader

    def set_epoch(self, epoch: int, start: int = 0) -> int:
        """Select ``epoch``'s permutation and start at its batch ``start``; returns 0: none to skip by reading."""
        self.state.epoch, self.start = int(epoch), int(start)
        return 0

    def batches(self, rank: int = 0, world: int = 1) -> np.ndarray:
        """(n_batches, batch_size, 2) (store, row) pairs of the current epoch on ``rank`` of ``world``."""
        plan = epoch_plan([len(t.keys) for t in self.tables], self.weights, self.epoch_samples, self.seed,
                          self.state.epoch)
        self._count(world)  # an epoch without a batch is an error
        return rank_batches(plan, self.batch_size, rank, world)

    def _count(self, world: int) -> int:
        n = self.epoch_samples // (self.batch_size * world)
        if n < 1:
            raise DataError(None, "train.epoch_samples", f"an epoch of {self.epoch_samples} records holds no batch of "
                                                         f"{self.batch_size} for each of {world} process(es): lower "
                                                         "train.batch_size or raise train.epoch_samples")
        return n

    def __len__(self) -> int:
        """Batches per epoch on this rank: epoch_samples // (batch_size * ranks), whatever the workers."""
        return self._count(pytorch_worker_info()[1])

    def __iter__(self):
        rank, world, worker, workers = pytorch_worker_info()
        mine = self.batches(rank, world)[self.start:][worker::workers]
        batches = self._read(mine)
        return errors_as_items(batches) if get_worker_info() is not None else batches

    def _read(self, batches: np.ndarray):
        pool = ThreadPoolExecutor(min(REMOTE_THREADS, self.batch_size)) if any(t.remote for t in self.tables) else None
        try:
            for pairs in batches:
                fetch = (lambda p: self.tables[p[0]].read(int(p[1])))
                records = list(pool.map(fetch, pairs)) if pool is not None else [fetch(p) for p in pairs]
                yield self.collate([self.convert(rec) for rec in records])
        finally:
            if pool is not None:
                pool.shutdown(wait=False, cancel_futures=True)
