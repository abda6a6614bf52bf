"""Inference over stores: a checkpoint's predictions and the ground truth, per sample, in stored order.

The network sees the deterministic central crop; hand outputs are wrist-relative and placed with the
ground-truth wrist (as HOISDF). Everything collected is numpy float64, metres, camera frame.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from hoidata.errors import DataError
from hoidata.store import read_index
from hoisdf.config import config_from_dict
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.augment import augment_batch
from hoisdf.scoring.submissions import DEXYCB_TIP_JOINTS, HO3D_TIP_VERTICES
from hoisdf.model.precision import autocast, trace_dtypes
from hoisdf.training.checkpoint import CHECKPOINTS, find_checkpoint, load_checkpoint, load_weights
from hoisdf.training.losses import hand_targets, mirrored_shape_mano

SDF_KEYS = ("hand_points", "hand_sdf", "obj_points", "obj_sdf", "hand_rows", "obj_rows")


@dataclass
class Collected:
    """Per-sample predictions and ground truth (N samples): ``arrays`` hold numpy float64, metres, camera frame."""

    keys: list[str] = field(default_factory=list)
    store: list[int] = field(default_factory=list)  # index into the evaluated stores
    rows: list[int] = field(default_factory=list)  # row of the record in its store's index (stored order)
    names: list[str] = field(default_factory=list)  # object names
    frame_ids: list[str] = field(default_factory=list)
    arrays: dict[str, list] = field(default_factory=dict)  # joints, gt_joints, root, obj_pose, ... (chunks)
    vis: dict[str, dict] = field(default_factory=dict)  # key -> image, K and query points of the first samples
    dtypes: dict[str, str] = field(default_factory=dict)  # stage / output -> dtype seen on the first batch

    def add(self, **chunks) -> None:
        for k, v in chunks.items():
            self.arrays.setdefault(k, []).append(np.asarray(v, dtype=np.float64))

    def get(self, name: str) -> np.ndarray | None:
        chunks = self.arrays.get(name)
        return np.concatenate(chunks) if chunks else None

    def sort(self) -> None:
        """Put the samples in stored order (store, then index row), whatever order the loader workers gave."""
        order = np.lexsort((self.rows, self.store))
        for name in ("keys", "store", "rows", "names", "frame_ids"):
            setattr(self, name, [getattr(self, name)[i] for i in order])
        self.arrays = {k: [self.get(k)[order]] for k in self.arrays}


def resolve_device(device: str | torch.device | None) -> torch.device:
    return torch.device(device) if device else torch.device("cuda" if torch.cuda.is_available() else "cpu")


def run_folder(ckpt: Path) -> Path:
    """The run folder of a checkpoint path (``RUN/checkpoints/x.pt`` -> ``RUN``) or of a run folder."""
    ckpt = Path(ckpt)
    if ckpt.is_dir():
        return ckpt
    return ckpt.parent.parent if ckpt.parent.name == CHECKPOINTS else ckpt.parent


def load_for_eval(run, mano, device: torch.device, boxes: str | None = None):
    """(model in eval mode, TrainConfig, info dict with checkpoint path, epoch and step) from a run or .pt."""
    from hoisdf.model import build_model

    path = find_checkpoint(run)
    payload = load_checkpoint(path)
    config = config_from_dict(payload["config"], path)
    settings = replace(config.model, weights="", **({"test_boxes": boxes} if boxes else {}))
    model = build_model(settings, mano)
    load_weights(model, payload["model"], path)
    progress = payload.get("progress") if isinstance(payload.get("progress"), dict) else {}
    info = {"checkpoint": str(path), "epoch": progress.get("epoch"), "global_step": progress.get("global_step"),
            "test_boxes": settings.test_boxes}
    return model.to(device).eval(), config, info


def to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def _keep_vis(col: Collected, batch: dict, out: dict, limit: int) -> None:
    """Keep the network input image, its K and the query points (camera frame) of the first samples."""
    for i in range(min(len(batch["key"]), limit - len(col.vis))):
        img = (batch["img"][i].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().cpu().numpy()
        points = [out["hand_query"][i] + batch["hand_root"][i], out["obj_query"][i] + batch["obj_center"][i]]
        sdf = [out["hand_query_sdf"][i], out["obj_query_sdf"][i]]
        col.vis[batch["key"][i]] = {"img": img, "K": to_numpy(batch["K"][i]), "points": to_numpy(torch.cat(points)),
                                    "sdf": to_numpy(torch.cat(sdf))}


def predict_batch(model, mano, mirrored, batch: dict, config,
                  precision: str = "fp32") -> tuple[dict, dict[str, np.ndarray]]:
    """One loader batch (on the model's device) -> (network input batch and raw outputs, per-sample arrays:
    joints, verts (when predicted), gt_joints, gt_verts, root, obj_pose, gt_obj_pose, obj_center; metres,
    upstream_crop 1 / 0 when the loader says which records are upstream crops;
    camera frame, the predicted hand placed at the ground-truth wrist). ``precision``: "fp32" or "bf16"
    (autocast on the batch's device; geometry stays fp32, see :mod:`hoisdf.model.precision`)."""
    device = batch["img"].device
    batch = augment_batch({k: v for k, v in batch.items() if k not in SDF_KEYS}, config.augment, None, train=False)
    with torch.no_grad(), autocast(device, precision):
        out = model(batch, points="field")
    gt = hand_targets(mano, mirrored, batch)  # full precision, outside autocast
    root = batch["hand_root"].float()[:, None]
    pose = torch.eye(4, device=device).repeat(len(root), 1, 1)
    pose[:, :3, :3], pose[:, :3, 3] = out["obj_rotation"].float(), out["obj_translation"].float()
    arrays = {"joints": out["joints"].float() + root, "gt_joints": batch["joints_3d"], "root": root[:, 0],
              "gt_verts": gt["verts"].float() + root, "obj_pose": pose, "gt_obj_pose": batch["object_pose"],
              "obj_center": batch["obj_center"]}
    if "verts" in out:
        arrays["verts"] = out["verts"].float() + root
    if "upstream_crop" in batch:  # the record is upstream's test crop (hoidata record.crop = "upstream")
        arrays["upstream_crop"] = batch["upstream_crop"]
    return (batch, out), {k: to_numpy(v) for k, v in arrays.items()}


def infer(model, mano, config, stores: list, batch_size: int, device: torch.device, limit: int | None = None,
          vis: int = 0, progress: bool = True, workers: int = 0, indexes: dict | None = None,
          precision: str = "fp32") -> Collected:
    """Predictions and ground truth of the records of ``stores``, returned in stored order (store after store).

    ``workers`` loader processes decode records (shards are split between them, so with ``limit`` the first
    samples are the first ones the loader delivers); ``vis`` keeps pictures' inputs of the first samples.
    ``indexes``: already read store indexes by store path. ``precision``: see :func:`predict_batch`; the dtypes
    the first batch ran in are kept in ``Collected.dtypes``.
    """
    mano.to(device)
    mirrored, col = mirrored_shape_mano(mano), Collected()
    bar = tqdm(desc="evaluating", unit="img", disable=not progress)
    for s, store in enumerate(stores):
        index = (indexes or {}).get(store) or read_index(store)
        rows, lab = {k: i for i, k in enumerate(index.keys)}, index.labels
        bar.total = (bar.total or 0) + min(len(rows), (limit or len(rows) + len(col.keys)) - len(col.keys))
        data = build_dataset([StoreSpec(store)], batch_size, n_hand=1, n_object=1, training=False)
        for batch in make_loader(data, min(workers, len(index.shards)), pin_memory=device.type == "cuda"):
            n = len(batch["key"]) if limit is None else min(len(batch["key"]), limit - len(col.keys))
            if n <= 0:
                break
            batch = {k: v[:n].to(device) if torch.is_tensor(v) else v[:n] for k, v in batch.items()}
            with trace_dtypes(model) if not col.dtypes else nullcontext({}) as seen:
                (batch, out), arrays = predict_batch(model, mano, mirrored, batch, config, precision)
            col.dtypes = col.dtypes or dict(seen)
            missing = [k for k in batch["key"] if k not in rows]
            if missing:
                raise DataError(store, missing[0], "record missing from the store index")
            r = np.array([rows[k] for k in batch["key"]])
            col.add(**arrays, ho3d_tips=lab["tip_convention"][r] == "ho3d", ho3d=lab["dataset"][r] == "ho3d",
                    mirrored=lab["mirrored"][r])
            col.keys += batch["key"]
            col.store += [s] * n
            col.rows += r.tolist()
            col.names += [str(x) for x in lab["object_name"][r]]
            col.frame_ids += [str(x) for x in lab["frame_id"][r]]
            _keep_vis(col, batch, out, vis)
            bar.update(n)
    bar.close()
    if not col.keys:
        raise DataError(stores[0] if stores else None, None, "no records to evaluate")
    col.sort()
    _use_ho3d_tips(col)
    return col


def _use_ho3d_tips(col: Collected) -> None:
    """Records whose joints follow HO-3D's fingertip vertices get predicted tips taken from the same vertices."""
    verts, sel = col.get("verts"), col.get("ho3d_tips").astype(bool)
    if verts is None or not sel.any():
        return
    joints = col.get("joints")
    joints[np.ix_(sel, DEXYCB_TIP_JOINTS)] = verts[sel][:, list(HO3D_TIP_VERTICES)]
    col.arrays["joints"] = [joints]

