"""The SDF lineage's reconstruction scores (gSDF, AlignSDF, HORT), computed as their evaluator computes them.

What gSDF's ``datasets/dexycb/dexycb.py::_evaluate`` does for one frame and one part (hand or object), and what
this module repeats operation for operation (docs/scoring.md, "Reconstruction"):

1. load both meshes with ``trimesh.load(path, process=False)``, the prediction first;
2. draw 30,000 points on each surface with ``trimesh.sample.sample_surface`` (prediction first, then the ground
   truth, hand before object, from one unseeded stream), and multiply them by 100 (metres -> cm);
3. nearest-neighbour distances both ways with a k-d tree; Chamfer = mean squared distance ground truth ->
   prediction + mean squared distance prediction -> ground truth (cm^2);
4. each precision as ``np.mean(d < t).astype(np.float32)`` (strict), F = ``2 p1 p2 / (p1 + p2 + 1e-7)`` in the
   precisions' float32 arithmetic (numpy >= 2 keeps a float32 scalar plus a Python float in float32), at
   1 and 5 mm for the hand, 5 and 10 mm for the object;
5. any exception in 1-4 makes all three numbers of the part ``None``.

``tools/eval.py`` then averages each number over the frames where it is neither ``None`` nor NaN (the
*survivor mean*, :func:`survivor_mean`), F-scores in float32 as numpy averages a list of float32 scalars, and
reports the median Chamfer beside the mean. Neither file aligns the meshes: gSDF's reconstruction step
(``recon.py``, ``chamfer_optim``) fits the predicted hand to the ground truth in translation and scale before it
writes the file, so the files it scores already carry that fit.
"""

from __future__ import annotations

import numpy as np

from hoidata.reading_media import read_mesh

POINTS = 30000  # surface samples per mesh
CM = 100.0  # the meshes are in metres; distances are scored in cm
# (name, threshold in cm) of each part's F-scores, in gSDF's order
THRESHOLDS = {"hand": (("f_1mm", 0.1), ("f_5mm", 0.5)), "obj": (("f_5mm", 0.5), ("f_10mm", 1.0))}
EPS = 1e-7  # gSDF's denominator guard


def load_mesh(path):
    """``trimesh.load(path, process=False)``, as gSDF loads both meshes (a scene or point cloud is returned as it
    comes; :func:`part_scores` then fails on it as gSDF does), through the guarded door: a file trimesh refuses
    is a DataError naming it."""
    return read_mesh(path, process=False)


def sample_points(mesh, rng: np.random.Generator, count: int = POINTS) -> np.ndarray:
    """``count`` points on the surface, in cm: ``trimesh.sample.sample_surface`` drawing from ``rng``."""
    import trimesh

    points, _ = trimesh.sample.sample_surface(mesh, count, seed=rng)
    return points * CM


def fscore32(d_gt_to_pred: np.ndarray, d_pred_to_gt: np.ndarray, threshold: float) -> np.float32:
    """gSDF's F-score at ``threshold`` (cm): strict ``<``, float32 precisions, the 1e-7 guard."""
    p1 = np.mean(d_gt_to_pred < threshold).astype(np.float32)
    p2 = np.mean(d_pred_to_gt < threshold).astype(np.float32)
    return 2 * p1 * p2 / (p1 + p2 + EPS)


def point_scores(pred_cm: np.ndarray, gt_cm: np.ndarray, part: str) -> dict:
    """Chamfer (cm^2, float64) and the part's two F-scores (float32) of two point sets in cm."""
    from scipy.spatial import cKDTree

    d_gt_to_pred, _ = cKDTree(pred_cm).query(gt_cm)
    d_pred_to_gt, _ = cKDTree(gt_cm).query(pred_cm)
    out = {"chamfer": np.mean(np.square(d_gt_to_pred)) + np.mean(np.square(d_pred_to_gt))}
    for name, threshold in THRESHOLDS[part]:
        out[name] = fscore32(d_gt_to_pred, d_pred_to_gt, threshold)
    return out


def part_scores(pred_path, gt_path, part: str, rng: np.random.Generator) -> dict | None:
    """One part of one frame exactly as ``_evaluate``: the three numbers, or None where gSDF's ``try`` fails.

    Draws from ``rng`` in gSDF's order (prediction, then ground truth); a failure before a draw draws nothing.
    """
    try:
        pred = load_mesh(pred_path)
        gt = load_mesh(gt_path)
        pred_cm = sample_points(pred, rng)
        gt_cm = sample_points(gt, rng)
        return point_scores(pred_cm, gt_cm, part)
    except Exception:  # noqa: BLE001 - gSDF's bare except: any failure is a None, which is what is reproduced
        return None


def frame_rng(seed: int, frame_id: str) -> np.random.Generator:
    """The stream of one frame under ``--seed``: the same draws whatever order or subset the frames come in."""
    return np.random.default_rng([int(seed), *frame_id.encode()])


def survivor_mean(values: list) -> float:
    """``tools/eval.py``'s mean: over the values that are not None and not NaN (NaN when none survives); float32
    values are averaged in float32, as numpy averages a list of float32 scalars."""
    kept = [v for v in values if v is not None and not np.isnan(v)]
    return float(np.mean(kept)) if kept else float("nan")


def survivor_median(values: list) -> float:
    """``tools/eval.py``'s median Chamfer, over the same survivors."""
    kept = [v for v in values if v is not None and not np.isnan(v)]
    return float(np.median(kept)) if kept else float("nan")
