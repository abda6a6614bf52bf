"""Result files for the official evaluators: HO-3D challenge ``pred.json`` and DexYCB HPE ``.txt``.

HO-3D (docs/conventions.md, "The official evaluators"; ``shreyashampali/ho3d:pred.py``, ``eval.py``):
    ``pred.json`` is the JSON list ``[xyz_list, verts_list]``: N items of 21 x 3 joints and N items of
    778 x 3 vertices, metres, **OpenGL** camera frame (our OpenCV points times diag(1, -1, -1)), joints in
    HO-3D order (16 MANO joints, then the thumb..pinky tips), samples in ``evaluation.txt`` order
    (N = 11,524 for v2). The server expects it zipped as ``pred.zip``.

DexYCB (docs/conventions.md, "The official evaluators"; ``dex_ycb_toolkit/hpe_eval.py``):
    one line per sample, 64 comma-separated numbers: the integer sample index, then x1,y1,z1 ... x21,y21,z21
    in **millimetres**, camera frame, DexYCB joint order.

Inside the project joints are (N, 21, 3) metres, OpenCV frame, DexYCB/manopth order; these writers and
readers convert at the border, and each reader inverts its writer exactly (up to the text precision).
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hoidata.atomic import write_atomic
from hoidata.errors import DataError
from hoidata.hand import DEXYCB_TO_MANO, MANO_TO_DEXYCB, TIP_VERTICES
from hoidata.reading import is_zip, numbers_only, parse_json, read_bytes, read_text, read_zip_member
from hoidata.shapes import first_non_number, join, kind_of, not_finite

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])  # its own inverse
HO3D_TIP_VERTICES = TIP_VERTICES[("ho3d", "right")]  # thumb, index, middle, ring, pinky
DEXYCB_TIP_JOINTS = (4, 8, 12, 16, 20)  # thumb..little tips in DexYCB order
NUM_JOINTS = 21
HPE_COLUMNS = 1 + NUM_JOINTS * 3  # 64


def _points(x, name: str, count: int | None = None) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[2] != 3 or (count is not None and arr.shape[1] != count):
        want = f"(N, {count if count is not None else 'V'}, 3)"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} holds non-finite values")
    return arr


# ---------------------------------------------------------------- HO-3D pred.json

def _rows_in_order(ids: Sequence[str], order: Sequence[str] | None) -> np.ndarray:
    """Row index of each frame of ``order`` in ``ids``; raises naming the first missing frame."""
    ids = [str(i) for i in ids]
    row = {}
    for k, frame in enumerate(ids):
        if frame in row:
            raise ValueError(f"frame {frame!r} has two predictions (rows {row[frame]} and {k})")
        row[frame] = k
    if order is None:
        return np.arange(len(ids))
    missing = [str(f) for f in order if str(f) not in row]
    if missing:
        raise ValueError(f"no prediction for frame {missing[0]!r} of the evaluation list "
                         f"({len(missing)} of {len(order)} frames missing)")
    return np.array([row[str(f)] for f in order], dtype=np.int64)


def to_ho3d(joints, verts, tip_vertices: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Our convention -> HO-3D's: (N, 21, 3) joints, (N, V, 3) vertices, OpenCV, DexYCB order, metres ->
    OpenGL, HO-3D joint order, metres.

    ``tip_vertices`` (thumb..pinky vertex ids, e.g. :data:`HO3D_TIP_VERTICES`) replaces the five
    fingertip joints by those vertices first: HO-3D's ground truth takes its tips from 744/333/444/555/672,
    manopth (and so a model trained on DexYCB-style joints) from 745/317/444/556/673.
    """
    joints, verts = _points(joints, "joints", NUM_JOINTS), _points(verts, "verts")
    if tip_vertices is not None:
        joints = joints.copy()
        joints[:, list(DEXYCB_TIP_JOINTS)] = verts[:, list(tip_vertices)]
    return joints[:, DEXYCB_TO_MANO] @ OPENCV_TO_OPENGL.T, verts @ OPENCV_TO_OPENGL.T


