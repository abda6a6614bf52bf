"""The per-process side of an export: :class:`ExportWorker`, the engine's worker context, writes one chunk of
frames (each frame's entry and files from its format, :mod:`~hoidata.export.handoccnet` or
:mod:`~hoidata.export.gsdf`, then the chunk's manifest). It holds what a process loads once: the MANO layers and
repaired objects (a :class:`~hoidata.records.RecordWorker`: what the store's SDF rows were computed on),
the raw object files, and the store whose SDF rows a gsdf export re-uses."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.export import gsdf, handoccnet
from hoidata.export.files import write_json
from hoidata.reading import decode_npy, parse_json
from hoidata.records import RecordWorker
from hoidata.shapes import Record, String, check


def chunk_path(work: Path, number: int) -> Path:
    """Chunk ``number``'s manifest in the export's work folder."""
    return Path(work) / f"chunk-{number:06d}.json"


def shard_rows(path: Path) -> dict[str, dict]:
    """``{key: {"sdf": int16 (N, 6), "meta": dict}}`` of a store shard's records that carry SDF rows (an 'eval'
    record has none); the tar and member names are checked by the store's reader, each member by the door."""
    from hoidata import schema, store

    out = {}
    for members in store.read_shard_members(path):
        if schema.SDF not in members:
            continue
        key = members.get("__key__")
        meta = check(parse_json(store.record_member(members, schema.META, path), path, f"{key}.{schema.META}"),
                     Record({"key": String()}), path, f"{key}.{schema.META}")
        sdf = decode_npy(members[schema.SDF], path, f"{key}.{schema.SDF}")
        if sdf.dtype != np.int16 or sdf.ndim != 2 or sdf.shape[1] != 6:
            raise DataError(path, f"{key}.{schema.SDF}", f"expected int16 (N, 6) rows, got {sdf.dtype} {sdf.shape}")
        out[meta["key"]] = {"sdf": sdf, "meta": meta}
    return out


@dataclass
class ExportJob:
    """One chunk to export: its frames with their consumer ids and record keys, the format, the output folder and
    the options every chunk carries (recorded in ``export.json``; ``opts["work"]``: the chunk manifests' folder)."""

    number: int
    fmt: str
    frames: list
    ids: list
    keys: list[str]
    out: str
    opts: dict


@dataclass(frozen=True)
class ExportWorkerSpec:
    """What a worker process needs to export chunks (picklable: the engine sends it to every worker)."""

    mano_dir: Path
    models_dir: Path
    store: str | None = None  # gsdf: the store whose SDF rows are re-used

    def open(self) -> ExportWorker:
        return ExportWorker(self.mano_dir, self.models_dir, self.store)


class ExportWorker:
    """One process's export state (see the module docstring)."""

    def __init__(self, mano_dir: Path, models_dir: Path, store: str | None = None):
        self.records = RecordWorker(mano_dir, models_dir)  # no renderer: exports draw no masks
        self.store = Path(store) if store else None
        self._raw: dict = {}
        self._store_keys: dict | None = None
        self._shards: dict = {}

    def mano(self, side: str, fix_left_shapedirs: bool = False):
        """The MANO layer (float64) of a side and left-hand shape convention, loaded once per worker."""
        return self.records.hand_model(side, fix_left_shapedirs)

    def hands_mean(self, side: str) -> np.ndarray:
        """MANO's ``hands_mean`` (45,) of a side (the relaxed mean pose the mean-relative convention is offset from)."""
        return self.mano(side).hands_mean.double().numpy()

    def object_asset(self, name: str):
        """The repaired full-resolution object (what the store's SDF rows were computed on)."""
        return self.records.object_asset(name)

    def raw_object(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """The object's ``textured_simple.obj`` as the file holds it: vertices (V, 3) m and faces (F, 3)."""
        if name not in self._raw:
            mesh = self.records.object_mesh(name)
            self._raw[name] = (np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64))
        return self._raw[name]

    def store_record(self, key: str) -> dict | None:
        """The decoded ``sdf.npy`` and ``meta.json`` of a store record (None: no store, or the key is not in it).

        The store's index maps keys to shards; a shard is read once and its records kept for the chunk's frames.
        """
        from hoidata import schema, store

        if self.store is None:
            return None
        if self._store_keys is None:
            index = store.read_index(self.store)
            names = {info.number: info.name for info in index.shards}
            self._store_keys = {str(k): names[int(s)] for k, s in zip(index.labels["key"], index.labels["shard"])}
        name = self._store_keys.get(key)
        if name is None:
            return None
        if name not in self._shards:  # chunks follow the reader's order, so one shard at a time suffices
            self._shards = {name: shard_rows(self.store / name)}
        return self._shards[name].get(key)

    def entry(self, fmt: str, frame, ident: int, key: str, out: Path, opts: dict) -> dict:
        """One frame's manifest entry: {'split', 'image', 'annotation', 'files', ...} (files relative to ``out``)."""
        if ident is None or int(ident) < 0:
            raise ValueError("the consumer's image id (the toolkit's sample index) is unknown for this frame")
        if fmt == "handoccnet":
            return handoccnet.frame_entry(self, frame, int(ident))
        return gsdf.frame_entry(self, frame, int(ident), key, out, opts)

    def run(self, job: ExportJob) -> tuple[int, int, list]:
        """One chunk's entries and files, then its manifest; returns (number, exported, skips)."""
        entries, skips = [], []
        for frame, ident, key in zip(job.frames, job.ids, job.keys):
            try:
                entries.append(self.entry(job.fmt, frame, ident, key, Path(job.out), job.opts))
            except (DataError, ValueError) as e:  # a frame that cannot be exported is skipped with its reason
                skips.append({"frame_id": frame.frame_id, "reason": str(e), "path": str(frame.image_path),
                              "sample_index": int(frame.sample_index)})
        write_json(chunk_path(Path(job.opts["work"]), job.number), {"entries": entries, "skipped": skips})
        return job.number, len(entries), skips

    def close(self) -> None:
        self.records.close()
        self._shards, self._raw = {}, {}
