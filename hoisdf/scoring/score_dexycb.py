"""``hoisdf score dexycb``: any method's DexYCB HPE result file scored as dex-ycb-toolkit's ``hpe_eval.py`` does.

Ground truth (``HPEEvaluator._generate_anno_file``): every sample of the toolkit split (``s0_test`` etc.,
enumerated as ``DexYCBDataset`` does: :func:`hoidata.datasets.dexycb_layout.toolkit_split`), its
``labels_%06d.npz`` ``joint_3d`` times 1000 in float32, then float64; samples whose joints are all -1 are left out.
Result file (``_load_results``): one line per sample, the integer sample index and 63 millimetre coordinates
(:func:`hoisdf.scoring.submissions.read_dexycb_hpe`). Every valid sample must be in it (the toolkit's assert);
lines may come in any order. Numbers: :func:`hoisdf.scoring.official.dexycb_hpe_scores`, the toolkit's
MPJPE (mm) and AUC (0-50 mm) for ``absolute``, ``root-relative`` and ``procrustes``.

Stricter than the toolkit, each as one line naming the file and line: a duplicate index (the toolkit keeps the
last), an index outside the split (it ignores those), NaN or a wrong column count.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.datasets.dexycb_layout import (
    SEQUENCES_PER_SUBJECT,
    SUBJECTS,
    label_path,
    list_sequences,
    read_labels,
    read_meta,
    split_members,
    toolkit_split,
)
from hoidata.errors import DataError
from hoisdf.scoring.official import HPE_ALIGNMENTS, dexycb_hpe_scores, toolkit_gt_mm
from hoisdf.scoring.submissions import read_dexycb_hpe

HELP = "DexYCB HPE result file (dex-ycb-toolkit format) against a DexYCB folder's labels (hpe_eval.py's numbers)"


def add_arguments(p) -> None:
    p.add_argument("--pred", required=True, type=Path, metavar="RESULT.txt", help="the HPE result file")
    p.add_argument("--root", required=True, type=Path, metavar="DEXYCB_DIR", help="the DexYCB folder ($DEX_YCB_DIR)")
    p.add_argument("--split", default="s0_test", metavar="SETUP_SPLIT",
                   help="the toolkit's dataset name: s0..s3 _ train|val|test (default s0_test)")


def _parse_split(name: str) -> tuple[str, str]:
    setup, _, split = name.partition("_")
    split_members(setup, split)  # ValueError naming an unknown setup or split
    return setup, split


def toolkit_ground_truth(root: Path, name: str) -> tuple[dict[int, np.ndarray], int, str, bool]:
    """The toolkit's HPE ground truth of a split ``name`` (e.g. 's0_test') under ``root``.

    Returns ({sample index: (21, 3) mm float64} of the valid samples in index order, the split's size, {sample
    index: 'subject/sequence/serial frame f'} for messages, whether every subject of the split is present with
    its 100 sequences). Raises DataError naming a missing or malformed label file."""
    setup, split = _parse_split(name)
    root = Path(root)
    enum = toolkit_split(root, setup, split)
    gt, where = {}, {}
    for key, (start, frames) in enum.first.items():
        seq_dir = root / key
        objects = len(read_meta(seq_dir)["ycb_ids"])
        for c, serial in enumerate(enum.serials):
            for f in range(frames):
                joints = read_labels(label_path(seq_dir, serial, f), objects, keys=("joint_3d",))["joint_3d"]
                index = start + c * frames + f
                where[index] = f"{key}/{serial} frame {f}"
                if not np.all(joints == -1):
                    gt[index] = toolkit_gt_mm(joints.reshape(21, 3))
    subjects = split_members(setup, split)[0]
    complete = all(len(list_sequences(root, SUBJECTS[s])) == SEQUENCES_PER_SUBJECT for s in subjects)
    return gt, enum.size, where, complete


def match_results(path: Path, ids: np.ndarray, gt: dict, size: int, where: dict) -> np.ndarray:
    """Rows of the result file in the order of the valid ground-truth indices; DataError naming the line of an
    index outside the split, or the first valid sample without a line."""
    row = {int(i): k for k, i in enumerate(ids)}
    outside = [k for k, i in enumerate(ids) if not 0 <= i < size]
    if outside:
        k = outside[0]
        raise DataError(path, f"line {k + 1}", f"sample index {ids[k]} is not in the split (indices 0..{size - 1})")
    missing = [i for i in gt if i not in row]
    if missing:
        raise DataError(path, None, f"no line for sample index {missing[0]} ({where[missing[0]]}); {len(missing)} "
                        f"of the split's {len(gt)} valid samples missing (the toolkit stops at the first)")
    return np.array([row[i] for i in gt], dtype=np.int64)


def score(args) -> dict:
    """The toolkit's numbers for ``args.pred`` on ``args.split`` of ``args.root``: ``{alignment: {"mpjpe": mm,
    "auc": ratio}}`` for :data:`~hoisdf.scoring.official.HPE_ALIGNMENTS`, plus ``split``, ``samples`` (valid
    samples scored), ``ignored`` (lines of invalid samples), ``official``, ``note``, ``pred_file``, ``root``."""
    gt, size, where, complete = toolkit_ground_truth(args.root, args.split)
    if not gt:
        raise DataError(args.root, None, f"no sample of {args.split} with hand joints here ({size} samples found; "
                        "is this the DexYCB folder, with the split's subject folders?)")
    ids, pred_mm = read_dexycb_hpe(args.pred, unit="mm")
    rows = match_results(Path(args.pred), ids, gt, size, where)
    scores = dexycb_hpe_scores(pred_mm[rows], np.stack(list(gt.values())))
    note = (f"the whole {args.split} split, as hpe_eval.py scores it" if complete else
            f"some subjects of {args.split} are missing or incomplete under {args.root}: NOT the official number")
    return {**scores, "split": args.split, "samples": len(gt), "ignored": len(ids) - len(rows), "official": complete,
            "note": note, "pred_file": str(args.pred), "root": str(args.root)}


def format_result(result: dict) -> str:
    """The toolkit's table layout: alignment, MPJPE (mm), AUC."""
    lines = [f"DexYCB {result['split']} HPE scores of {result['pred_file']} ({result['samples']} samples"
             + (f"; {result['ignored']} lines of samples without hand joints ignored" if result["ignored"] else "")
             + ")", f"  {result['note']}", f"  {'alignment':<14}{'MPJPE (mm)':>12}{'AUC':>9}"]
    lines += [f"  {a:<14}{result[a]['mpjpe']:12.4f}{result[a]['auc']:9.4f}" for a in HPE_ALIGNMENTS]
    return "\n".join(lines)