def from_ho3d(joints, verts) -> tuple[np.ndarray, np.ndarray]:
    """HO-3D's convention -> ours (the inverse of :func:`to_ho3d` without tip replacement)."""
    joints, verts = _points(joints, "joints", NUM_JOINTS), _points(verts, "verts")
    return (joints @ OPENCV_TO_OPENGL.T)[:, MANO_TO_DEXYCB], verts @ OPENCV_TO_OPENGL.T


def write_ho3d_pred(path, ids: Sequence[str], joints, verts, order: Sequence[str] | None = None,
                    tip_vertices: Sequence[int] | None = None) -> Path:
    """Write an HO-3D challenge submission.

    Args:
        path: ``pred.json``, or a ``.zip`` path to get the archive the server takes (member ``pred.json``).
        ids: (N,) frame ids of the prediction rows, as in ``evaluation.txt`` (``SEQ/id``).
        joints: (N, 21, 3) metres, OpenCV camera frame, DexYCB order (absolute, not root-relative).
        verts: (N, V, 3) metres, OpenCV camera frame (V = 778 for the mesh metrics to be computed).
        order: the evaluation list; samples are written in this order, and a frame without a
            prediction is an error naming it. None writes the rows in the order given.
        tip_vertices: see :func:`to_ho3d`.

    Returns:
        The written path. Raises ValueError for missing frames, duplicate ids, bad shapes, or joints
        all at positive OpenGL z (the server's ``pred.py`` check: points behind the camera, usually
        joints already in OpenGL or root-relative).
    """
    path = Path(path)
    joints, verts = _points(joints, "joints", NUM_JOINTS), _points(verts, "verts")
    if not len(ids) == len(joints) == len(verts):
        raise ValueError(f"ids, joints and verts differ in length: {len(ids)}, {len(joints)}, {len(verts)}")
    rows = _rows_in_order(ids, order)
    gl_joints, gl_verts = to_ho3d(joints[rows], verts[rows], tip_vertices)
    if len(gl_joints) and np.all(gl_joints[..., 2] > 0):
        raise ValueError("every joint has positive z in OpenGL (negative depth in OpenCV): pass absolute "
                         "camera-frame joints in the OpenCV frame")
    text = json.dumps([gl_joints.tolist(), gl_verts.tolist()]).encode()
    if path.suffix == ".zip":
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("pred.json", text)
        text = buf.getvalue()
    write_atomic(path, text)
    return path


def _bad_entry(items: list, count: int | None) -> tuple[int, str] | None:
    """(index, problem) of the first item that is not a (count, 3) list of finite numbers (any K when ``count``
    is None, but the same K as item 0), or None. A string, boolean or null is never taken for a number (eval.py's
    numpy would take ``true`` for 1.0)."""
    want = count
    for i, item in enumerate(items):
        bad = first_non_number(item)
        if bad is not None:
            return i, f"expected numbers, got {kind_of(bad[1])}" + (f" (point {bad[0][0]})" if bad[0] else "")
        try:
            arr = np.array(item, dtype=np.float64)
        except (ValueError, TypeError):
            return i, "not a list of (x, y, z) lists of numbers (ragged)"
        if want is None and arr.ndim == 2:
            want = arr.shape[0]
        if arr.size == 0 and count is None and want in (None, 0):
            want = 0
            continue
        if arr.ndim != 2 or arr.shape != (want, 3):
            return i, f"expected {want if want is not None else 'K'} (x, y, z) points, got shape {arr.shape}"
        if not np.isfinite(arr).all():
            k = int(np.flatnonzero(~np.isfinite(arr).all(1))[0])
            return i, f"point {k} is not finite: {arr[k].tolist()}"
    return None


