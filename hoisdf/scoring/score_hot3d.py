"""``hoisdf score hot3d``: a HOT3D hand-tracking challenge submission scored offline, as the challenge's evaluation
(``hand_tracking_toolkit/evaluation.py`` and ``metrics.py``, facebookresearch/hand_tracking_toolkit) scores it.

Submission (``submissions.write_mano_poses_file`` / ``write_mano_shapes_file`` there): a folder or a ``.tar`` holding
``result_pose_<suffix>.json`` (pose track) and/or ``result_shape_<suffix>.json`` (shape track), ``<suffix>`` one of
``umetrack``, ``hot3d``. Pose entries: ``sequence_name``, ``frame_id`` (int), ``mano_theta`` (15 PCA coefficients,
``flat_hand_mean=False``), ``wrist_xform`` (6: axis-angle, translation, metres), ``hand_side`` (1 right, 0 left).
Shape entries: ``sequence_name``, ``mano_beta`` (10), ``hand_side``. Ground truth folder: ``gt_landmarks_<suffix>.json``
(``sequence_name``, ``frame_id``, ``landmarks`` (20, 3) metres, the toolkit's landmark order) and
``gt_shape_<suffix>.json`` (as the shape entries), with ``mano/`` (MANO_RIGHT.pkl, MANO_LEFT.pkl) unless ``--mano``.

Scoring, as the server does: per sequence, entries sorted by ``frame_id`` (stable) and paired by position with the
ground truth's; the predicted pose posed with the sequence's first ground-truth betas through MANO (PCA 15,
``flat_hand_mean=False``; the left model's shape-direction fix where its file has the bug, as the toolkit checks);
landmarks = 15 MANO joints and the fingertip vertices 744, 320, 443, 554, 671 (:data:`TIP_VERTICES`), the wrist left
out; MPJPE (mm), PCK AUC over 0-50 mm (101 thresholds, 0-100) of all 19 and of the 5 tips; sequences weighted by
their entries. Shape track: MPVPE (mm) of the zero-pose left-hand meshes, the mean over sequences.

Stricter than the server (each one ``error:`` line naming the file, entry and field): a malformed entry, a
sequence of the ground truth missing from the submission or with another number of entries (the server crashes or
misaligns). Entries whose ``frame_id`` / ``hand_side`` differ from the ground truth's at the same position are
scored as the server scores them, with a warning.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.hand import load_mano, read_mano_file
from hoidata.hand.pose import pca_to_axis_angle
from hoidata.reading import list_tar, parse_json, read_bytes
from hoidata.shapes import Integer, ListOf, Numbers, Record, String, check

HELP = "HOT3D hand-tracking challenge submission (result_pose/shape_<suffix>.json) against its ground truth"
SUFFIXES = ("umetrack", "hot3d")  # the server scores each one present
TIP_VERTICES = (744, 320, 443, 554, 671)  # the toolkit's fingertips (thumb to pinky), MANO vertex ids
# the toolkit's 20 landmarks (5 tips, the wrist, thumb 2, index 3, middle 3, ring 3, pinky 3) as DexYCB joints
# (wrist, then four joints per finger base to tip, thumb first); the tips are replaced by TIP_VERTICES
CANONICAL = (4, 8, 12, 16, 20, 0, 2, 3, 5, 6, 7, 9, 10, 11, 13, 14, 15, 17, 18, 19)
EVALUATED = tuple(i for i in range(20) if i != 5)  # the wrist (5) is not scored (UmeTrack's differs from MANO's)
THRESHOLDS_MM = np.linspace(0.0, 50.0, 101)
POSE_FIELDS = {"mano_theta": 15, "wrist_xform": 6}


def add_arguments(p) -> None:
    p.add_argument("--pred", required=True, type=Path, metavar="DIR|SUBMISSION.tar", help="the submission")
    p.add_argument("--gt", required=True, type=Path, metavar="DIR",
                   help="folder with gt_landmarks_<suffix>.json and gt_shape_<suffix>.json (and mano/)")
    p.add_argument("--mano", type=Path, default=None, metavar="DIR", help="MANO folder (default: GT/mano)")
    p.add_argument("--track", choices=("pose", "shape"), default="pose",
                   help="the challenge phase: pose_estimation or shape_estimation")


def _member(source: Path, name: str):
    """The parsed JSON file ``name`` of a folder or tar (at any depth of the tar; two of that name are an error
    naming both), or None when absent."""
    source = Path(source)
    if source.is_dir():
        path = source / name
        return parse_json(read_bytes(path, "HOT3D result file"), path) if path.is_file() else None
    if not source.is_file():
        raise DataError(source, None, "not found: give the submission folder or its .tar")
    listing = list_tar(source, lambda member: name if Path(member).name == name else None, "tar")
    if name not in listing.members:
        if listing.truncated:
            raise DataError(source, None, f"not a readable tar ({listing.truncated})")
        return None
    where = f"{source}:{listing.members[name].name}"
    return parse_json(listing.read(name), where)


def _entries_shape(arrays: dict, with_frame: bool, side: bool) -> ListOf:
    """The declared shape of a result or ground-truth file: a list of entries, each with a ``sequence_name``,
    the numbers ``arrays`` (key -> shape) and, as asked, an integer ``frame_id`` and ``hand_side`` 0 / 1."""
    required = {"sequence_name": String(), **{k: Numbers(shape) for k, shape in arrays.items()}}
    if with_frame:
        required["frame_id"] = Integer()
    if side:
        required["hand_side"] = Integer(0, 1)
    return ListOf(Record(required), label="entry {}")


def read_entries(entries, where, arrays: dict, with_frame: bool = True, side: bool = True) -> dict:
    """Entries grouped per ``sequence_name``, each sorted by ``frame_id`` (stable, as the toolkit's
    ``group_by_sequence_names``): ``{sequence: {"frame_id": (N,), "hand_side": (N,), key: (N, *shape)}}``.
    Checked against their declared shape first (a string or boolean is never a number; NaN is named)."""
    rows: dict[str, list] = {}
    for entry in check(entries, _entries_shape(arrays, with_frame, side), where):
        row = {k: entry[k] for k in arrays} | {k: entry.get(k, 0) for k in ("frame_id", "hand_side")}
        rows.setdefault(entry["sequence_name"], []).append(row)
    out = {}
    for seq, items in rows.items():
        items.sort(key=lambda r: r["frame_id"])
        out[seq] = {k: np.stack([np.asarray(r[k]) for r in items]) for k in items[0]}
    return out


class HandModels:
    """MANO right and left (float64) as the toolkit's ``MANOHandModel`` builds them: the left model's
    ``shapedirs[:, 0]`` negated only where its file carries the right hand's (their difference sums below 1)."""

    def __init__(self, mano_dir: Path):
        import torch  # the MANO layer is torch's; scoring files imports it only to pose hands

        left, right = read_mano_file(mano_dir, "left", False), read_mano_file(mano_dir, "right", False)
        buggy = np.abs(left.shapedirs[:, 0, :] - right.shapedirs[:, 0, :]).sum() < 1
        self.layers = {1: load_mano(mano_dir, "right", dtype=torch.float64),
                       0: load_mano(mano_dir, "left", fix_left_shapedirs=bool(buggy), dtype=torch.float64)}

    def __call__(self, theta, wrist, betas, side) -> tuple[np.ndarray, np.ndarray]:
        """(N, 20, 3) landmarks and (N, 778, 3) vertices, metres, of N poses (the toolkit's ``forward_kinematics``)."""
        import torch

        n = len(theta)
        landmarks, verts = np.zeros((n, 20, 3)), np.zeros((n, 778, 3))
        for s, mano in self.layers.items():
            rows = np.flatnonzero(np.asarray(side) == s)
            if not len(rows):
                continue
            pose = pca_to_axis_angle(np.concatenate([wrist[rows, :3], theta[rows]], 1),
                                     mano.hands_components.double().numpy(), mano.hands_mean.double().numpy())
            with torch.no_grad():
                out = mano(torch.as_tensor(pose), torch.as_tensor(betas[rows]), torch.as_tensor(wrist[rows, 3:]))
            v, j = out.vertices.double().numpy(), out.joints.double().numpy()
            landmarks[rows] = j[:, list(CANONICAL)]
            landmarks[rows, :5] = v[:, list(TIP_VERTICES)]
            verts[rows] = v
        return landmarks, verts


