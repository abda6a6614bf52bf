"""Per-process state of an export: MANO layers and object meshes loaded once per worker, and the store whose
SDF rows a gsdf export re-uses (the formats, :mod:`~hoidata.export.handoccnet` and :mod:`~hoidata.export.gsdf`,
ask here)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

_STATE: dict = {}


def init(mano_dir: Path, models_dir: Path, store: str | None = None) -> None:
    """Worker set-up: one thread for torch, empty caches, the store's key -> shard map (if a store is given)."""
    import torch

    torch.set_num_threads(1)
    _STATE.clear()
    _STATE.update(mano_dir=Path(mano_dir), models_dir=Path(models_dir), manos={}, assets={}, raw={}, shards={},
                  store=Path(store) if store else None, store_keys=None)


def mano(side: str, fix_left_shapedirs: bool = False):
    """The MANO layer (float64) of a side and left-hand shape convention, loaded once per worker."""
    import torch

    from hoidata.hand import load_mano

    key = (side, fix_left_shapedirs or side == "right")
    if key not in _STATE["manos"]:
        _STATE["manos"][key] = load_mano(_STATE["mano_dir"], side=side, fix_left_shapedirs=key[1], dtype=torch.float64)
    return _STATE["manos"][key]


def hands_mean(side: str) -> np.ndarray:
    """MANO's ``hands_mean`` (45,) of a side (the relaxed mean pose the mean-relative convention is offset from)."""
    return mano(side).hands_mean.double().numpy()


def object_asset(name: str):
    """The repaired full-resolution object (runner.object_asset: what the store's SDF rows were computed on)."""
    from hoidata.pipeline.runner import object_asset as load

    if name not in _STATE["assets"]:
        _STATE["assets"][name] = load(_STATE["models_dir"], name)
    return _STATE["assets"][name]


def raw_object(name: str) -> tuple[np.ndarray, np.ndarray]:
    """The object's ``textured_simple.obj`` as the file holds it: vertices (V, 3) m and faces (F, 3)."""
    from hoidata.objects import load_object_mesh, object_mesh_path

    if name not in _STATE["raw"]:
        mesh = load_object_mesh(object_mesh_path(_STATE["models_dir"], name))
        _STATE["raw"][name] = (np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64))
    return _STATE["raw"][name]


def store_record(key: str) -> dict | None:
    """The decoded ``sdf.npy`` and ``meta.json`` of a store record (None: no store, or the key is not in it).

    The store's index maps keys to shards; a shard is read once and its records kept for the chunk's frames.
    """
    from hoidata import schema, store

    if _STATE["store"] is None:
        return None
    if _STATE["store_keys"] is None:
        index = store.read_index(_STATE["store"])
        names = {info.number: info.name for info in index.shards}
        _STATE["store_keys"] = {str(k): names[int(s)] for k, s in zip(index.labels["key"], index.labels["shard"])}
    name = _STATE["store_keys"].get(key)
    if name is None:
        return None
    if name not in _STATE["shards"]:
        _STATE["shards"] = {name: {}}  # chunks follow the reader's order, so one shard at a time suffices
        for members in store.read_shard_members(_STATE["store"] / name):  # checks the tar and member names
            if schema.SDF not in members:  # an 'eval' record: no SDF rows to re-use
                continue
            meta = json.loads(members[schema.META])
            sdf = np.load(io.BytesIO(members[schema.SDF]), allow_pickle=False)
            schema.dequantize_sdf(sdf)  # raises ValueError unless int16 (N, 6)
            _STATE["shards"][name][meta["key"]] = {"sdf": sdf, "meta": meta}
    return _STATE["shards"][name].get(key)
