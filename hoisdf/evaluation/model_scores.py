"""Scoring collected predictions: per-sample metrics, the mean-pose baseline, object meshes, plausibility."""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from hoidata.errors import DataError
from hoidata.geometry.mirror import mirror_mesh
from hoidata.store import read_index
from hoisdf.evaluation.inference import Collected, to_numpy
from hoisdf.scoring import metrics as M
from hoisdf.scoring.plausibility import (
    BUDGET,
    REL_TOLERANCE,
    TOLERANCE,
    frame_metrics_many,
    summarize,
)
from hoisdf.training.losses import hand_targets, mirrored_shape_mano

BASELINE_ROWS = 10000  # at most this many label rows (evenly spaced) make the mean pose


def _masked(fn, mask: np.ndarray, *arrays) -> dict[str, np.ndarray]:
    """Per-sample metrics of ``fn`` on the rows in ``mask``; the other rows are NaN."""
    n = len(mask)
    if not mask.any():
        return {k: np.full(n, np.nan) for k in fn(*[np.zeros_like(a[:1]) for a in arrays])}
    out = {}
    for k, v in fn(*[a[mask] for a in arrays]).items():
        out[k] = np.full(n, np.nan)
        out[k][mask] = v
    return out


def score(joints, gt_joints, verts, gt_verts, obj_pose, gt_obj_pose, obj_verts: list, obj_valid) -> dict:
    """Per-sample metrics (N,) in metres / ratios: :func:`hoisdf.scoring.metrics.joint_metrics`, ``mesh_metrics`` when
    ``verts`` is not None, ``object_metrics``. Samples without finite GT joints, or with ``obj_valid`` False,
    get NaN for the hand resp. object metrics (and are skipped by the means)."""
    hand_ok = np.isfinite(gt_joints).all((1, 2)) & np.isfinite(joints).all((1, 2))
    out = _masked(M.joint_metrics, hand_ok, joints, gt_joints)
    if verts is not None:
        out.update(_masked(M.mesh_metrics, hand_ok & np.isfinite(verts).all((1, 2)), verts, gt_verts))
    obj_ok = np.asarray(obj_valid, bool) & np.isfinite(obj_pose).all((1, 2))
    fn = lambda p, g, idx: M.object_metrics(p, g, [obj_verts[i] for i in idx])
    return {**out, **_masked(fn, obj_ok, obj_pose, gt_obj_pose, np.arange(len(obj_pose)))}


def mean_hand(store, mano, max_rows: int = BASELINE_ROWS, index=None) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean wrist-relative GT joints (21, 3) and MANO vertices (778, 3) over a store's labels (metres), and
    the number of rows used (at most ``max_rows``, evenly spaced; rows without finite joints are skipped)."""
    lab = (index or read_index(store)).labels
    n = len(lab["key"])
    rows = np.unique(np.linspace(0, n - 1, min(n, max_rows)).round().astype(np.int64)) if n else np.zeros(0, int)
    rows = rows[np.isfinite(lab["joints_3d"][rows]).all((1, 2)) & np.isfinite(lab["mano_pose"][rows]).all(1)]
    if len(rows) == 0:
        raise DataError(store, "joints_3d", "no record with finite hand labels for the mean-pose baseline")
    joints = lab["joints_3d"][rows].astype(np.float64)
    device = mano.v_template.device
    mirrored, total = mirrored_shape_mano(mano), np.zeros((778, 3))
    for start in range(0, len(rows), 2048):
        sel = rows[start:start + 2048]
        batch = {k: torch.as_tensor(lab[k][sel]).to(device) for k in ("mano_pose", "mano_betas", "mirrored")}
        total += to_numpy(hand_targets(mano, mirrored, batch)["verts"]).astype(np.float64).sum(0)
    return (joints - joints[:, :1]).mean(0), total / len(rows), len(rows)


def sample_meshes(objects: dict, names: list[str], mirrored) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each sample's object mesh (vertices, faces) in the frame its ``object_pose`` poses: a mirrored record
    poses the x-mirrored model (``hoidata.records.records.mirror_frame``), so it gets the mirrored vertices with the
    faces flipped to stay outward wound. Meshes are shared between samples, not copied."""
    cache, out = {}, []
    for name, flip in zip(names, np.asarray(mirrored, bool)):
        if (name, flip) not in cache:
            cache[name, flip] = mirror_mesh(*objects[name]) if flip else objects[name]
        out.append(cache[name, flip])
    return out


