"""Where the loader's samples come from: each rank's and worker's shard sequence, shards read strictly against
the index, and the DataLoader wrapper that carries a worker's errors to the main process.

A store is a local folder or, given as an explicit ``http(s)://``, ``s3://`` or ``gs://`` URL, a remote one
(:func:`hoidata.store.resolve_store` decides). Either way a shard is one :func:`hoidata.store.shard_source` (a Path
or a RemoteFile) read by :func:`hoidata.store.read_checked_shard` with the same checks, never through webdataset's
URL opener, which would run a store folder named ``pipe:...`` as a shell command. Ranks and workers get their
shards by position in the index's shard list, so a remote store is split exactly as its local copy.
"""

from __future__ import annotations

from itertools import count

import numpy as np
import torch
from webdataset.utils import pytorch_worker_info

from hoidata.errors import DataError
from hoidata.store import UNKNOWN_SIZE, read_checked_shard, read_index, resolve_store, shard_sizes, shard_source


class ShardStream:
    """Source stage: this rank's ``{"url": shard source}`` dicts (Path or RemoteFile), one shuffled pass after another.

    Training with at least as many shards as ranks: every epoch the shard list is shuffled by
    (seed, epoch) and rank r keeps every world-th shard of it, so ranks read disjoint shards (disjoint
    samples); passes over the rank's own shards are reshuffled by (seed, epoch, pass, rank). With fewer
    shards than ranks, all ranks partition one common endless sequence of passes (seeded by
    (seed, epoch, pass)) by position instead: every rank has data, and ranks read different passes.
    Evaluation (``repeat=False``): one pass in stored order, split by position. The split_by_worker
    stage that follows divides the rank's stream between its DataLoader workers the same way.
    """

    def __init__(self, urls: list[str], seed: int, state, repeat: bool):  # state: the epoch holder (.epoch)
        self.urls, self.seed, self.state, self.repeat = list(urls), seed, state, repeat

    def __call__(self):
        rank, world, _, _ = pytorch_worker_info()
        epoch, n = self.state.epoch, len(self.urls)
        if self.repeat and n >= world:
            mine = np.random.default_rng([self.seed, epoch]).permutation(n)[rank::world]
            for p in count():
                for i in np.random.default_rng([self.seed, epoch, p, rank]).permutation(mine):
                    yield {"url": self.urls[i]}
        position = 0
        for p in count():
            order = np.random.default_rng([self.seed, epoch, p]).permutation(n) if self.repeat else range(n)
            for i in order:
                if position % world == rank:
                    yield {"url": self.urls[i]}
                position += 1
            if not self.repeat:
                return


class ReadShards:
    """``{"url": shard source}`` -> the shard's raw records, each checked against the index (read_checked_shard)."""

    def __init__(self, expected: dict):
        self.expected = expected  # shard source (Path or RemoteFile) -> (keys in order, size in bytes)

    def __call__(self, src):
        for item in src:
            keys, size = self.expected[item["url"]]
            for members in read_checked_shard(item["url"], keys, size):
                yield {**members, "__url__": item["url"]}


_ERROR = "__error__"  # a worker's DataError or OSError, sent to the main process as an item (see make_loader)


def errors_as_items(batches):
    """In a DataLoader worker: pass a DataError or OSError on as one last item that make_loader raises again
    (torch would turn it into a RuntimeError holding the worker's traceback)."""
    try:
        yield from batches
    except DataError as exc:
        yield {_ERROR: ("data", exc.path, exc.field, exc.problem)}
    except OSError as exc:
        yield {_ERROR: ("os", exc.errno, exc.strerror or str(exc), exc.filename)}


def store_shards(location) -> tuple[object, dict]:
    """(the store's index, {shard source: (its keys in order, its size in bytes)} of its non-empty shards), after
    checking every shard file is there with the size the index gives (so a missing or cut shard is an error
    before the first step, not hours later; a remote store's sizes are asked concurrently). Sources are Paths, or
    RemoteFiles of a store URL. A store without records is an error."""
    path = resolve_store(location)
    index = read_index(path)
    sources = [shard_source(path, info.name) for info in index.shards]
    expected = {}
    for info, shard, size in zip(index.shards, sources, shard_sizes(sources)):
        if size != info.size and size != UNKNOWN_SIZE:  # unknown: a server that does not say; the reader counts
            problem = "missing" if size is None else f"{size} bytes, the index says {info.size}: truncated or replaced"
            raise DataError(shard, None, f"{problem} (hoidata verify checks the whole store)")
        if info.count:
            expected[shard] = (tuple(index.keys[index.shard_rows(info.number)]), info.size)
    if not expected:
        raise DataError(path, None, "the store holds no records")
    return index, expected


def _worker_failure(exc: RuntimeError) -> Exception:
    """torch's report of a worker that died or failed outside our stages -> one DataError line; else ``exc``."""
    lines = [line for line in str(exc).splitlines() if line.strip()]
    if not lines or "worker" not in lines[0].lower():
        return exc
    return DataError(None, None, f"a data loader worker failed: {lines[0]}"
                                 + (f" ({lines[-1].strip()})" if len(lines) > 1 else ""))


class Loader:
    """A DataLoader over already-batched ``dataset`` elements that raises a worker's DataError or OSError in
    the main process as it was raised, and a worker that failed to start or died as one DataError line."""

    def __init__(self, dataset: MixedStores, num_workers: int, pin_memory: bool):
        self.dataset = dataset
        self.loader = torch.utils.data.DataLoader(dataset, batch_size=None, num_workers=num_workers,
                                                  pin_memory=pin_memory, persistent_workers=False)

    def __iter__(self):
        # started here, not at the first batch: the DataLoader draws its seed from torch's RNG when it starts, and
        # the trainer restores a resumed run's RNG after iter() (a global-shuffle epoch reads no batch before that)
        try:
            return self._batches(iter(self.loader))
        except RuntimeError as exc:
            raise _worker_failure(exc) from None

    @staticmethod
    def _batches(batches):
        try:
            for batch in batches:
                if _ERROR in batch:
                    kind, *args = batch[_ERROR]
                    raise DataError(*args) if kind == "data" else OSError(*args)
                yield batch
        except RuntimeError as exc:
            raise _worker_failure(exc) from None

    def __len__(self) -> int:
        return len(self.dataset)