def pose_metrics(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """MPJPE (mm) and PCK AUCs (0-100) of (N, 20, 3) landmarks in metres, over the 19 EVALUATED landmarks."""
    err = np.linalg.norm(pred[:, EVALUATED] - gt[:, EVALUATED], axis=-1) * 1000.0
    return {"MPJPE": float(err.mean()), "PCK_AUC": _auc(err), "FINGERTIP_PCK_AUC": _auc(err[:, :5])}


def _auc(err_mm: np.ndarray) -> float:
    pck = np.array([(err_mm <= t).mean() * 100.0 for t in THRESHOLDS_MM])
    return float(np.trapezoid(pck, THRESHOLDS_MM) / (THRESHOLDS_MM[-1] - THRESHOLDS_MM[0]))


def score_pose(pred: dict, gt_landmarks: dict, gt_shape: dict, models: HandModels, where, warnings: list) -> dict:
    per, weights = [], []
    for seq, gt in gt_landmarks.items():
        if seq not in pred:
            raise DataError(where, seq, "sequence of the ground truth missing from the submission")
        p, n = pred[seq], len(gt["landmarks"])
        if len(p["mano_theta"]) != n:
            raise DataError(where, seq, f"{len(p['mano_theta'])} entries, the ground truth has {n}")
        if seq not in gt_shape:
            raise DataError(where, seq, "no ground-truth shape for this sequence")
        if (p["frame_id"] != gt["frame_id"]).any():
            warnings.append(f"{seq}: frame_id differs from the ground truth's at the same position (paired by position)")
        betas = np.repeat(gt_shape[seq]["mano_beta"][:1], n, 0)
        landmarks, _ = models(p["mano_theta"], p["wrist_xform"], betas, p["hand_side"])
        per.append(pose_metrics(landmarks, gt["landmarks"]))
        weights.append(n)
    return {k: float(np.average([m[k] for m in per], weights=weights)) for k in per[0]} | {"entries": sum(weights)}


def score_shape(pred: dict, gt_shape: dict, models: HandModels, where) -> dict:
    errors = []
    for seq, gt in gt_shape.items():
        if seq not in pred:
            raise DataError(where, seq, "sequence of the ground truth missing from the submission")
        a, b = pred[seq]["mano_beta"], gt["mano_beta"]
        if len(a) != len(b):
            raise DataError(where, seq, f"{len(a)} entries, the ground truth has {len(b)}")
        zero_t, zero_w, left = np.zeros((2 * len(a), 15)), np.zeros((2 * len(a), 6)), np.zeros(2 * len(a), int)
        _, verts = models(zero_t, zero_w, np.concatenate([a, b]), left)  # the toolkit poses both as left hands
        errors.append(float(np.linalg.norm(verts[:len(a)] - verts[len(a):], axis=-1).mean() * 1000.0))
    return {"MPVPE": float(np.mean(errors)), "entries": len(errors)}


def score(args) -> dict:
    """The scores of ``args.pred`` (see the module docstring) per dataset suffix present, as
    ``<suffix>_<METRIC>`` (mm / 0-100), plus ``samples``, ``official``, ``note``, ``warnings``."""
    mano_dir = args.mano or Path(args.gt) / "mano"
    models, out, warnings, samples = None, {}, [], 0
    for suffix in SUFFIXES:
        name = f"result_{args.track}_{suffix}.json"
        entries = _member(args.pred, name)
        if entries is None:
            continue
        where = f"{args.pred}:{name}" if Path(args.pred).is_file() else Path(args.pred) / name
        models = models or HandModels(mano_dir)
        gt_shape = read_entries(_member(args.gt, f"gt_shape_{suffix}.json") or _missing(args.gt, suffix, "shape"),
                                Path(args.gt) / f"gt_shape_{suffix}.json", {"mano_beta": (10,)}, with_frame=False)
        if args.track == "pose":
            gt = read_entries(_member(args.gt, f"gt_landmarks_{suffix}.json") or _missing(args.gt, suffix, "landmarks"),
                              Path(args.gt) / f"gt_landmarks_{suffix}.json", {"landmarks": (20, 3)}, side=False)
            pred = read_entries(entries, where, {k: (n,) for k, n in POSE_FIELDS.items()})
            result = score_pose(pred, gt, gt_shape, models, where, warnings)
        else:
            pred = read_entries(entries, where, {"mano_beta": (10,)}, with_frame=False)
            result = score_shape(pred, gt_shape, models, where)
        samples += result.pop("entries")
        out.update({f"{suffix}_{k}": v for k, v in result.items()})
    if not out:
        raise DataError(args.pred, None, f"no result_{args.track}_<{'|'.join(SUFFIXES)}>.json in the submission")
    return {**out, "samples": samples, "official": False, "warnings": warnings, "track": args.track,
            "note": "scored as the challenge's evaluation.py; the official test ground truth is held by its server",
            "pred_file": str(args.pred), "ground_truth": str(args.gt)}


def _missing(gt_dir, suffix: str, kind: str):
    raise DataError(Path(gt_dir) / f"gt_{kind}_{suffix}.json", None, "ground truth missing for a scored suffix")


def format_result(result: dict) -> str:
    lines = [f"HOT3D challenge {result['track']} scores of {result['pred_file']} ({result['samples']} "
             f"{'entries' if result['track'] == 'pose' else 'sequences'})", f"  {result['note']}"]
    lines += [f"  warning: {w}" for w in result["warnings"]]
    for key, value in result.items():
        if key.startswith(SUFFIXES) and isinstance(value, float):
            unit = "mm" if key.endswith(("MPJPE", "MPVPE")) else ""
            lines.append(f"  {key:<28} {value:10.4f} {unit}".rstrip())
    return "\n".join(lines)
