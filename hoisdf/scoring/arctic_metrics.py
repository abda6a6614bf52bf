"""ARCTIC's leaderboard metrics as its evaluation code computes them (docs/scoring.md, "ARCTIC"), in numpy float64.

Per sequence and view: each metric is a vector (one value per frame; MDev one per contact window) with NaN
where ARCTIC leaves a frame out; :func:`pool` concatenates the vectors of every sequence and view and takes
the mean of the non-NaN values, as the leaderboard pools them. Hands: (N, 778, 3) vertices and ARCTIC's 21
joints (16 MANO joints + 5 fingertip vertices), wrist first; objects: (N, V, 3) vertices with part ids (1 top,
2 bottom: the root is the mean of the bottom vertices); metres, any camera frame shared by hands and object.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

FPS = 30.0
FIELD_MAX = 0.1  # metres: the interaction field's clamp
CONTACT = 3e-3  # metres: in contact (CDev, MDev)
WINDOW = 15  # frames: the shortest contact window MDev uses
SUCCESS_ALPHA = 0.05  # fraction of the object's diameter


def nanmean(a: np.ndarray, axis=None) -> np.ndarray:
    """The mean of the non-NaN values (NaN where there are none), ARCTIC's ``torch_utils.nanmean``."""
    a = np.asarray(a, np.float64)
    ok = ~np.isnan(a)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, a, 0.0).sum(axis=axis) / ok.sum(axis=axis)


def interaction_field(vh_r, vh_l, vo) -> dict[str, np.ndarray]:
    """ARCTIC's field targets per frame: ``dist.ro`` (N, 778) each right-hand vertex's distance to the nearest
    object vertex and ``idx.ro`` that vertex, ``dist.lo`` / ``idx.lo``, ``dist.or`` / ``dist.ol`` (N, V) each
    object vertex's to the nearest hand vertex; distances clamped to [0, :data:`FIELD_MAX`]."""
    out = {k: [] for k in ("dist.ro", "idx.ro", "dist.lo", "idx.lo", "dist.or", "idx.or", "dist.ol", "idx.ol")}
    for r, l, o in zip(vh_r, vh_l, vo):
        for key, a, b in (("ro", r, o), ("lo", l, o), ("or", o, r), ("ol", o, l)):
            _, idx = cKDTree(b).query(a)
            out[f"idx.{key}"].append(idx)
            out[f"dist.{key}"].append(np.minimum(np.linalg.norm(a - b[idx], axis=-1), FIELD_MAX))
    return {k: np.array(v) for k, v in out.items()}