def _as_point_list(items, path, field: str, count: int | None, plain: bool) -> np.ndarray:
    """A JSON list of N (K, 3) nested lists -> (N, K, 3) float64, checked like the evaluator's reshape.

    A malformed item is named with its index, e.g. ``pred.json: 'xyz_list[17]': expected 21 (x, y, z) points,
    got shape (20, 3)``; with ``count`` None every item must have item 0's K (eval.py decides from item 0).
    ``plain``: the file holds numbers only (:func:`hoidata.reading.numbers_only`), so one conversion checks it."""
    if not isinstance(items, list):
        raise DataError(path, field, f"expected a list of samples, got {kind_of(items)}")
    if len(items) == 0:
        return np.zeros((0, count or 0, 3))
    arr = None
    if plain:
        try:
            arr = np.array(items, dtype=np.float64)
        except (ValueError, TypeError):
            arr = None
    ok = arr is not None and arr.ndim == 3 and arr.shape[2] == 3 and (count is None or arr.shape[1] == count)
    if not (ok and np.isfinite(arr).all()):  # find and name the first bad item (the slow path, errors only)
        bad = _bad_entry(items, count)
        if bad is not None:
            raise DataError(path, f"{field}[{bad[0]}]", bad[1])
        if arr is None and not plain:
            arr = np.array(items, dtype=np.float64)  # every item checked: numbers of one shape
        elif arr is None or arr.size:  # no single bad item, yet not an (N, K, 3) array of finite numbers
            raise DataError(path, field, f"expected (N, {count or 'K'}, 3) finite numbers")
    return arr.reshape(len(items), -1, 3)


def _load_submission(path: Path) -> tuple[bytes, str | None]:
    """The bytes of a pred.json, or of the file the server takes from a zip (its top-level ``pred.json``, else its
    only top-level ``.json``: eval.py's ``_search_pred_file`` on the unpacked folder), and that member's name. A
    file that starts as a zip does, or is named ``.zip``, is read as an archive (a cut one is named as such)."""
    if not (path.suffix.lower() == ".zip" or is_zip(path)):
        return read_bytes(path, "HO-3D submission (pred.json)"), None

    def choose(names: list[str]) -> str:
        top = [n for n in names if "/" not in n and n.endswith(".json")]
        if "pred.json" in top or len(top) == 1:
            return "pred.json" if "pred.json" in top else top[0]
        raise DataError(path, "pred.json", f"the archive has no top-level pred.json and {len(top)} other "
                        "top-level .json files (the server takes pred.json, else the only .json)")

    return read_zip_member(path, choose, "HO-3D submission archive (pred.zip)")[::-1]


def read_ho3d_lists(path) -> tuple[np.ndarray, np.ndarray]:
    """A ``pred.json`` (or a ``pred.zip`` holding one, as the server unpacks it) as stored: xyz (N, 21, 3) and
    verts (N, V, 3), metres, OpenGL frame, HO-3D joint order, in file order.

    Checks what eval.py's ``main`` relies on: the top level is ``[xyz_list, verts_list]`` with one item per sample
    in each, every item a (K, 3) list of finite numbers (V may be 0: no mesh). Raises
    :class:`hoidata.errors.DataError` naming the file (the archive's member) and the malformed part.
    """
    path = Path(path)
    data, member = _load_submission(path)
    value = parse_json(data, path, member)
    if not isinstance(value, list) or len(value) != 2:
        raise DataError(path, member, "expected the JSON list [xyz_list, verts_list]")
    plain = numbers_only(data)
    joints = _as_point_list(value[0], path, join(member, "xyz_list"), NUM_JOINTS, plain)
    verts = _as_point_list(value[1], path, join(member, "verts_list"), None, plain)
    if len(joints) != len(verts):
        raise DataError(path, member, f"xyz_list has {len(joints)} samples but verts_list {len(verts)}")
    return joints, verts


