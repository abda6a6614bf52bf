"""``hoisdf score ho3d``: any method's HO-3D challenge submission scored offline, as the server's eval.py scores it.

Inputs: a ``pred.json`` (or the ``pred.zip`` holding it) in the challenge layout (``[xyz_list, verts_list]``,
metres, OpenGL frame, HO-3D joint order, ``evaluation.txt`` order; :mod:`hoisdf.scoring.submissions`) and the
folder of the released ground truth, ``evaluation_xyz.json`` / ``evaluation_verts.json`` (plus ``evaluation.txt``
for a subset). The 14 numbers are :func:`hoisdf.scoring.official.ho3d_challenge_scores`, the ones eval.py
writes to ``scores.txt``, under its names and in its units.

A result is ``official`` only when the whole evaluation split of the version was scored (11,524 samples for v2,
20,137 for v3, eval.py's ``db_size``); a subset (``--subset PREFIX`` or ``--ids FILE``) or ground truth of another
size says so in ``note``, and the printed table repeats it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.hand import DEXYCB_TO_MANO
from hoidata.reading import read_lines, read_text
from hoisdf.scoring.official import (
    HO3D_EVALUATION_SIZES,
    HO3D_SCORES,
    HO3D_UNITS,
    ho3d_challenge_scores,
    read_ho3d_gt,
)
from hoisdf.scoring.submissions import read_ho3d_lists

HELP = "HO-3D challenge pred.json / pred.zip against the released evaluation ground truth (scores.txt's 14 numbers)"
WRIST_WARNING_M = 0.2  # a median wrist error above this is far beyond any method: a wrong frame or order


def add_arguments(p) -> None:
    p.add_argument("--pred", required=True, type=Path, metavar="PRED.json|PRED.zip", help="the submission file")
    p.add_argument("--gt", required=True, type=Path, metavar="DIR",
                   help="folder with evaluation_xyz.json, evaluation_verts.json (and evaluation.txt for a subset)")
    p.add_argument("--version", choices=sorted(HO3D_EVALUATION_SIZES), default="v2",
                   help="HO-3D version of the ground truth (the full split's size: v2 11,524, v3 20,137)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--subset", default=None, metavar="PREFIX",
                       help="score only the evaluation.txt entries starting with PREFIX (e.g. a sequence 'SM1/')")
    which.add_argument("--ids", type=Path, default=None, metavar="FILE",
                       help="score only the SEQ/id entries listed in FILE (one a line)")


def read_order(gt_dir: Path) -> list[str]:
    """``evaluation.txt`` of the ground-truth folder: its ``SEQ/id`` entries in file order."""
    path = Path(gt_dir) / "evaluation.txt"
    if not path.is_file():
        raise DataError(path, None, "a subset needs the evaluation list beside the ground truth")
    return read_lines(path, "HO-3D evaluation list")


def subset_rows(order: list[str], prefix: str | None, ids_file: Path | None) -> np.ndarray:
    """Row numbers (into ``order``) of a subset: the entries starting with ``prefix``, or those listed in
    ``ids_file`` (in the list's order; an unknown or repeated id is an error naming the line)."""
    if prefix is not None:
        rows = [i for i, entry in enumerate(order) if entry.startswith(prefix)]
        if not rows:
            raise ValueError(f"--subset {prefix!r}: no evaluation.txt entry starts with it")
        return np.asarray(rows)
    where = {entry: i for i, entry in enumerate(order)}
    rows, seen = [], {}
    for number, line in enumerate(read_text(ids_file, "list of SEQ/id entries").splitlines(), start=1):
        entry = line.strip()
        if not entry:
            continue
        if entry not in where:
            raise DataError(ids_file, f"line {number}", f"{entry!r} is not an entry of evaluation.txt")
        if entry in seen:
            raise DataError(ids_file, f"line {number}", f"{entry!r} already on line {seen[entry]}")
        seen[entry] = number
        rows.append(where[entry])
    if not rows:
        raise DataError(ids_file, None, "lists no SEQ/id entry")
    return np.asarray(rows)


def _select(pred: tuple, gt: tuple, rows: np.ndarray | None, full: int, pred_path: Path) -> tuple:
    """The prediction and ground-truth rows to score: all, or a subset given a full-length or a subset-length
    prediction (a subset-length file holds the subset's samples in the subset's order)."""
    n = len(pred[0])
    if rows is None:
        if n != full:
            raise DataError(pred_path, None, f"{n} samples, the ground truth has {full} (eval.py: 'Expected format "
                            "mismatch'); a file for part of the split is scored with --subset or --ids")
        return pred, gt
    if n == full:
        return tuple(a[rows] for a in pred), tuple(a[rows] for a in gt)
    if n == len(rows):
        return pred, tuple(a[rows] for a in gt)
    raise DataError(pred_path, None, f"{n} samples: neither the full split ({full}) nor the subset ({len(rows)})")


def _wrist_profile(xyz: np.ndarray) -> np.ndarray:
    """(21,) median over samples of each joint's distance to joint 0: the joint order's fingerprint."""
    return np.median(np.linalg.norm(xyz - xyz[:, :1], axis=-1), axis=0)


def _warnings(pred_xyz: np.ndarray, gt_xyz: np.ndarray) -> list[str]:
    """Signs of a file in the wrong frame, unit, joint order or sample order (scored anyway, as the server would:
    pred.json carries no ids, so its order cannot be checked directly)."""
    if not len(pred_xyz):
        return []
    out = []
    if np.all(pred_xyz[..., 2] > 0):
        out.append("every joint has positive z: the challenge expects the OpenGL frame (scene at negative z); "
                   "the server's pred.py refuses such a file")
    prof, ref = _wrist_profile(pred_xyz), _wrist_profile(gt_xyz)
    if np.median(prof) > 50 * max(np.median(ref), 1e-6):
        out.append("the hand is over 50 times the ground truth's size: are the joints in millimetres? "
                   "(metres expected)")
    elif np.abs(prof[DEXYCB_TO_MANO] - ref).mean() < 0.5 * np.abs(prof - ref).mean():
        out.append("the joints look like DexYCB/manopth order (wrist, thumb 1-4, ...): the challenge expects HO-3D's "
                   "(16 MANO joints, then the 5 tips)")
    wrist = float(np.median(np.linalg.norm(pred_xyz[:, 0] - gt_xyz[:, 0], axis=-1)))
    if wrist > WRIST_WARNING_M:
        out.append(f"median wrist error {wrist * 100:.1f} cm: check the frame (OpenGL, metres) and the sample "
                   "order (evaluation.txt's)")
    return out


def score(args) -> dict:
    """The scores of ``args.pred`` against ``args.gt`` (see the module docstring): the 14 names of
    :data:`~hoisdf.scoring.official.HO3D_SCORES` plus ``samples``, ``official``, ``note``, ``warnings``,
    ``units``, ``version``, ``pred_file`` and ``ground_truth``. Raises DataError naming the file, entry and field of
    a malformed submission."""
    pred = read_ho3d_lists(args.pred)
    gt = read_ho3d_gt(args.gt)
    if pred[1].shape[1] == 0:
        raise DataError(args.pred, "verts_list", "every sample has no vertices: the server's eval.py cannot score "
                        "that (it fails aligning them); give the (778, 3) MANO vertices, or any (V, 3) points")
    subset = args.subset is not None or args.ids is not None
    rows = None
    if subset:
        order = read_order(args.gt)
        if len(order) != len(gt[0]):
            raise DataError(Path(args.gt) / "evaluation.txt", None, f"{len(order)} entries, the ground truth has "
                            f"{len(gt[0])}")
        rows = subset_rows(order, args.subset, args.ids)
    (pred_xyz, pred_verts), (gt_xyz, gt_verts) = _select(pred, gt, rows, len(gt[0]), Path(args.pred))
    scores = ho3d_challenge_scores(pred_xyz, pred_verts, gt_xyz, gt_verts)
    size = HO3D_EVALUATION_SIZES[args.version]
    official = not subset and len(gt[0]) == size
    if subset:
        note = (f"SUBSET: {len(rows)} of the {len(gt[0])} evaluation samples; NOT the official full-set number "
                "(the challenge scores the whole split)")
    elif not official:
        note = (f"the ground truth holds {len(gt[0])} samples, HO-3D {args.version}'s evaluation split {size}: "
                "NOT the official full-set number")
    else:
        note = f"the whole HO-3D {args.version} evaluation split, as the challenge server scores it"
    return {**scores, "samples": len(pred_xyz), "official": official, "note": note,
            "warnings": _warnings(pred_xyz, gt_xyz), "units": HO3D_UNITS, "version": args.version,
            "pred_file": str(args.pred), "ground_truth": str(args.gt)}


def format_result(result: dict) -> str:
    """The printed table: the note, then one line per score name with its value and unit."""
    width = max(map(len, HO3D_SCORES))
    lines = [f"HO-3D {result['version']} challenge scores of {result['pred_file']} ({result['samples']} samples)",
             f"  {result['note']}"]
    lines += [f"  warning: {w}" for w in result["warnings"]]
    for name in HO3D_SCORES:
        unit = "cm" if name.endswith("mean3d") else ""
        lines.append(f"  {name:<{width}}  {result[name]:10.6f} {unit}".rstrip())
    return "\n".join(lines)
