"""The official evaluators' numbers, computed with this project's metrics (:mod:`hoisdf.scoring.metrics`).

- DexYCB HPE (``NVlabs/dex-ycb-toolkit:dex_ycb_toolkit/hpe_eval.py``, ``HPEEvaluator.evaluate``): MPJPE in mm and
  AUC over 0-50 mm at 100 thresholds for three alignments: ``absolute``, ``root-relative`` (each set minus its own
  wrist) and ``procrustes`` (``align_w_scale``, reflections admitted). :func:`dexycb_hpe_scores` returns the
  dict ``evaluate`` returns.
- HO-3D challenge (``shreyashampali/ho3d:eval.py``, ``main``): the 14 lines of ``scores.txt``, with its names and
  units: ``*_mean3d`` in **cm**, AUCs over 0-5 cm at 100 thresholds and F-scores unitless. Joints are compared
  raw, after ``align_w_scale`` (Procrustes) and after ``align_sc_tr`` (scale from the wrist to joint 4 of HO-3D's
  order, the middle MCP, then the wrist moved onto the GT wrist: the current script; before 2021-06 it used joint
  9); the mesh errors and aligned F-scores use a separate Procrustes fit of the 778 vertices. F-scores at 5 and
  15 mm count points strictly closer than the threshold and are averaged over samples.

Every per-point error is pooled over samples and points: with all points visible (as both evaluators feed
them) the mean of ``EvalUtil``'s per-keypoint means and AUCs equals the pooled mean and AUC.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.atomic import write_atomic
from hoidata.errors import DataError
from hoidata.reading import numbers_only, parse_json, read_bytes
from hoidata.shapes import numbers
from hoisdf.scoring import metrics as M

HPE_ALIGNMENTS = ("absolute", "root-relative", "procrustes")
HO3D_SCORES = ("xyz_mean3d", "xyz_auc3d", "xyz_procrustes_al_mean3d", "xyz_procrustes_al_auc3d",
               "xyz_scale_trans_al_mean3d", "xyz_scale_trans_al_auc3d", "mesh_mean3d", "mesh_auc3d",
               "mesh_al_mean3d", "mesh_al_auc3d", "f_score_5", "f_al_score_5", "f_score_15", "f_al_score_15")
HO3D_UNITS = "cm for *_mean3d (scores.txt's unit); AUCs (0-5 cm) and F-scores are ratios"
HO3D_V2_EVALUATION = 11524  # eval.py's db_size('evaluation', 'v2'): the server also requires this many samples
HO3D_EVALUATION_SIZES = {"v2": HO3D_V2_EVALUATION, "v3": 20137}  # db_size('evaluation', version) (utils/fh_utils.py)
HO3D_MCP = 4  # middle MCP in HO-3D's joint order (align_sc_tr)
HO3D_F_THRESHOLDS = (0.005, 0.015)  # metres
NOT_MANO = -1.0  # eval.py's mesh scores when the predicted meshes do not have the GT's vertex count


def dexycb_hpe_scores(pred_mm, gt_mm) -> dict[str, dict[str, float]]:
    """``hpe_eval``'s result of predictions against ground truth: (N, 21, 3) **millimetres**, camera frame, DexYCB
    order (the toolkit aligns in mm, so its 1e-8 is in mm). For its exact numbers pass the file's values as it
    parses them and the ground truth as it computes it (:func:`toolkit_gt_mm`).

    Returns ``{"absolute" | "root-relative" | "procrustes": {"mpjpe": mm, "auc": ratio over 0-50 mm}}``.
    """
    pred, gt = M.as_pair(pred_mm, gt_mm)
    errors = {
        "absolute": M.point_errors(pred, gt),
        "root-relative": M.point_errors(pred - pred[:, :1], gt - gt[:, :1]),
        "procrustes": M.point_errors(M.procrustes_align(pred, gt), gt),
    }
    return {name: {"mpjpe": float(e.mean()), "auc": M.auc(e, 0.0, 50.0, 100)} for name, e in errors.items()}


def toolkit_gt_mm(joints_m) -> np.ndarray:
    """The toolkit's ground truth from DexYCB joints in metres (float32 values, as its labels hold them): times 1000
    in float32, then float64, so errors at the AUC's 0 mm threshold come out as the toolkit's."""
    return (np.asarray(joints_m).astype(np.float32) * np.float32(1000.0)).astype(np.float64)


def align_by_keypoint_trafo(pred_verts, pred_xyz, gt_xyz) -> np.ndarray:
    """eval.py's aligned vertices of a prediction whose vertex count is not the GT's: ``align_by_trafo(verts_pred,
    align_w_scale(xyz, xyz_pred, return_trafo=True))``, reproduced with its quirk.

    The keypoints' similarity fit (rotation R, scale s of the unit-norm sets, GT norm s1) is applied to the
    vertices centred on their own mean, which is added back together with the keypoints' centroid offset; the
    prediction's own norm is never divided out, so the result is ``s * s1 * R (v - mean_v) + mean_gt_xyz -
    mean_pred_xyz + mean_v`` (not the keypoints' map unless the predicted joints have unit norm).

    Args:
        pred_verts: (N, V, 3) predicted points; pred_xyz, gt_xyz: (N, 21, 3) joints, metres.
    Returns:
        (N, V, 3) the points eval.py's aligned F-scores use.
    """
    pred_xyz, gt_xyz = M.as_pair(pred_xyz, gt_xyz)
    mu_p, mu_g = pred_xyz.mean(1, keepdims=True), gt_xyz.mean(1, keepdims=True)
    x, y = pred_xyz - mu_p, gt_xyz - mu_g
    u, sv, vt = np.linalg.svd(np.einsum("nki,nkj->nij", y, x))  # as orthogonal_procrustes(gt_n, pred_n)
    rot = u @ vt
    factor = sv.sum(1) / (np.sqrt(np.sum(x * x, axis=(1, 2))) + M.PROCRUSTES_EPS)  # s * s1, the eps as eval.py
    mu_v = pred_verts.mean(1, keepdims=True)
    return factor[:, None, None] * np.einsum("nij,nkj->nki", rot, pred_verts - mu_v) + (mu_g - mu_p) + mu_v


def _mean_auc(errors: np.ndarray) -> tuple[float, float]:
    """(mean in cm, AUC over 0-5 cm) of per-point errors in metres."""
    return float(errors.mean()) * 100.0, M.auc(errors, 0.0, 0.05, 100)


def ho3d_challenge_scores(pred_xyz, pred_verts, gt_xyz, gt_verts) -> dict[str, float]:
    """The 14 ``scores.txt`` values of predictions against ground truth, all in HO-3D's convention.

    Args:
        pred_xyz: (N, 21, 3) metres, HO-3D joint order (the frame does not matter, both must share it).
        gt_xyz: (N, 21, 3) the ground truth, likewise.
        pred_verts: (N, V, 3); V = 778 (the GT's count) for the mesh scores. Any other V > 0 (a method with its
            own topology) gets eval.py's -100 / -1 mesh scores and F-scores of those points, aligned for the
            ``f_al_*`` scores by :func:`align_by_keypoint_trafo`. V = 0 (no mesh; eval.py cannot score that)
            gives the same mesh scores and F-scores of 0.
        gt_verts: (N, 778, 3).
    """
    pred_xyz, gt_xyz = M.as_pair(pred_xyz, gt_xyz)
    gt_verts = M.as_batch(gt_verts, "gt_verts")
    pred_verts = np.asarray(pred_verts, np.float64).reshape(len(pred_xyz), -1, 3)
    out = {}
    out["xyz_mean3d"], out["xyz_auc3d"] = _mean_auc(M.point_errors(pred_xyz, gt_xyz))
    pa = M.procrustes_align(pred_xyz, gt_xyz)
    out["xyz_procrustes_al_mean3d"], out["xyz_procrustes_al_auc3d"] = _mean_auc(M.point_errors(pa, gt_xyz))
    st = M.st_align(pred_xyz, gt_xyz, wrist=0, middle_mcp=HO3D_MCP)
    out["xyz_scale_trans_al_mean3d"], out["xyz_scale_trans_al_auc3d"] = _mean_auc(M.point_errors(st, gt_xyz))
    if pred_verts.shape[1] == gt_verts.shape[1]:
        aligned = M.procrustes_align(pred_verts, gt_verts)
        out["mesh_mean3d"], out["mesh_auc3d"] = _mean_auc(M.point_errors(pred_verts, gt_verts))
        out["mesh_al_mean3d"], out["mesh_al_auc3d"] = _mean_auc(M.point_errors(aligned, gt_verts))
    else:  # not MANO's topology: no mesh errors; the F-scores use the keypoints' transform (eval.py)
        aligned = align_by_keypoint_trafo(pred_verts, pred_xyz, gt_xyz) if pred_verts.shape[1] else pred_verts
        out.update(mesh_mean3d=NOT_MANO * 100, mesh_auc3d=NOT_MANO, mesh_al_mean3d=NOT_MANO * 100, mesh_al_auc3d=NOT_MANO)
    plain, al = _f_scores(pred_verts, gt_verts), _f_scores(aligned, gt_verts)
    for k, thr in enumerate(HO3D_F_THRESHOLDS):
        tag = round(thr * 1000)
        out[f"f_score_{tag}"], out[f"f_al_score_{tag}"] = float(plain[:, k].mean()), float(al[:, k].mean())
    return {name: out[name] for name in HO3D_SCORES}


def _f_scores(pred, gt) -> np.ndarray:
    """(N, 2) F-scores at :data:`HO3D_F_THRESHOLDS` of (N, V, 3) against (N, 778, 3) point sets: the same numbers
    as :func:`hoisdf.scoring.metrics.f_score` per threshold, with each nearest-neighbour search done once."""
    from scipy.spatial import cKDTree

    out = np.zeros((len(pred), len(HO3D_F_THRESHOLDS)))
    if pred.shape[1] == 0:
        return out
    thr = np.asarray(HO3D_F_THRESHOLDS)
    for i, (p, g) in enumerate(zip(pred, gt)):
        d_p, d_g = cKDTree(g).query(p)[0], cKDTree(p).query(g)[0]
        precision = (d_p[:, None] < thr).mean(0)
        recall = (d_g[:, None] < thr).mean(0)
        total = precision + recall
        out[i] = np.where(total > 0, 2 * precision * recall / np.where(total > 0, total, 1.0), 0.0)
    return out


def read_ho3d_gt(folder) -> tuple[np.ndarray, np.ndarray]:
    """``evaluation_xyz.json`` and ``evaluation_verts.json`` of a folder (the lists eval.py scores against) as
    (N, 21, 3) and (N, 778, 3) arrays, HO-3D's convention as stored. DataError names a missing or malformed file."""
    lists = []
    for name, count in (("evaluation_xyz.json", 21), ("evaluation_verts.json", 778)):
        path = Path(folder) / name
        data = read_bytes(path, "HO-3D ground-truth file")
        lists.append(numbers(parse_json(data, path), path, None, (None, count, 3), plain=numbers_only(data)))
    if len(lists[0]) != len(lists[1]):
        raise DataError(folder, "evaluation_verts.json", f"{len(lists[1])} samples, evaluation_xyz.json has {len(lists[0])}")
    return lists[0], lists[1]


def score_ho3d_submission(pred_path, gt_folder) -> dict:
    """Score a ``pred.json`` / ``pred.zip`` against a folder's ground-truth lists as the challenge server does.

    Returns the 14 scores (:data:`HO3D_SCORES`) plus ``samples``, ``units`` and ``ground_truth``. Raises DataError
    if the prediction does not have one item per ground-truth sample (eval.py's 'Expected format mismatch.').
    """
    from hoisdf.scoring.submissions import read_ho3d_lists

    pred_xyz, pred_verts = read_ho3d_lists(pred_path)
    gt_xyz, gt_verts = read_ho3d_gt(gt_folder)
    if len(pred_xyz) != len(gt_xyz):
        raise DataError(pred_path, None, f"{len(pred_xyz)} samples, the ground truth in {gt_folder} has {len(gt_xyz)}")
    scores = ho3d_challenge_scores(pred_xyz, pred_verts, gt_xyz, gt_verts)
    return {**scores, "samples": len(gt_xyz), "units": HO3D_UNITS, "ground_truth": str(gt_folder)}


def write_scores_txt(path, scores: dict) -> Path:
    """``scores.txt`` as eval.py writes it: one ``name: %f`` line per score, in its order."""
    return write_atomic(path, "".join(f"{name}: {scores[name]:f}\n" for name in HO3D_SCORES).encode())


def format_ho3d_scores(scores: dict) -> str:
    """The challenge scores as printed lines: joints, then mesh, then F-scores (scores.txt's names and units)."""
    cells = [f"{name} {scores[name]:.4f}" for name in HO3D_SCORES]
    rows = [cells[0:6], cells[6:10], cells[10:14]]
    return (f"HO-3D challenge scores of {scores.get('pred_file', 'pred.json')} ({scores['samples']} samples; "
            f"{HO3D_UNITS}):\n" + "\n".join("  " + ", ".join(r) for r in rows))