def read_ho3d_pred(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``pred.json`` (or a ``pred.zip`` holding one) back into our convention.

    Returns:
        joints (N, 21, 3) and verts (N, V, 3): metres, OpenCV frame, DexYCB order, in file order.
        Raises :class:`hoidata.errors.DataError` naming the file and the part that is malformed.
    """
    return from_ho3d(*read_ho3d_lists(path))


# ---------------------------------------------------------------- DexYCB HPE result file

def write_dexycb_hpe(path, ids: Sequence[int], joints, decimals: int = 6) -> Path:
    """Write a DexYCB HPE result file: per line the sample index, then 63 coordinates in millimetres.

    Args:
        path: output ``.txt`` path.
        ids: (N,) non-negative integer sample indices of the DexYCB split (the toolkit's image ids).
        joints: (N, 21, 3) metres, camera frame (OpenCV, as DexYCB), DexYCB joint order.
        decimals: digits after the decimal point, in millimetres (6 = 1 nm).
    """
    path = Path(path)
    joints = _points(joints, "joints", NUM_JOINTS)
    ids_arr = np.asarray(ids)
    if ids_arr.shape != (len(joints),) or (len(ids_arr) and not np.issubdtype(ids_arr.dtype, np.integer)):
        raise ValueError(f"ids must be {len(joints)} integers, got shape {ids_arr.shape}, dtype {ids_arr.dtype}")
    if len(np.unique(ids_arr)) != len(ids_arr) or (len(ids_arr) and ids_arr.min() < 0):
        raise ValueError("ids must be unique non-negative integers")
    mm = joints.reshape(len(joints), -1) * 1000.0
    lines = [f"{int(i):d}," + ",".join(f"{v:.{decimals}f}" for v in row) for i, row in zip(ids_arr, mm)]
    write_atomic(path, "".join(line + "\n" for line in lines).encode())
    return path


def hpe_missing_ids(ids, size: int | None, skipped: Sequence[dict]) -> np.ndarray | None:
    """The ids the toolkit's ``hpe_eval.py`` would stop at: samples 0..size-1 of the split that it counts as
    valid (it drops only ``joint_3d`` all -1, which the reader's skips name with
    :data:`~hoidata.datasets.dexycb_frames.TOOLKIT_INVALID`) and that ``ids`` lack. None if ``size`` is unknown.
    """
    from hoidata.datasets.dexycb_frames import TOOLKIT_INVALID

    if size is None:
        return None
    invalid = {int(s["sample_index"]) for s in skipped if s.get("reason") == TOOLKIT_INVALID and "sample_index" in s}
    present = np.zeros(size, bool)
    ids = np.asarray(ids, np.int64)
    present[ids[(ids >= 0) & (ids < size)]] = True
    present[[i for i in invalid if 0 <= i < size]] = True
    return np.flatnonzero(~present)


def read_dexycb_hpe(path, unit: str = "m") -> tuple[np.ndarray, np.ndarray]:
    """Parse a DexYCB HPE result file as ``hpe_eval.py::_load_results`` does, more strictly.

    Returns:
        ids (N,) int64 and joints (N, 21, 3) in file order: metres, or with ``unit="mm"`` the file's millimetre
        values exactly as the toolkit parses them.

    Raises:
        DataError: naming the file and the 1-based line, for a line without exactly 64 comma-separated
            fields (blank lines included, as the toolkit), a non-integer index, a non-numeric or non-finite
            coordinate, or an index seen on an earlier line (the toolkit would silently keep the last one).
    """
    path = Path(path)
    ids, rows, seen = [], [], {}
    lines = read_text(path, "DexYCB HPE result file").split("\n")
    for number, line in enumerate(lines[:-1] if lines[-1] == "" else lines, start=1):  # as a file's lines
        where = f"line {number}"
        elems = line.split(",")
        if len(elems) != HPE_COLUMNS:
            raise DataError(path, where, f"expected {HPE_COLUMNS} comma-separated values, got {len(elems)}")
        try:
            image_id = int(elems[0])
        except ValueError:
            raise DataError(path, where, f"sample index {elems[0].strip()!r} is not an integer") from None
        try:
            coords = np.array([float(v) for v in elems[1:]], dtype=np.float64)
        except ValueError as err:
            raise DataError(path, where, f"non-numeric coordinate: {err}") from None
        problem = not_finite(coords)
        if problem:
            raise DataError(path, where, f"non-finite coordinates: {HPE_COLUMNS - 1} numbers, {problem}")
        if image_id in seen:
            raise DataError(path, where, f"sample index {image_id} already on line {seen[image_id]}")
        seen[image_id] = number
        ids.append(image_id)
        rows.append(coords.reshape(NUM_JOINTS, 3) / (1.0 if unit == "mm" else 1000.0))
    joints = np.stack(rows) if rows else np.zeros((0, NUM_JOINTS, 3))
    return np.asarray(ids, dtype=np.int64), joints