def error_accel(gt: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """(N, P, D) -> (N - 2,): the mean over points of the norm of the central-difference acceleration error
    (units / s^2 at :data:`FPS`)."""
    h2 = (1.0 / FPS) ** 2
    acc_gt = (gt[:-2] - 2 * gt[1:-1] + gt[2:]) / h2
    acc_pred = (pred[:-2] - 2 * pred[1:-1] + pred[2:]) / h2
    return np.linalg.norm(acc_pred - acc_gt, axis=2).mean(axis=1)


def _valid3(flags: np.ndarray) -> np.ndarray:
    return np.convolve(flags, np.ones(3), mode="valid").astype(np.int64) == 3


def _pad(x: np.ndarray) -> np.ndarray:
    return np.concatenate([[np.nan], x, [np.nan]])


def _root_o(v: np.ndarray, part_ids: np.ndarray) -> np.ndarray:
    return v[:, part_ids == 2].mean(axis=1)


def _hands(gt: dict):
    valid = gt["is_valid"]
    return valid, gt["right_valid"] * valid, gt["left_valid"] * valid


def pose_metrics(pred: dict, gt: dict, part_ids: np.ndarray, diameter: float, field: dict) -> dict:
    """The pose task's vectors of one sequence and view. ``pred`` / ``gt``: ``j.r``, ``j.l``, ``v.r``, ``v.l``,
    ``v.o``, ``radian``; ``gt`` also ``is_valid``, ``right_valid``, ``left_valid`` (0/1 floats); ``field``:
    :func:`interaction_field` of the ground truth. Degrees, mm, percent, m/s^2 as ARCTIC reports them."""
    valid, rv, lv = _hands(gt)
    out = {}
    aae = np.abs(pred["radian"] / np.pi * 180 - gt["radian"] / np.pi * 180)
    out["aae"] = np.where(valid == 0, np.nan, aae)
    err = {}
    for s, hv in (("r", rv), ("l", lv)):
        e = np.linalg.norm((gt[f"j.{s}"] - gt[f"j.{s}"][:, :1]) - (pred[f"j.{s}"] - pred[f"j.{s}"][:, :1]), axis=-1)
        err[s] = np.where(hv[:, None] == 0, np.nan, e).mean(axis=1)
    out["mpjpe/ra/h"] = nanmean(np.stack([err["r"], err["l"]], 1), axis=1) * 1000
    root = {k: d["j.r"][:, 0] for k, d in (("pred", pred), ("gt", gt))}
    others = {"l": (lambda d: d["j.l"][:, 0], lv * rv), "o": (lambda d: _root_o(d["v.o"], part_ids), rv * valid)}
    for key, (get, ok) in others.items():
        rel = (get(pred) - root["pred"]) - (get(gt) - root["gt"])
        out[f"mrrpe/r/{key}"] = np.where(ok == 0, np.nan, np.linalg.norm(rel, axis=-1)) * 1000
    ra_gt = gt["v.o"] - _root_o(gt["v.o"], part_ids)[:, None]
    ra_pred = pred["v.o"] - _root_o(pred["v.o"], part_ids)[:, None]
    hit = (np.linalg.norm(ra_gt - ra_pred, axis=-1) < diameter * SUCCESS_ALPHA).mean(axis=1)
    out["success_rate/0.05"] = np.where(valid == 0, np.nan, hit) * 100
    cd = []
    for s, hv in (("r", rv), ("l", lv)):
        disp = np.take_along_axis(pred["v.o"], field[f"idx.{s}o"][..., None], axis=1) - pred[f"v.{s}"]
        d = np.linalg.norm(disp, axis=-1)
        d[(hv == 0)] = np.nan
        d[field[f"dist.{s}o"] > CONTACT] = np.nan
        cd.append(nanmean(d, axis=1))
    out["cdev/ho"] = nanmean(np.stack(cd, 1), axis=1) * 1000
    acc = {}
    for s, hv in (("r", rv), ("l", lv)):
        a = error_accel(gt[f"v.{s}"] - gt[f"j.{s}"][:, :1], pred[f"v.{s}"] - pred[f"j.{s}"][:, :1])
        acc[s] = np.where(_valid3(hv), a, np.nan)
    out["acc/h"] = _pad(nanmean(np.stack([acc["r"], acc["l"]], 1), axis=1))
    a = error_accel(ra_gt, ra_pred)
    out["acc/o"] = np.where(_valid3(valid), a, np.nan)
    return out


def find_windows(dist: np.ndarray, idx: np.ndarray, vo0: np.ndarray) -> tuple[list, int]:
    """ARCTIC's stable-contact windows [m, n, i, j] of one hand (``dist`` / ``idx``: (N, 778) ground-truth
    field to the object; ``vo0``: the object's vertices in the first frame): a hand vertex within
    :data:`CONTACT` of the object from frame m to n (>= :data:`WINDOW` frames; a contact still on in the last
    frame closes no window), whose nearest object vertices stay together (the mean of their pairwise
    distances, ARCTIC's upper-triangle mask of the first WINDOW x WINDOW block left out, at most CONTACT);
    j the most frequent nearest object vertex (the smallest on a tie). Also returns how many windows start
    at the first frame: ARCTIC's own check of its windows then fails (it reads the frame before as the last)."""
    contacts = dist < CONTACT
    frames = len(dist)
    windows, stops = [], 0
    for v in np.flatnonzero(contacts.sum(axis=0) >= WINDOW):
        col = contacts[:, v]
        start = None
        for f in range(frames):
            if col[f] and start is None:
                start = f
            elif not col[f] and start is not None:
                end, s = f - 1, start
                start = None
                if end - s + 1 < WINDOW:
                    continue
                js = idx[s:end + 1, v]
                pts = vo0[js]
                pair = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
                rows, cols = np.triu_indices(WINDOW)
                pair[rows, cols] = np.nan
                if nanmean(pair.reshape(-1)) > CONTACT:
                    continue
                values, counts = np.unique(js, return_counts=True)
                windows.append((s, end, int(v), int(values[np.argmax(counts)])))
                stops += int(s == 0)
    return windows, stops


def motion_deviation(windows: list, pred_vh: np.ndarray, pred_vo: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """MDev (mm) per window: the mean over its valid consecutive frame pairs of the difference between the
    hand vertex's and the object vertex's motion."""
    out = []
    for m, n, i, j in windows:
        delta = np.diff(pred_vh[m:n + 1, i], axis=0) - np.diff(pred_vo[m:n + 1, j], axis=0)
        ok = (valid[m:n + 1][1:] * valid[m:n + 1][:-1]).astype(bool)
        out.append(nanmean(np.where(ok, np.linalg.norm(delta, axis=-1), np.nan)))
    return np.array(out, np.float64) * 1000


def field_metrics(pred: dict, gt: dict, flags: dict) -> dict:
    """The field task's vectors of one sequence and view: ``pred`` / ``gt`` ``dist.ro``, ``dist.lo`` (N, 778),
    ``dist.or``, ``dist.ol`` (N, V; a prediction's extra columns are cut); mm (averages) and m/s^2."""
    valid, rv, lv = _hands(flags)
    nv = gt["dist.or"].shape[1]
    p = {k: v[:, :nv] if k in ("dist.or", "dist.ol") else v for k, v in pred.items()}
    avg = {k: np.where(valid == 0, np.nan, np.abs(gt[k] - p[k]).mean(axis=1)) for k in gt}
    out = {"avg/ho": nanmean(np.stack([avg["dist.ro"], avg["dist.lo"]], 1), axis=1) * 1000,
           "avg/oh": nanmean(np.stack([avg["dist.or"], avg["dist.ol"]], 1), axis=1) * 1000}
    acc = {k: error_accel(gt[k][..., None], p[k][..., None]) for k in gt}
    ok = {"dist.ro": rv, "dist.lo": lv, "dist.or": valid, "dist.ol": valid}
    acc = {k: np.where(_valid3(ok[k]), a, np.nan) for k, a in acc.items()}
    out["acc/oh"] = _pad(nanmean(np.stack([acc["dist.or"], acc["dist.ol"]], 1), axis=1))
    out["acc/ho"] = _pad(nanmean(np.stack([acc["dist.ro"], acc["dist.lo"]], 1), axis=1))
    return out


def pool(parts: list[dict]) -> dict[str, float]:
    """Every key's vectors concatenated over sequences and views, then the mean of the non-NaN values."""
    keys = list(dict.fromkeys(k for p in parts for k in p))
    return {k: float(nanmean(np.concatenate([np.atleast_1d(p[k]) for p in parts if k in p]))) for k in keys}
