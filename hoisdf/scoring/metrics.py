"""Evaluation metrics for hand and object pose, as the official evaluators compute them.

Pure numpy, batched over samples, **metres in**; every per-sample function returns (N,) arrays so that
per-object means and overall means come from the same numbers. Millimetre conversion and metric names
for printing live only in :func:`report_units` at the end of this file.

Definitions (docs/upstream.md, "Evaluation as upstream computes it"; docs/conventions.md, "The official evaluators"):

- joints: (N, 21, 3) in DexYCB/manopth order (0 wrist, 1-4 thumb, 5-8 index, 9-12 middle, 13-16 ring,
  17-20 little); hand vertices (N, 778, 3);
- MJE: mean over joints of the L2 error (absolute, or root-relative: each set minus its own wrist, the
  zero wrist term included in the 21-joint mean, as HOISDF and the DexYCB toolkit do);
- PA-MJE: per-sample similarity Procrustes as the official evaluators align (FreiHAND/HO-3D ``align_w_scale``,
  which dex-ycb-toolkit's ``hpe_eval`` imports): scipy's ``orthogonal_procrustes``, the plain SVD solution, so a
  reflection (det R = -1) is admitted when it fits better. ``*_no_reflection`` metrics restrict the alignment to
  proper rotations (Umeyama with the sign fix, as HOISDF's own ``rigid_align``); the two differ only where the best
  fit is a mirror image (e.g. near-flat hands of an early model);
- ST-MJE: HO-3D's ``align_sc_tr``: scale the prediction so its wrist-to-middle-MCP length matches the GT
  one (HO-3D joint 4 = our joint 9), then move its wrist onto the GT wrist; no rotation;
- AUC: PCK (fraction of errors <= t, FreiHAND ``EvalUtil``) at ``steps`` thresholds linearly spaced in
  [lo, hi], trapezoid-integrated, divided by (hi - lo). With the same number of errors per sample the
  mean of per-sample AUCs equals the AUC of the pooled errors, which is how the evaluators pool;
- object poses: (N, 4, 4) rigid transforms model -> camera, ``v_cam = R v + t``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree

WRIST = 0
MIDDLE_MCP = 9  # DexYCB order; HO-3D's align_sc_tr uses its joint 4, the same anatomical joint
AUC_LO, AUC_HI, AUC_STEPS = 0.0, 0.05, 100  # metres: 0-50 mm in 100 steps (EvalUtil.get_measures)
F_THRESHOLDS = (0.005, 0.015)  # F@5mm, F@15mm


def as_batch(x, name: str, last: int = 3) -> np.ndarray:
    """(N, K, last) float64; a single (K, last) set becomes N = 1."""
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[-1] != last:
        raise ValueError(f"{name} must have shape (N, K, {last}) or (K, {last}), got {np.shape(x)}")
    return arr


def as_pair(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    """``pred`` and ``gt`` as :func:`as_batch` arrays of one shape (a ValueError naming both shapes otherwise)."""
    pred, gt = as_batch(pred, "pred"), as_batch(gt, "gt")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape, got {pred.shape} and {gt.shape}")
    return pred, gt


# ---------------------------------------------------------------- alignment

PROCRUSTES_EPS = 1e-8  # align_w_scale adds this to both Frobenius norms


def procrustes_align(pred, gt, scale: bool = True, reflection: bool = True) -> np.ndarray:
    """Align each predicted point set onto its GT by a similarity (or rigid) transform.

    Args:
        pred: (N, K, 3) or (K, 3) points (any unit; the evaluators' 1e-8 is in that unit).
        gt: the corresponding points, same shape and unit.
        scale: True for a similarity (rotation, translation, scale), False for a rigid transform.
        reflection: True (the official definition, ``align_w_scale``): R = U V^T from the SVD of
            gt_c^T pred_c, an improper rotation when that fits better; scale = sum of the singular values over
            (|pred_c|_F + 1e-8)^2. False: proper rotations only (det R = +1; Umeyama 1991), so a mirror image
            keeps its error.

    Returns:
        (N, K, 3) aligned prediction ``c R p + t``. A degenerate prediction (all points equal) maps onto the
        GT centroid.
    """
    pred, gt = as_pair(pred, gt)
    mu_p, mu_g = pred.mean(1, keepdims=True), gt.mean(1, keepdims=True)
    x, y = pred - mu_p, gt - mu_g
    u, s, vt = np.linalg.svd(np.einsum("nki,nkj->nij", y, x))  # (N, 3, 3): gt x pred
    d = np.ones_like(s)
    if not reflection:
        d[:, -1] = np.sign(np.linalg.det(u) * np.linalg.det(vt))
        d[d == 0] = 1.0
    rot = np.einsum("nij,nj,njk->nik", u, d, vt)
    norm_p = np.sqrt(np.sum(x * x, axis=(1, 2))) + PROCRUSTES_EPS
    c = np.sum(s * d, axis=1) / norm_p ** 2 if scale else np.ones(len(pred))
    return c[:, None, None] * np.einsum("nij,nkj->nki", rot, x) + mu_g


def st_align(pred, gt, wrist: int = WRIST, middle_mcp: int = MIDDLE_MCP) -> np.ndarray:
    """HO-3D scale-translation alignment (``align_sc_tr``): (N, 21, 3) -> (N, 21, 3), metres.

    The prediction is scaled by |gt[mcp] - gt[wrist]| / |pred[mcp] - pred[wrist]| (left unscaled where
    its bone has zero length), then translated so that its wrist lands on the GT wrist.
    """
    pred, gt = as_pair(pred, gt)
    bone_p = np.linalg.norm(pred[:, middle_mcp] - pred[:, wrist], axis=-1)
    bone_g = np.linalg.norm(gt[:, middle_mcp] - gt[:, wrist], axis=-1)
    ratio = np.where(bone_p > 0, bone_g / np.where(bone_p > 0, bone_p, 1.0), bone_g)
    rel = pred - pred[:, wrist:wrist + 1]
    return rel * ratio[:, None, None] + gt[:, wrist:wrist + 1]


# ---------------------------------------------------------------- hand joints and vertices

def point_errors(pred, gt) -> np.ndarray:
    """(N, K) L2 distance of corresponding points, metres."""
    pred, gt = as_pair(pred, gt)
    return np.linalg.norm(pred - gt, axis=-1)


def mje(pred, gt, root_relative: bool = False, root: int = WRIST) -> np.ndarray:
    """(N,) mean joint error, metres; ``root_relative`` subtracts joint ``root`` from each set first."""
    pred, gt = as_pair(pred, gt)
    if root_relative:
        pred, gt = pred - pred[:, root:root + 1], gt - gt[:, root:root + 1]
    return point_errors(pred, gt).mean(1)


def pa_mje(pred, gt, reflection: bool = True) -> np.ndarray:
    """(N,) mean joint error after per-sample similarity Procrustes alignment (:func:`procrustes_align`), metres."""
    return point_errors(procrustes_align(pred, gt, reflection=reflection), gt).mean(1)


def st_mje(pred, gt, wrist: int = WRIST, middle_mcp: int = MIDDLE_MCP) -> np.ndarray:
    """(N,) mean joint error after HO-3D's scale-translation alignment (:func:`st_align`), metres."""
    return point_errors(st_align(pred, gt, wrist, middle_mcp), gt).mean(1)


def mme(pred_verts, gt_verts) -> np.ndarray:
    """(N,) mean per-vertex error (unaligned), metres."""
    return point_errors(pred_verts, gt_verts).mean(1)


def pa_mme(pred_verts, gt_verts) -> np.ndarray:
    """(N,) mean per-vertex error after Procrustes alignment of the vertices, metres."""
    return point_errors(procrustes_align(pred_verts, gt_verts), gt_verts).mean(1)


def pck_curve(errors, thresholds) -> np.ndarray:
    """Fraction of errors <= each threshold: errors any shape (metres, NaN ignored) -> (T,)."""
    err = np.asarray(errors, dtype=np.float64).ravel()
    err = err[~np.isnan(err)]
    thr = np.asarray(thresholds, dtype=np.float64)
    if len(err) == 0:
        return np.zeros(len(thr))
    return np.searchsorted(np.sort(err), thr, side="right") / len(err)


def _trapezoid(y: np.ndarray, x: np.ndarray) -> float:
    return float(np.sum((y[1:] + y[:-1]) * np.diff(x)) / 2.0)


def auc(errors, lo: float = AUC_LO, hi: float = AUC_HI, steps: int = AUC_STEPS) -> float:
    """Normalised area under the PCK curve at ``steps`` thresholds in [lo, hi] (metres): in [0, 1]."""
    if not hi > lo or steps < 2:
        raise ValueError(f"need hi > lo and steps >= 2, got lo={lo}, hi={hi}, steps={steps}")
    thr = np.linspace(lo, hi, steps)
    return _trapezoid(pck_curve(errors, thr), thr) / (hi - lo)


def auc_per_sample(errors, lo: float = AUC_LO, hi: float = AUC_HI, steps: int = AUC_STEPS) -> np.ndarray:
    """(N,) AUC of each row of (N, K) errors; their mean is the AUC of all errors pooled."""
    err = np.asarray(errors, dtype=np.float64)
    return np.array([auc(row, lo, hi, steps) for row in err.reshape(len(err), -1)])


def vauc(pred_verts, gt_verts, procrustes: bool = False) -> np.ndarray:
    """(N,) AUC over 0-50 mm of the per-vertex errors (VAUC; PA-VAUC with ``procrustes=True``)."""
    if procrustes:
        pred_verts = procrustes_align(pred_verts, gt_verts)
    return auc_per_sample(point_errors(pred_verts, gt_verts))


def f_score(pred_pts, gt_pts, threshold: float) -> tuple[float, float, float]:
    """F-score of two point sets at ``threshold`` metres: (f, precision, recall).

    precision = fraction of predicted points closer than ``threshold`` to some GT point, recall = the
    converse (HO-3D's code swaps the two names; F is symmetric). Strict ``<`` as the evaluators.
    Either set empty gives (0, 0, 0); identical non-empty sets give (1, 1, 1) for threshold > 0.
    """
    pred = np.asarray(pred_pts, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_pts, dtype=np.float64).reshape(-1, 3)
    if len(pred) == 0 or len(gt) == 0:
        return 0.0, 0.0, 0.0
    precision = float(np.mean(cKDTree(gt).query(pred)[0] < threshold))
    recall = float(np.mean(cKDTree(pred).query(gt)[0] < threshold))
    if precision + recall == 0:
        return 0.0, precision, recall
    return 2 * precision * recall / (precision + recall), precision, recall


def f_scores(pred_verts, gt_verts, threshold: float, procrustes: bool = False) -> np.ndarray:
    """(N,) F-score per sample of (N, V, 3) vertex sets at ``threshold`` metres, optionally PA-aligned."""
    pred, gt = as_pair(pred_verts, gt_verts)
    if procrustes:
        pred = procrustes_align(pred, gt)
    return np.array([f_score(p, g, threshold)[0] for p, g in zip(pred, gt)])


# ---------------------------------------------------------------- objects

def _poses(pose, name: str) -> np.ndarray:
    arr = np.asarray(pose, dtype=np.float64)
    arr = arr[None] if arr.ndim == 2 else arr
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (N, 4, 4) or (4, 4), got {np.shape(pose)}")
    return arr


def _posed(pose: np.ndarray, vertices) -> list[np.ndarray]:
    """Model vertices posed by each transform: a list of N (V_i, 3) arrays, camera frame.

    ``vertices``: one (V, 3) model shared by all samples, (N, V, 3), or a sequence of N (V_i, 3).
    """
    models = _models(vertices, len(pose))
    return [v @ p[:3, :3].T + p[:3, 3] for p, v in zip(pose, models)]


def _models(vertices, n: int) -> list[np.ndarray]:
    if isinstance(vertices, np.ndarray) and vertices.ndim == 2:
        vertices = [vertices] * n
    models = [np.asarray(v, dtype=np.float64) for v in vertices]
    if len(models) != n or any(v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 for v in models):
        raise ValueError(f"vertices must be one (V, 3) model or {n} non-empty (V_i, 3) models")
    return models


def _pose_pair(pred_pose, gt_pose) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = _poses(pred_pose, "pred_pose"), _poses(gt_pose, "gt_pose")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_pose and gt_pose differ in shape: {pred.shape} vs {gt.shape}")
    return pred, gt


def oce(pred_t, gt_t) -> np.ndarray:
    """(N,) object centre error: L2 between translations (N, 3) (the model origin in camera), metres."""
    pred, gt = np.asarray(pred_t, dtype=np.float64), np.asarray(gt_t, dtype=np.float64)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise ValueError(f"pred_t and gt_t must both be (N, 3), got {pred.shape} and {gt.shape}")
    return np.linalg.norm(pred - gt, axis=-1).reshape(-1)


def _aabb_corners(points: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box of (V, 3) points, fixed order (x slowest, z fastest)."""
    lo, hi = points.min(0), points.max(0)
    sel = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return np.where(sel == 1, hi, lo)


def mce(pred_pose, gt_pose, vertices) -> np.ndarray:
    """(N,) mean corner error as upstream HOISDF computes it, metres.

    The corners are those of the **axis-aligned box in the camera frame** of each posed model (min/max
    of the transformed vertices), not the model's own 3D box: a rotation about the box centre can
    leave this error at 0. :func:`box_corner_error` is the corner error proper.
    """
    pred_pose, gt_pose = _pose_pair(pred_pose, gt_pose)
    pred, gt = _posed(pred_pose, vertices), _posed(gt_pose, vertices)
    return np.array([np.linalg.norm(_aabb_corners(p) - _aabb_corners(g), axis=1).mean() for p, g in zip(pred, gt)])


def box_corner_error(pred_pose, gt_pose, vertices) -> np.ndarray:
    """(N,) mean L2 over the 8 corners of the model's canonical (model-frame) axis-aligned box, each
    posed by the predicted and by the GT transform (HO-3D ``objCorners3DRest`` style), metres."""
    pred_pose, gt_pose = _pose_pair(pred_pose, gt_pose)
    corners = [_aabb_corners(v) for v in _models(vertices, len(pred_pose))]
    pred, gt = _posed(pred_pose, corners), _posed(gt_pose, corners)
    return np.array([np.linalg.norm(p - g, axis=1).mean() for p, g in zip(pred, gt)])


def add_s(pred_pose, gt_pose, vertices) -> np.ndarray:
    """(N,) ADD-S: mean over predicted posed vertices of the distance to the closest GT posed vertex,
    metres (upstream direction: pred -> GT)."""
    pred_pose, gt_pose = _pose_pair(pred_pose, gt_pose)
    pred, gt = _posed(pred_pose, vertices), _posed(gt_pose, vertices)
    return np.array([cKDTree(g).query(p)[0].mean() for p, g in zip(pred, gt)])


def add(pred_pose, gt_pose, vertices) -> np.ndarray:
    """(N,) ADD / OME: mean distance between corresponding posed vertices, metres."""
    pred_pose, gt_pose = _pose_pair(pred_pose, gt_pose)
    pred, gt = _posed(pred_pose, vertices), _posed(gt_pose, vertices)
    return np.array([np.linalg.norm(p - g, axis=1).mean() for p, g in zip(pred, gt)])


ome = add  # HO-3D tables call the ADD-like vertex error "OME" (upstream variable MME_error)


# ---------------------------------------------------------------- per-sample bundles

def joint_metrics(pred, gt, root: int = WRIST, middle_mcp: int = MIDDLE_MCP) -> dict[str, np.ndarray]:
    """Per-sample joint metrics of (N, 21, 3) sets: mje (absolute), rr_mje, pa_mje (official alignment),
    pa_mje_no_reflection, st_mje (metres) and the AUCs auc (absolute), rr_auc, pa_auc (0-50 mm)."""
    pred, gt = as_pair(pred, gt)
    rr_p, rr_g = pred - pred[:, root:root + 1], gt - gt[:, root:root + 1]
    pa = procrustes_align(pred, gt)
    return {
        "mje": mje(pred, gt), "rr_mje": mje(pred, gt, root_relative=True, root=root), "pa_mje": mje(pa, gt),
        "pa_mje_no_reflection": pa_mje(pred, gt, reflection=False), "st_mje": st_mje(pred, gt, root, middle_mcp),
        "auc": auc_per_sample(point_errors(pred, gt)), "rr_auc": auc_per_sample(point_errors(rr_p, rr_g)),
        "pa_auc": auc_per_sample(point_errors(pa, gt)),
    }


def mesh_metrics(pred_verts, gt_verts, thresholds: Sequence[float] = F_THRESHOLDS) -> dict[str, np.ndarray]:
    """Per-sample hand mesh metrics of (N, V, 3) sets: mme, pa_mme, pa_mme_no_reflection (metres), vauc, pa_vauc and the
    F-scores ``f<mm>`` / ``pa_f<mm>`` (e.g. f5, f15) at ``thresholds`` metres."""
    pred, gt = as_pair(pred_verts, gt_verts)
    pa = procrustes_align(pred, gt)
    out = {"mme": mme(pred, gt), "pa_mme": mme(pa, gt), "vauc": vauc(pred, gt), "pa_vauc": vauc(pa, gt),
           "pa_mme_no_reflection": mme(procrustes_align(pred, gt, reflection=False), gt)}
    for thr in thresholds:
        tag = f"{thr * 1000:g}"
        out[f"f{tag}"] = f_scores(pred, gt, thr)
        out[f"pa_f{tag}"] = f_scores(pa, gt, thr)
    return out


def object_metrics(pred_pose, gt_pose, vertices) -> dict[str, np.ndarray]:
    """Per-sample object metrics (metres): oce, mce (upstream), box_corner_error, add_s, ome."""
    pred_pose, gt_pose = _pose_pair(pred_pose, gt_pose)
    return {
        "oce": oce(pred_pose[:, :3, 3], gt_pose[:, :3, 3]), "mce": mce(pred_pose, gt_pose, vertices),
        "box_corner_error": box_corner_error(pred_pose, gt_pose, vertices),
        "add_s": add_s(pred_pose, gt_pose, vertices), "ome": add(pred_pose, gt_pose, vertices),
    }


# ---------------------------------------------------------------- aggregation and reporting

def per_group_mean(values, groups) -> dict:
    """Mean of (N,) ``values`` per group label in (N,) ``groups``, NaN values skipped (a group with
    none left gets NaN). Keys are the group labels as Python scalars, in sorted order."""
    vals = np.asarray(values, dtype=np.float64).reshape(-1)
    grp = np.asarray(groups).reshape(-1)
    if len(vals) != len(grp):
        raise ValueError(f"values and groups differ in length: {len(vals)} vs {len(grp)}")
    out = {}
    for g in np.unique(grp):
        sel = vals[(grp == g) & ~np.isnan(vals)]
        out[g.item() if hasattr(g, "item") else g] = float(sel.mean()) if len(sel) else float("nan")
    return out


def _nanmean(values) -> float:
    vals = np.asarray(values, dtype=np.float64).reshape(-1)
    vals = vals[~np.isnan(vals)]
    return float(vals.mean()) if len(vals) else float("nan")


def summarize(per_sample: Mapping[str, np.ndarray], groups=None) -> dict[str, dict[str, float]]:
    """Means of per-sample metrics, overall and per group, converted for reporting by :func:`report_units`.

    Args:
        per_sample: metric name -> (N,) values in SI units (metres, or ratios for AUC / F-scores). NaN
            marks a sample not evaluated for that metric (e.g. HO-3D's unseen 019_pitcher_base for the
            object metrics) and is skipped.
        groups: optional (N,) labels (e.g. object names) for per-group means.

    Returns:
        ``{"all": {metric: value}, <group>: {metric: value}, ...}`` with lengths in millimetres.
    """
    lengths = {k: len(np.asarray(v).reshape(-1)) for k, v in per_sample.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"per-sample arrays differ in length: {lengths}")
    out = {"all": report_units({k: _nanmean(v) for k, v in per_sample.items()})}
    if groups is not None:
        by_metric = {k: per_group_mean(v, groups) for k, v in per_sample.items()}
        for g in sorted(next(iter(by_metric.values()), {})):
            out[str(g)] = report_units({k: by_metric[k][g] for k in per_sample})
    return out


RATIO_METRICS = frozenset({"rr_auc", "pa_auc", "auc", "vauc", "pa_vauc", "contact_ratio"})


def report_units(means: Mapping[str, float]) -> dict[str, float]:
    """Reporting layer: metres -> millimetres for every length metric; ratios (AUCs, F-scores: names in
    :data:`RATIO_METRICS` or starting with ``f``/``pa_f`` followed by a digit) are left as they are."""
    def is_ratio(name: str) -> bool:
        stem = name.removeprefix("pa_")
        return name in RATIO_METRICS or (stem[:1] == "f" and stem[1:2].isdigit())

    return {k: float(v) if is_ratio(k) else float(v) * 1000.0 for k, v in means.items()}
