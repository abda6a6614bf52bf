"""``dataset.frame_list = PATH``: build exactly the frames of a published DexYCB frame list.

The format is gSDF's (``zerchen/gSDF:datasets/dexycb/splits/*.json``, e.g. ``train_s0_29k.json`` /
``test_s0_5k.json``): one JSON list of dex-ycb-toolkit sample indices of one split, written as zero-padded
decimal strings (``"00000030"``); plain integers are accepted too. The ids index the toolkit's enumeration of
the split (``hoidata.datasets.dexycb_layout.ToolkitSplit``), so a list picks frames, not a rule: the setting's
``sides``, ``frame_stride`` and ``proximity_mm`` are not applied (left hands in a list are mirrored). A listed
frame whose annotation the reader cannot use is skipped with its reason like any other; an id the dataset does
not have (past the split's end, or a camera or frame missing on disk) is an error naming it.
"""

from __future__ import annotations

import hashlib
from collections import Counter
from pathlib import Path

from hoidata.errors import DataError
from hoidata.reading import read_bytes, read_json

SHOWN = 8  # ids named in an error message


def read_frame_list(path) -> tuple[int, ...]:
    """The sorted, unique sample ids of a frame-list JSON file; DataError naming the file and the bad item."""
    path = Path(path)
    items = read_json(path, "frame list")
    if not isinstance(items, list) or not items:
        raise DataError(path, None, "expected a non-empty JSON list of sample ids")
    ids = []
    for n, item in enumerate(items):
        text = item if isinstance(item, str) else None
        if isinstance(item, int) and not isinstance(item, bool) and item >= 0:
            ids.append(item)
        elif text is not None and text.isascii() and text.isdigit():
            ids.append(int(text))
        else:
            raise DataError(path, f"item {n}", f"{item!r} is not a sample id (a non-negative integer or digit string)")
    if len(set(ids)) != len(ids):
        twice = sorted(i for i, n in Counter(ids).items() if n > 1)
        raise DataError(path, None, f"ids listed more than once: {twice[:SHOWN]}")
    return tuple(sorted(ids))


def check_listed(path, ids, frames, skips, toolkit) -> None:
    """Every listed id must be a frame of the dataset: built (``frames``) or skipped with a reason (``skips``).

    ``toolkit``: the reader's ToolkitSplit (None when its enumeration could not be read). Raises DataError naming
    the file and the first ids that are not.
    """
    if toolkit is None:
        raise DataError(path, None, "the split's sample ids are unknown (a meta.yml could not be read; see the skips)")
    found = {f.sample_index for f in frames} | {s.sample_index for s in skips}
    missing = [i for i in ids if i not in found]
    if missing:
        beyond = sum(i >= toolkit.size for i in missing)
        raise DataError(path, None, f"{len(missing)} listed ids are not frames of this dataset's {toolkit.name} "
                                    f"({toolkit.size} samples; {beyond} past its end, the others' files are missing): "
                                    f"{missing[:SHOWN]}{' ...' if len(missing) > SHOWN else ''}")


def frame_list_provenance(path, ids) -> dict:
    """What the index records about the list: its path, sha256 and number of ids."""
    return {"path": str(path), "sha256": hashlib.sha256(read_bytes(path, "frame list")).hexdigest(), "ids": len(ids)}