def plausibility_of(groups: dict, mano, progress: bool = True, workers: int = 1) -> dict:
    """Penetration depth, intersection volume, contact ratio, IVU and self-penetration of closed hands, per group:
    ``groups`` maps a name to (verts (N, 778, 3), poses (N, 4, 4), meshes: N object (vertices, faces), see
    :func:`sample_meshes`, posed by ``poses``). Every group's frames run on one pool of ``workers`` processes
    (:func:`hoisdf.scoring.plausibility.frame_metrics_many`; volumes to 0.1 cm^3 or 1 %, whichever is larger,
    within the scorer's budget). Returns {name: :func:`~hoisdf.scoring.plausibility.summarize` of its frames}."""
    faces = np.asarray(mano.closed_faces)
    samples, sizes, n_points = [], {}, {v.shape[1] for v, _, _ in groups.values()}
    for name, (verts, poses, meshes) in groups.items():
        if not len(verts):
            sizes[name] = 0
            continue
        closed = mano.close(torch.as_tensor(verts, dtype=torch.float32)).cpu().numpy().astype(np.float64)
        samples += [(closed[i], faces, v @ poses[i][:3, :3].T + poses[i][:3, 3], f) for i, (v, f) in enumerate(meshes)]
        sizes[name] = len(meshes)
    if len(n_points) > 1:
        raise ValueError(f"every group's hands need the same vertex count, got {sorted(n_points)}")
    with tqdm(total=len(samples), desc="plausibility", disable=not progress, leave=False) as bar:
        frames = frame_metrics_many(samples, workers, lambda _: bar.update(), tolerance=TOLERANCE,
                                    n_points=n_points.pop() if n_points else None, rel_tolerance=REL_TOLERANCE,
                                    max_cells=BUDGET)
    out, start = {}, 0
    for name, size in sizes.items():
        out[name], start = summarize(frames[start:start + size], TOLERANCE), start + size
    return out


def baseline_scores(col: Collected, mano, store, obj_verts: list, obj_valid, index=None) -> dict[str, np.ndarray]:
    """Per-sample metrics of the mean-pose baseline (see the module docstring) on the collected samples."""
    mean_j, mean_v, _ = mean_hand(store, mano, index=index)
    root, verts = col.get("root")[:, None], col.get("verts")
    pose = np.tile(np.eye(4), (len(root), 1, 1))
    pose[:, :3, 3] = col.get("obj_center")
    return score(mean_j + root, col.get("gt_joints"), None if verts is None else mean_v + root, col.get("gt_verts"),
                 pose, col.get("gt_obj_pose"), obj_verts, obj_valid)


def plausibility_summary(col: Collected, meshes: list, mano, count: int, progress: bool, workers: int = 1) -> dict:
    """Plausibility of the predicted hand/object and, for reference, of the ground truth, first ``count`` samples,
    on ``workers`` processes."""
    verts, k = col.get("verts"), min(count, len(col.keys))
    if verts is None or k == 0:
        return {"skipped": "no predicted hand mesh" if verts is None else "--plausibility 0"}
    out, groups = {}, {}
    for name, v, p in (("model", "verts", "obj_pose"), ("ground_truth", "gt_verts", "gt_obj_pose")):
        hands, poses = col.get(v)[:k], col.get(p)[:k]
        known = np.flatnonzero(np.isfinite(hands).all((1, 2)) & np.isfinite(poses).all((1, 2)))  # eval records: no GT
        if len(known):
            groups[name] = (hands[known], poses[known], [meshes[i] for i in known])
        else:
            out[name] = {"skipped": "no ground-truth hand mesh (evaluation records)"}
    reports = plausibility_of(groups, mano, progress, workers)  # one pool for the model's frames and the GT's
    return {name: reports[name] if name in reports else out[name] for name in ("model", "ground_truth")}
