"""The per-process side of the record pipelines: resources loaded once per worker, and one store shard of records.

:class:`RecordWorker` holds what build-sdf, render-synthetic and export load once per process (the MANO layers,
the repaired objects, the mask renderers by record size) and builds one frame's record; it is build-sdf's worker
context for :mod:`hoidata.engine.engine` (``run(job)`` builds and writes one :class:`ShardJob`), and the other
pipelines' contexts hold one. :class:`RecordWorkerSpec` is the small picklable spec the engine sends to a worker
process to open it there.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata import store
from hoidata.atomic import write_json_atomic
from hoidata.errors import DataError
from hoidata.records import fingerprint
from hoidata.records.store_writer import extra_name
from hoidata.records.records import ObjectAsset


def load_object_asset(models_dir: Path, name: str, upstream: bool = False) -> ObjectAsset:
    """Repaired full-resolution object geometry and its 21-point box, for SDF and masks; ``upstream``: also the
    21-point box of its ``points.xyz`` as upstream's loaders build it (``record.crop = "upstream"``)."""
    from hoidata.geometry.upstream_crop import box21_upstream
    from hoidata.objects import (
        box21,
        load_object_mesh,
        load_points,
        object_mesh_path,
        object_points_path,
        repair_mesh,
    )

    geo, report = repair_mesh(load_object_mesh(object_mesh_path(models_dir, name)))
    points = box21_upstream(load_points(object_points_path(models_dir, name))) if upstream else None
    return ObjectAsset(name, np.asarray(geo.vertices), np.asarray(geo.faces), bool(report.watertight),
                       box21(np.asarray(geo.vertices)), points)


@dataclass
class ShardJob:
    """One shard to build: its frames and keys, the record settings, the store folder; ``root`` (the dataset
    folder) makes the shard's skips file fingerprint the files its frames read; ``extra`` goes into that file."""

    number: int
    frames: list
    keys: list[str]
    settings: object
    out: Path
    root: Path | None = None
    extra: dict | None = None


class RecordWorker:
    """One process's MANO layers, object assets and mask renderers, each loaded on first use and kept.

    Args:
        mano_dir: the MANO folder (MANO_RIGHT.pkl, MANO_LEFT.pkl).
        models_dir: the object models folder.
        crop_size: px; when given, the mask renderer of records of this size is made now, so a machine without
            GL fails when the worker starts (one WorkerError), not in its first record.
    """

    def __init__(self, mano_dir: Path, models_dir: Path, crop_size: int | None = None):
        import torch

        torch.set_num_threads(1)  # one process per core: torch's own threads would oversubscribe it
        self.mano_dir, self.models_dir = Path(mano_dir), Path(models_dir)
        self._manos: dict = {}
        self._objects: dict = {}
        self._meshes: dict = {}
        self._renderers: dict = {}
        if crop_size is not None:
            self.renderer(crop_size)

    def hand_model(self, side: str, fix_left_shapedirs: bool = False):
        """The float64 MANO layer of a side and left-hand shape convention, loaded once."""
        import torch

        from hoidata.hand import load_mano

        key = (side, fix_left_shapedirs or side == "right")
        if key not in self._manos:
            self._manos[key] = load_mano(self.mano_dir, side=side, fix_left_shapedirs=key[1], dtype=torch.float64)
        return self._manos[key]

    def object_asset(self, name: str, upstream: bool = False) -> ObjectAsset:
        """:func:`load_object_asset` of the worker's models folder, loaded once per (name, upstream)."""
        if (name, upstream) not in self._objects:
            self._objects[name, upstream] = load_object_asset(self.models_dir, name, upstream)
        return self._objects[name, upstream]

    def object_mesh(self, name: str):
        """The object's ``textured_simple.obj`` as the file holds it (a trimesh, not repaired), loaded once: what
        render-synthetic draws and export writes."""
        from hoidata.objects import load_object_mesh, object_mesh_path

        if name not in self._meshes:
            self._meshes[name] = load_object_mesh(object_mesh_path(self.models_dir, name))
        return self._meshes[name]

    def renderer(self, size: int):
        """The mask renderer of records of ``size`` px (masks at half of it), made on first use."""
        from hoidata.render.masks import MaskRenderer

        if size not in self._renderers:
            self._renderers[size] = MaskRenderer(size // 2, size // 2)
        return self._renderers[size]

    def record(self, frame, key: str, settings, source=None) -> dict:
        """One frame's encoded record members; ``source`` (when given) replaces ``frame.source`` in the stored meta
        only: the frame keeps the paths its files are read from."""
        from hoidata.records.records import build_eval_record, build_record

        crops = settings.crop_policy()
        obj = self.object_asset(frame.object_name, crops.needs_points)
        if not frame.has_hand_pose:  # e.g. HO-3D's evaluation split: no hand mesh, so no masks or SDF
            rec = build_eval_record(frame, obj, key, settings)
        else:
            mano = self.hand_model(frame.side, frame.fix_left_shapedirs)  # the model the labels were made with
            rec = build_record(frame, mano, obj, self.renderer(crops.record_size(frame, obj.upstream_box21)), key,
                               settings)
        if source is not None:
            rec["meta"]["source"] = source
        return store.encode_record(key, rec["img"], rec["seg"], rec["heatmap"], rec["sdf"], rec["meta"],
                                   rec.get("frame"))

    def run(self, job: ShardJob) -> tuple[int, int, list]:
        """Build and write one shard (empty when every frame was skipped); returns (number, records written, skips).

        The shard (tar and sidecar) is written first, then its skips file: a shard counts as done only with both.
        """
        records, skips, inputs = [], [], {}
        for frame, key in zip(job.frames, job.keys):
            source = None
            if job.root is not None:
                inputs.update(fingerprint.frame_inputs(frame, Path(job.root)))
                # the record's 'source' names files relative to the dataset folder, however --root was spelled; the
                # frame keeps its paths (the record recipe may read them: labels, HO-3D's meta for upstream crops)
                source = fingerprint.root_relative(frame.source, Path(job.root))
            try:
                records.append((key, self.record(frame, key, job.settings, source)))
            except (DataError, ValueError) as e:  # a broken frame is skipped with its reason, the build goes on
                skips.append({"frame_id": frame.frame_id, "reason": str(e), "path": str(frame.image_path)})
        store.write_shard(job.out, job.number, records)
        write_json_atomic(Path(job.out) / extra_name(job.number),
                          {"skipped": skips, "records": len(records), "inputs": inputs, **(job.extra or {})})
        return job.number, len(records), skips

    def close(self) -> None:
        """Release the renderers' GL contexts now (not whenever they are garbage-collected); the caches go too."""
        renderers, self._renderers = self._renderers, {}
        for renderer in renderers.values():
            renderer.close()
        self._manos, self._objects, self._meshes = {}, {}, {}


@dataclass(frozen=True)
class RecordWorkerSpec:
    """build-sdf's worker spec for the engine: ``open()`` makes a :class:`RecordWorker` in the worker process."""

    mano_dir: Path
    models_dir: Path
    crop_size: int

    def open(self) -> RecordWorker:
        return RecordWorker(self.mano_dir, self.models_dir, self.crop_size)
