"""HO-3D's evaluation list (``evaluation.txt``), checked before a submission is made from it.

The challenge pairs predictions with its ground truth by position (``shreyashampali/ho3d:eval.py`` ``main``: the
i-th item of ``pred.json``'s two lists is scored against the i-th item of ``evaluation_xyz.json`` /
``evaluation_verts.json``, which are in ``evaluation.txt`` order, and it asserts both lists have exactly as many
items as the ground truth), and ``pred.py`` builds those lists from ``evaluation.txt`` read with ``readlines()``, one
entry per line. So a list given to ``--ho3d-order`` must be that file exactly: one ``<SEQ>/<id>`` per line, each
frame once, every frame of the evaluated store and none else, in the ground truth's order. Anything else
(a duplicated, missing, unknown or reordered line, a byte-order mark, CR LF line ends, a blank line, a trailing
one included) is refused with one line naming the file, the line and the entry, before any work.
"""

from __future__ import annotations

import re
from pathlib import Path

from hoidata.errors import DataError
from hoidata.reading import read_bytes

ENTRY = re.compile(r"[^/\s]+/[^/\s]+")  # <SEQ>/<id>, as pred.py splits it
LIST_NAME = "evaluation.txt"


def ho3d_entry(frame_id: str) -> str:
    """A record's HO-3D frame id (``SEQ_id``, :class:`hoidata.datasets.ho3d.HO3DReader`) -> the list's ``SEQ/id``."""
    return "/".join(str(frame_id).rsplit("_", 1))


def _line_problem(raw: bytes, number: int) -> tuple[str, str] | None:
    """(entry as shown, problem) of one line of the file (without its LF), or None if it is a clean entry."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return repr(raw[:60]), "not UTF-8 text"
    if number == 1 and text.startswith("\ufeff"):
        return repr(text[1:]), ("starts with a byte-order mark (U+FEFF), which pred.py would read as part of the "
                                "first frame's name; save the file as UTF-8 without it")
    if text.endswith("\r"):
        return repr(text[:-1]), "ends with CR LF; the challenge's list has LF line ends (convert it, e.g. dos2unix)"
    if not text.strip():
        return repr(text), "blank line; the list has one frame per line and no blank lines (pred.py would count it)"
    if not ENTRY.fullmatch(text):
        return repr(text), "expected one '<SEQ>/<id>' and nothing else on the line"
    return None


def read_evaluation_list(path) -> list[str]:
    """The entries of an HO-3D ``evaluation.txt``, refused (DataError naming the file, the 1-based line and the
    entry) unless every line is exactly one ``<SEQ>/<id>``, LF-terminated (the last line may lack its LF), each
    entry once."""
    path = Path(path)
    data = read_bytes(path, "HO-3D evaluation list")
    lines = data.split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()  # the LF that ends the last line
    if not lines:
        raise DataError(path, None, "empty HO-3D evaluation list")
    entries, first_seen = [], {}
    for number, raw in enumerate(lines, 1):
        problem = _line_problem(raw, number)
        if problem:
            raise DataError(path, f"line {number}", f"{problem[0]}: {problem[1]}")
        entry = raw.decode("utf-8")
        if entry in first_seen:
            raise DataError(path, f"line {number}", f"{entry!r} again (first on line {first_seen[entry]}); each "
                                                    "frame must have exactly one prediction")
        first_seen[entry] = number
        entries.append(entry)
    return entries


def check_against_store(order: list[str], path, store, frame_ids, skipped=()) -> None:
    """Refuse a list that is not exactly the frames of an HO-3D store: an entry the store lacks (naming why, when
    the build skipped that frame) or a store frame the list lacks.

    Args:
        order: :func:`read_evaluation_list`'s entries. path: the list file (for messages). store: the store (for
            messages). frame_ids: the store's records' ``frame_id`` labels (``SEQ_id``). skipped: the index's
            skipped entries (dicts with ``frame_id`` and ``reason``).
    """
    have = {ho3d_entry(f) for f in frame_ids}
    why = {ho3d_entry(s.get("frame_id", "")): s.get("reason", "") for s in skipped if isinstance(s, dict)}
    for number, entry in enumerate(order, 1):
        if entry not in have:
            reason = f" (the build skipped it: {why[entry]})" if entry in why else ""
            raise DataError(path, f"line {number}", f"{entry!r} is not a record of {store}{reason}; a submission "
                                                    "needs a prediction for every line")
    listed = set(order)
    absent = sorted(have - listed)
    if absent:
        raise DataError(path, None, f"{len(absent)} of the {len(have)} frames of {store} are not in the list "
                                    f"(e.g. {absent[0]!r}): not the challenge's list for this store")


def check_against_ground_truth(order: list[str], path, gt_folder) -> None:
    """Refuse a list that differs from the ground truth's own ``GT/evaluation.txt`` in content or order: the
    server scores the i-th prediction against the i-th ground-truth item, so another order is scored silently
    wrong. The first differing line is named."""
    gt_path = Path(gt_folder) / LIST_NAME
    if not gt_path.is_file():
        raise DataError(gt_path, None, "not found: --ho3d-gt needs the ground truth's own evaluation list, whose "
                                       "order its evaluation_xyz.json and evaluation_verts.json follow")
    truth = read_evaluation_list(gt_path)
    for number, (entry, expected) in enumerate(zip(order, truth), 1):
        if entry != expected:
            raise DataError(path, f"line {number}", f"{entry!r}, but line {number} of {gt_path} is {expected!r}: "
                                                    "the server pairs predictions with its list by position")
    if len(order) != len(truth):
        number = min(len(order), len(truth)) + 1
        raise DataError(path, f"line {number}", f"the list has {len(order)} lines, {gt_path} has {len(truth)}")
