"""Record kinds on the training side: refuse stores training cannot use, fill in what evaluation records lack.

A store may hold ``eval`` records (``hoidata.schema.RECORD_KINDS``: HO-3D's evaluation split), which have no hand
labels, masks, heatmap or SDF samples. Training refuses them with one error naming the store; evaluation reads
them with those labels as NaN, which scoring treats as "no ground truth".
"""

from __future__ import annotations

import numpy as np

from hoidata import schema
from hoidata.errors import DataError


def fill_absent_labels(meta: dict, rec: dict, n_hand: int, n_object: int) -> tuple[dict, dict]:
    """An eval record's missing labels for evaluation: NaN hand labels (scored as 'no ground truth'), empty
    masks and heatmap, and zero SDF rows to draw from (evaluation drops the drawn points)."""
    half = rec[schema.IMG].shape[0] // 2
    meta = {**meta, **{name: np.full(schema.META_FIELDS[name][0], np.nan) for name in schema.EVAL_ABSENT}}
    meta["sdf_counts"] = np.array([n_hand, n_object, 0])
    sdf = np.zeros((n_hand + n_object, len(schema.SDF_COLUMNS)), schema.SDF_DTYPE)
    rec = {**rec, schema.SEG: np.zeros((half, half), np.uint8), schema.HEATMAP: np.zeros((half, half), np.uint8),
           schema.SDF: sdf}
    return meta, rec


def check_trainable(path, index) -> None:
    """A store training can use: every record ``full``; else one DataError naming the store and the missing labels."""
    kinds = index.labels["kind"]
    other = kinds != schema.FULL
    if other.any():
        raise DataError(path, "kind", f"{int(other.sum())} of {len(kinds)} records are {sorted(set(kinds[other].tolist()))} "
                                      f"records (e.g. HO-3D's evaluation split) without {', '.join(schema.EVAL_ABSENT)}"
                                      ": training needs them; evaluate this store with python -m hoisdf.evaluate")
