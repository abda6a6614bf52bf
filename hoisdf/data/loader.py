"""Training data for HOISDF: mixed, epoch-seeded WebDataset pipelines over ``hoidata`` stores.

One :class:`MixedStores` dataset reads several stores (e.g. real DexYCB with weight 1.0 and synthetic renders with
weight 0.6) and yields dicts of batched torch tensors (see :func:`build_dataset`); ``train.shuffle = "global"``
gives :mod:`hoisdf.data.global_shuffle`'s dataset instead, the same batches from one permutation per epoch.

How the pieces fit, per store::

    ShardStream   endless (training) sequence of this rank's shard paths: disjoint shard subsets per
                  rank when there are enough shards, else a slice of one common sequence of passes
    split_by_worker
                  each DataLoader worker keeps its own slice of the rank's sequence
    ReadShards    hoidata's strict tar reader, compared with the index (size, keys in order, count)
    -> _Shuffle (sample buffer) -> _Decode -> _ToArrays (SDF row sampling)

then :class:`_Mix` draws the next sample from store ``i`` with probability ``weight_i / sum(weights)`` and
:class:`_Batch` stacks samples into tensors; ``with_epoch`` cuts every worker at the same number of batches.
``augment.upstream``: _ToArrays ends with upstream's augmentation of each sample (:mod:`hoisdf.data.upstream_samples`).

Why an endless repeated shard stream rather than a finite list split between workers: with fewer shards than
``world_size * num_workers`` a finite split leaves some workers with nothing, and ``with_epoch`` then gives ranks
different batch counts (DDP hangs on the missing all-reduce). Repeating the reshuffled list before splitting means
worker ``w`` simply reads passes ``w, w + W, ...`` of the same shard: every worker has data, no sample is invented,
and for large stores (many shards) it degrades to the usual "disjoint shards per worker".
(``wds.ResampledShards`` draws shards with replacement: some read twice an epoch.)

Shards are read by :func:`hoidata.store.read_checked_shard`, from local files or, for a store given as an explicit
``http(s)://`` / ``s3://`` / ``gs://`` URL, from fsspec streams (:mod:`hoisdf.data.shards`), never through
webdataset's URL opener (which runs ``pipe:`` names as shell commands); an error in a DataLoader worker reaches
the caller as the same DataError (:func:`make_loader`), not as a worker traceback.

Epochs and workers: :meth:`MixedStores.set_epoch` stores the epoch in a holder object shared by every stage.
DataLoader workers receive a copy of the dataset at ``iter(loader)``, so call ``dataset.set_epoch(e)`` *before*
``for batch in loader`` each epoch; no ``persistent_workers=True`` (they keep the first epoch's copy).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import webdataset as wds
from torch.utils.data import default_collate, get_worker_info
from webdataset.utils import pytorch_worker_info

from hoidata import schema
from hoidata.errors import DataError
from hoidata.store import FRAME_IMAGE, KEY, decode_record
from hoisdf.data.global_shuffle import GlobalShuffle, record_table
from hoisdf.data.kinds import check_trainable, fill_absent_labels
from hoisdf.data.shards import Loader, ReadShards, ShardStream, errors_as_items, store_shards
from hoisdf.data.upstream_samples import finish_sample

_MIX_STREAM, _SHUFFLE_STREAM, _AUGMENT_STREAM = 1, 2, 3  # distinguish the RNG streams drawn from the same seed
SHUFFLES = ("stream", "global")  # train.shuffle: this module's streams, or global_shuffle's permutation


@dataclass(frozen=True)
class StoreSpec:
    """A store (a folder of ``shard-*.tar`` + ``index.zarr``, or its URL) and its relative sampling weight (> 0)."""

    path: Path | str
    weight: float = 1.0


class _EpochState:
    """Mutable holder of the current epoch, shared by reference between all stages of one dataset."""

    def __init__(self, epoch: int = 0):
        self.epoch = epoch


def _worker_seed(seed: int, epoch: int, stream: int, store: int) -> np.random.Generator:
    """An RNG for this (rank, worker): different per worker, reproducible for a fixed world layout."""
    rank, _, worker, _ = pytorch_worker_info()
    return np.random.default_rng([seed, epoch, stream, store, rank, worker])


def _key_seed(key: str) -> int:
    """A stable 63-bit integer from a record key (Python's hash() is salted per process)."""
    return int.from_bytes(hashlib.sha1(key.encode("utf-8")).digest()[:8], "little") >> 1


class _Shuffle:
    """Reservoir-style sample shuffle with a buffer of ``bufsize`` raw (undecoded) samples."""

    def __init__(self, bufsize: int, seed: int, state: _EpochState, store: int):
        self.bufsize, self.seed, self.state, self.store = bufsize, seed, state, store

    def __call__(self, src):
        if self.bufsize < 2:
            yield from src
            return
        rng = _worker_seed(self.seed, self.state.epoch, _SHUFFLE_STREAM, self.store)
        buf = []
        for sample in src:
            buf.append(sample)
            if len(buf) >= self.bufsize:
                i = int(rng.integers(len(buf)))
                buf[i], buf[-1] = buf[-1], buf[i]  # swap-pop: O(1) random removal
                yield buf.pop()
        rng.shuffle(buf)
        yield from buf


class _Decode:
    """Raw WebDataset sample -> :func:`hoidata.store.decode_record` output (errors name the shard).

    The heatmap PNG is checked (size limit, header, complete) but not decoded: augment_batch renders the heatmap
    from the joints, so no consumer reads the stored one (``hoidata verify`` decodes it)."""

    def __call__(self, src):
        for sample in src:
            yield decode_record(sample, sample.get("__url__", "<stream>"), undecoded=(schema.HEATMAP,))


def _pick_rows(rng: np.random.Generator, rows: np.ndarray, n: int) -> np.ndarray:
    """``n`` row indices from ``rows``: without replacement if there are enough, else with replacement."""
    if len(rows) == 0:
        raise ValueError("cannot sample SDF rows from an empty block")
    return rng.choice(rows, size=n, replace=len(rows) < n)


def _near_rows(rows: np.ndarray, dist: np.ndarray, near: float, n: int) -> np.ndarray:
    """Rows of a block whose |sdf| < near; if none are, the ``n`` closest rows (never empty)."""
    close = rows[np.abs(dist[rows]) < near]
    if len(close):
        return close
    return rows[np.argsort(np.abs(dist[rows]), kind="stable")[:n]]


def sample_sdf(sdf: np.ndarray, counts, rng: np.random.Generator, n_hand: int, n_object: int,
               near: float | None) -> dict[str, np.ndarray]:
    """Draw the SDF training points of one record.

    sdf: stored int16 (N, 6); counts: meta ``sdf_counts`` = [n_hand_set, n_object_set, n_uniform].
    Returns float32 arrays: hand_points (n_hand, 3) m relative to the hand root and hand_sdf (n_hand,) m
    (signed distance to the hand) from the hand-set and uniform rows; obj_points (n_object, 3) / obj_sdf
    (n_object,) (signed distance to the object) from the object-set and uniform rows; with ``near`` also
    hand_near_* / obj_near_* of the same sizes, drawn from the rows of the same pool whose |sdf| < near.
    The uniform rows (about 1 in 7 of each pool with the default build) teach the decoders the field far
    from the surface, which inference queries over its whole 64^3 grid (the reference's blocks mix them in
    the same way). Row indices of every draw are returned under ``<name>_rows`` (int64) for checking.
    """
    xyz, sdf_hand, sdf_obj, _ = schema.dequantize_sdf(sdf)
    return sample_sdf_arrays(xyz, sdf_hand, sdf_obj, counts, rng, n_hand, n_object, near)


def sample_sdf_arrays(xyz: np.ndarray, sdf_hand: np.ndarray, sdf_obj: np.ndarray, counts, rng: np.random.Generator,
                      n_hand: int, n_object: int, near: float | None) -> dict[str, np.ndarray]:
    """:func:`sample_sdf` on already dequantized float32 columns: xyz (N, 3), sdf_hand (N,), sdf_obj (N,)."""
    n_h, n_o, n_u = (int(c) for c in counts)
    uniform = np.arange(n_h + n_o, n_h + n_o + n_u)
    hand_rows, obj_rows = np.concatenate([np.arange(n_h), uniform]), np.concatenate([np.arange(n_h, n_h + n_o), uniform])
    draws = {"hand": (hand_rows, sdf_hand, n_hand), "obj": (obj_rows, sdf_obj, n_object)}
    out = {}
    for name, (rows, dist, n) in draws.items():
        picks = {name: _pick_rows(rng, rows, n)}
        if near is not None:
            picks[f"{name}_near"] = _pick_rows(rng, _near_rows(rows, dist, near, n), n)
        for prefix, idx in picks.items():
            out[f"{prefix}_points"] = xyz[idx]
            out[f"{prefix}_sdf"] = dist[idx]
            out[f"{prefix}_rows"] = idx.astype(np.int64)
    return out


def _f32(value) -> np.ndarray:
    return np.asarray(value, dtype=np.float32)


class _ToArrays:
    """Decoded record -> dict of per-sample numpy arrays in the final dtypes and layouts (see build_dataset)."""

    def __init__(self, seed: int, state: _EpochState, n_hand: int, n_object: int, near: float | None,
                 upstream: bool = False):
        self.seed, self.state, self.upstream = seed, state, upstream
        self.n_hand, self.n_object, self.near = n_hand, n_object, near

    def __call__(self, src):
        for rec in src:
            yield self.convert(rec)

    def convert(self, rec: dict) -> dict:
        meta, key = rec[schema.META], rec[KEY]
        if self.near is not None and "crop" in meta:
            raise DataError(None, key, "an upstream-crop record (record.crop = \"upstream\") is a 256 px test input "
                                       "without the context augmentation needs: train on project-crop records")
        if meta["kind"] != schema.FULL:  # an 'eval' record: only evaluation takes it, its hand labels as NaN
            if self.near is not None:
                raise DataError(None, key, f"a {meta['kind']!r} record lacks {', '.join(schema.EVAL_ABSENT)}")
            meta, rec = fill_absent_labels(meta, rec, self.n_hand, self.n_object)
        # seeded by the key, not by position, so the draw does not depend on the worker or shuffle
        rng = np.random.default_rng([self.seed, self.state.epoch, _key_seed(key)])
        out = sample_sdf(rec[schema.SDF], meta["sdf_counts"], rng, self.n_hand, self.n_object, self.near)
        out.update({
            "img": rec[schema.IMG],  # uint8 (S, S, 3): 1/4 of float32's bytes; augment_batch scales on the device
            "seg_bits": rec[schema.SEG],  # the four masks as the bits of one byte; augment_batch unpacks them
            "K": _f32(meta["K"]), "hand_root": _f32(meta["hand_root"]),
            "joints_3d": _f32(meta["joints_3d"]), "joints_2d": _f32(meta["joints_2d"]),
            "mano_pose": _f32(meta["mano_pose"]), "mano_betas": _f32(meta["mano_betas"]),
            "object_pose": _f32(meta["object_pose"]),
            "hand_box": _f32(meta["hand_box"]), "object_box": _f32(meta["object_box"]),
            "object_id": np.int64(meta["object_id"]),
            **crop_entries(meta),
            "mirrored": np.bool_(meta["mirrored"]),
            "is_synthetic": np.bool_(meta["dataset"] == "synthetic"),
            "key": key,
        })
        seed = self.upstream and [self.seed, self.state.epoch, _key_seed(key), _AUGMENT_STREAM]
        return finish_sample(rec[schema.IMG], meta, out, key, seed, rec.get(FRAME_IMAGE))


def crop_entries(meta: dict) -> dict:
    """A record's upstream-crop fields (schema.CROP_FIELDS) as batch entries: upstream_crop bool, grid_hand_box and
    grid_object_box (4,) f32 crop px, object_anchor (3,) f32 m; NaN (and False) for a project-crop record, so that
    every sample has the same entries and records of both crops batch together."""
    up = "crop" in meta
    return {"upstream_crop": np.bool_(up),
            **{name: _f32(meta[name] if up else np.full(schema.CROP_FIELDS[name][0], np.nan))
               for name in ("grid_hand_box", "grid_object_box", "object_anchor")}}


class _Mix:
    """Source stage: the next sample comes from store ``i`` with probability ``w_i / sum(w)``.

    A finite (evaluation) store that runs out is dropped and the rest are renormalised. With
    ``per_epoch=False`` (evaluation) the draw ignores the epoch, so every evaluation has the same order.
    """

    def __init__(self, stores: list, weights: list[float], seed: int, state: _EpochState, per_epoch: bool):
        self.stores, self.weights, self.seed, self.state = stores, weights, seed, state
        self.per_epoch = per_epoch

    def __call__(self):
        epoch = self.state.epoch if self.per_epoch else 0
        rng = _worker_seed(self.seed, epoch, _MIX_STREAM, 0)
        iters = [iter(s) for s in self.stores]
        w = np.asarray(self.weights, dtype=np.float64)
        while w.sum() > 0:
            i = int(rng.choice(len(iters), p=w / w.sum()))
            try:
                yield next(iters[i])
            except StopIteration:
                w[i] = 0.0


class _Batch:
    """Stack ``batch_size`` per-sample dicts into tensors; ``key`` stays a list of strings."""

    def __init__(self, batch_size: int, partial: bool):
        self.batch_size, self.partial = batch_size, partial

    def __call__(self, src):
        group = []
        for sample in src:
            group.append(sample)
            if len(group) == self.batch_size:
                yield collate(group)
                group = []
        if group and self.partial:
            yield collate(group)


def collate(samples: list[dict]) -> dict:
    """List of per-sample dicts (numpy values, ``key`` str) -> dict of batched tensors + ``key`` list.

    In a worker torch's default collation stacks straight into shared memory (no copy when the batch is
    sent); in the main process numpy stacks (torch.stack's threads stall on busy cores)."""
    if get_worker_info() is not None:
        out = default_collate([{k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in s.items()}
                               for s in samples])
    else:
        out = {k: [s[k] for s in samples] if k == "key" else torch.from_numpy(np.stack([s[k] for s in samples]))
               for k in samples[0]}
    out["img"] = out["img"].permute(0, 3, 1, 2)  # (B, S, S, 3) -> (B, 3, S, S), a view: channels-last strides
    return out


class MixedStores(wds.DataPipeline):
    """The dataset returned by :func:`build_dataset`; adds ``set_epoch`` and a per-worker epoch length."""

    def __init__(self, stages: list, state: _EpochState, epoch_samples: int | None, batch_size: int):
        super().__init__(*stages)
        self.state, self.epoch_samples, self.batch_size = state, epoch_samples, batch_size
        self.num_workers = 0  # set by make_loader; only used by __len__ in the main process

    def set_epoch(self, epoch: int, start: int = 0) -> int:
        """Select the shard order, sample shuffle, mixing and SDF draws of ``epoch`` (call before iter); returns
        ``start``: a stream cannot seek, so a resumed epoch draws and drops its first ``start`` batches."""
        self.state.epoch = int(epoch)
        return int(start)

    def batches_per_worker(self, num_workers: int, world_size: int = 1) -> int:
        """Batches each worker of each rank yields per epoch: epoch_samples // (B * workers * ranks), >= 1."""
        per = self.batch_size * max(1, num_workers) * max(1, world_size)
        return max(1, self.epoch_samples // per)

    def __len__(self) -> int:
        """Batches per epoch on this rank (needs epoch_samples; uses the make_loader worker count)."""
        if self.epoch_samples is None:
            raise TypeError("a single-pass dataset (training=False, no epoch_samples) has no length")
        _, world_size, _, _ = pytorch_worker_info()
        return self.batches_per_worker(self.num_workers, world_size) * max(1, self.num_workers)

    def __iter__(self):
        if self.epoch_samples is not None:
            # decided here, not at construction: only now do we know this worker's world layout
            _, world_size, _, num_workers = pytorch_worker_info()
            self.with_epoch(self.batches_per_worker(num_workers, world_size))
        if torch.utils.data.get_worker_info() is None:
            return super().__iter__()
        return errors_as_items(super().__iter__())


def _store_pipeline(urls: list[str], expected: dict, number: int, seed: int, state: _EpochState, training: bool,
                    shuffle_buffer: int, to_arrays: _ToArrays) -> wds.DataPipeline:
    """One store's sample stream (see the module docstring for the stages)."""
    return wds.DataPipeline(ShardStream(urls, seed, state, repeat=training), wds.split_by_worker, ReadShards(expected),
                            _Shuffle(shuffle_buffer if training else 0, seed, state, number), _Decode(), to_arrays)


def _check_args(stores: list[StoreSpec], batch_size: int, n_hand: int, n_object: int) -> None:
    if not stores:
        raise ValueError("build_dataset needs at least one store")
    for spec in stores:
        if not (np.isfinite(spec.weight) and spec.weight > 0):
            raise ValueError(f"{spec.path}: weight must be a positive number, got {spec.weight}")
    if min(batch_size, n_hand, n_object) < 1:
        raise ValueError(f"batch_size, n_hand and n_object must be >= 1, got {batch_size}, {n_hand}, {n_object}")


def build_dataset(stores: list[StoreSpec], batch_size: int, epoch_samples: int | None = None, seed: int = 0,
                  n_hand: int = 600, n_object: int = 200, near: float = 0.05, shuffle_buffer: int = 64,
                  training: bool = True, shuffle: str = "stream", progress: bool = True,
                  upstream: bool = False) -> MixedStores | GlobalShuffle:
    """A batched, weight-mixed, epoch-seeded IterableDataset over ``stores``.

    Each element is a dict (B = batch_size, S = crop size, H = S // 2, all tensors on the CPU):

    ==================  ===================  ======================================================
    img                 (B, 3, S, S) uint8   RGB crop 0-255, channels-last layout (float_image: [0, 1] f32)
    seg_bits            (B, H, H) uint8      the store's seg.png: bit 0 visible hand, 1 visible object, 2 amodal
                                             hand, 3 amodal object (augment.unpack_masks: (B, 4, H, H) planes)
    hand_points         (B, n_hand, 3) f32   metres, camera axes, relative to hand_root; hand-set and
                                             uniform rows
    hand_sdf            (B, n_hand) f32      metres, signed distance to the hand (negative inside)
    obj_points          (B, n_object, 3) f32 as hand_points, from the object-set and uniform rows
    obj_sdf             (B, n_object) f32    metres, signed distance to the object
    hand_near_points    (B, n_hand, 3) f32   training only: hand-set rows with |hand sdf| < near
    hand_near_sdf       (B, n_hand) f32      (HOISDF's "pre" points; drawn with replacement; if a
    obj_near_points     (B, n_object, 3) f32  record has no such row, its closest rows instead)
    obj_near_sdf        (B, n_object) f32
    *_rows              (B, n) int64         row index into the record's sdf.npy of each point above
    K                   (B, 3, 3) f32        intrinsics of img, crop pixels
    hand_root           (B, 3) f32           wrist joint, camera frame, metres
    joints_3d           (B, 21, 3) f32       camera frame, metres, DexYCB order
    joints_2d           (B, 21, 2) f32       crop pixels
    mano_pose           (B, 48) f32          flat-hand-mean axis-angle, camera frame
    mano_betas          (B, 10) f32          MANO shape
    object_pose         (B, 4, 4) f32        object model -> camera, metres
    hand_box            (B, 4) f32           x1, y1, x2, y2 of the projected hand mesh, img pixels
    object_box          (B, 4) f32           same for the object mesh
    object_id           (B,) int64           DexYCB class id 1..21
    upstream_crop       (B,) bool            record.crop = "upstream": img, K and the three below are upstream's
    grid_hand_box       (B, 4) f32           upstream's hand grid-filter box, img pixels (NaN: project crop)
    grid_object_box     (B, 4) f32           upstream's object grid-filter box, img pixels (NaN: project crop)
    object_anchor       (B, 3) f32           upstream's object anchor, camera frame, metres (NaN: project crop)
    mirrored            (B,) bool            a left hand mirrored to a right hand
    is_synthetic        (B,) bool            record from a synthetic store (meta dataset)
    key                 list of B str        record keys
    ==================  ===================  ======================================================

    SDF rows are drawn per record with an RNG seeded by (seed, epoch, key): ``n_hand`` from the hand and
    uniform sets and ``n_object`` from the object and uniform sets, without replacement when the pool is
    large enough.
    Mixing: the next sample comes from store i with probability weight_i / sum(weights).
    ``epoch_samples``: samples per epoch over all ranks and workers; default (training) the stores' sizes
    from their indexes scaled by their weights, ``sum(count_i * weight_i)``. Each worker yields
    ``batches_per_worker`` batches, so every rank and worker gives the same number.
    ``training=False``: no near points, no sample shuffle, one pass over each store's shards in stored
    order (a partial last batch is kept) unless ``epoch_samples`` is given.
    Call :meth:`MixedStores.set_epoch` before iterating each epoch (see the module docstring).
    ``shuffle="global"`` (training only): a :class:`~hoisdf.data.global_shuffle.GlobalShuffle`, one permutation per
    epoch over every store (weights: see there; ``progress``: a bar while it maps record offsets; no shuffle_buffer).
    ``upstream`` (training): each sample augmented as upstream's in its worker (S = 256, ``upstream_aug``).
    """
    _check_args(stores, batch_size, n_hand, n_object)
    if shuffle not in SHUFFLES or shuffle == "global" and not training:
        raise ValueError(f"shuffle must be one of {SHUFFLES} (global: training only), got {shuffle!r}")
    state = _EpochState()
    to_arrays = _ToArrays(seed, state, n_hand, n_object, near if training else None, upstream and training)
    pipes, sizes = [], []
    for number, spec in enumerate(stores):
        index, expected = store_shards(spec.path)
        if training:
            check_trainable(spec.path, index)
        sizes.append(sum(len(keys) for keys, _ in expected.values()))
        pipes.append(record_table(expected, str(spec.path), progress) if shuffle == "global" else
                     _store_pipeline(list(expected), expected, number, seed, state, training, shuffle_buffer, to_arrays))
    if epoch_samples is None and training:
        epoch_samples = max(1, round(sum(n * s.weight for n, s in zip(sizes, stores))))
    if shuffle == "global":
        return GlobalShuffle(pipes, [s.weight for s in stores], batch_size, epoch_samples, seed, state,
                             to_arrays.convert, collate)
    mix = _Mix(pipes, [s.weight for s in stores], seed, state, per_epoch=training)
    return MixedStores([mix, _Batch(batch_size, partial=not training)], state, epoch_samples, batch_size)


def make_loader(dataset: MixedStores | GlobalShuffle, num_workers: int, pin_memory: bool = False) -> Loader:
    """A :class:`Loader` (DataLoader, batch_size=None: no re-collation) over ``dataset``.

    Workers are not persistent, so a ``dataset.set_epoch(e)`` before each ``iter(loader)`` reaches them.
    """
    dataset.num_workers = num_workers
    return Loader(dataset, num_workers, pin_memory)
