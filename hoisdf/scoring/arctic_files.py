"""ARCTIC leaderboard submissions and ground-truth folders, read and checked (docs/scoring.md, "ARCTIC").

A submission (a folder or its ``.zip``) holds ``[<task>_<setup>_test/]eval/<sXX>_<sequence>_<view>/preds/<key>.pt``
(:data:`PRED_KEYS`) and ``meta_info/meta_info.imgname.pt``; a ground-truth folder holds
``<sXX>_<sequence>_<view>/{targets,meta_info}/<key>.pt`` as ARCTIC's extraction writes them (``eval_pose`` /
``eval_field`` on a split with labels, or the server's own copy). :func:`check_submission` lists every problem as
one line naming the file and the key; what the server tolerates (float16, predictions longer than the ground
truth, a missing or odd ``meta_info.imgname.pt``, which it never reads) is a note, not a problem.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.reading import open_zip, read_bytes, zip_names, zip_read
from hoisdf.scoring.torch_files import TensorArray, describe, read_pt

HAND = 778
# per-frame shape of every file the server reads; None: the object's vertex count or more (the field task)
PRED_KEYS = {"pose": {**{f"pred.mano.{k}.{s}": shape for s in ("r", "l")
                         for k, shape in (("cam_t", (3,)), ("beta", (10,)), ("pose", (16, 3, 3)))},
                      "pred.object.rot": (3,), "pred.object.cam_t": (3,), "pred.object.radian": ()},
             "field": {"pred.dist.ro": (HAND,), "pred.dist.lo": (HAND,), "pred.dist.or": None, "pred.dist.ol": None}}
TARGET_KEYS = {"mano.pose.r": (48,), "mano.pose.l": (48,), "mano.beta.r": (10,), "mano.beta.l": (10,),
               "mano.cam_t.r": (3,), "mano.cam_t.l": (3,), "object.rot": (3,), "object.cam_t": (3,),
               "object.radian": (), "is_valid": (), "left_valid": (), "right_valid": ()}
FLOATS = ("float16", "float32")  # the server converts float16 to float32
# float64 files the server also takes (its arithmetic promotes them); float64 MANO poses and betas and a float64
# articulation stop it (its float32 MANO layer and object tensors refuse them: measured with ARCTIC's code)
FLOAT64_TOLERATED = ("pred.mano.cam_t.r", "pred.mano.cam_t.l", "pred.object.rot", "pred.object.cam_t")
FOLDER = re.compile(r"^(s\d\d)_(.+)_(\d)$")


class Source:
    """A folder or a zip, read by relative path."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if self.path.is_dir():
            self.names = sorted(str(p.relative_to(self.path)) for p in self.path.rglob("*") if p.is_file())
            self.zip = None
        elif self.path.is_file():
            self.zip = open_zip(self.path, "submission (a folder or a zip)")  # cut or damaged: one line
            self.names = sorted(set(zip_names(self.zip)))
        else:
            raise DataError(self.path, None, "not found")

    def where(self, name: str) -> str:
        return f"{self.path}:{name}" if self.zip else str(self.path / name)

    def read(self, name: str):
        data = zip_read(self.zip, name, self.path) if self.zip else read_bytes(self.path / name, "submission file")
        return read_pt(self.where(name), data)


def eval_root(source: Source) -> str:
    """The ``eval/`` folder's prefix inside a submission (``eval/`` or ``<task>/eval/``)."""
    roots = sorted({n[: n.index("eval/") + 5] for n in source.names if re.match(r"^([^/]+/)?eval/[^/]+/", n)})
    if len(roots) != 1:
        raise DataError(source.path, "eval", "no eval/ folder of <sXX>_<sequence>_<view> folders" if not roots else
                        f"{len(roots)} eval/ folders ({', '.join(roots)}); the server reads one")
    return roots[0]


def folders(source: Source, prefix: str = "") -> list[str]:
    rest = [n[len(prefix):] for n in source.names if n.startswith(prefix)]
    return sorted({r.split("/")[0] for r in rest if "/" in r})


def _frames(value, where: str, key: str, per_frame, floats: tuple, vertices: int | None) -> tuple[np.ndarray, list]:
    """(array, problems) of one tensor file against its per-frame shape."""
    if not isinstance(value, TensorArray):
        return None, [str(DataError(where, key, f"holds {describe(value)}; a torch tensor is needed"))]
    problems = []
    if value.torch_dtype not in floats:
        problems.append(str(DataError(where, key, f"{value.torch_dtype}: save {' or '.join(floats)}")))
    arr = np.asarray(value, np.float64)
    want = per_frame
    if per_frame is None:
        ok = arr.ndim == 2 and (vertices is None or arr.shape[1] >= vertices)
        want = f"(frames, {vertices or 'V'} or more)"
    elif per_frame == ():
        ok = arr.ndim == 1 or (arr.ndim == 2 and arr.shape[1] == 1)
        want = "(frames,) or (frames, 1)"
    else:
        ok = arr.ndim == 1 + len(per_frame) and arr.shape[1:] == per_frame
        want = f"(frames, {', '.join(map(str, per_frame))})"
    if not ok:
        return None, problems + [str(DataError(where, key, f"shape {arr.shape}, expected {want}"))]
    bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
    if bad.any():
        problems.append(str(DataError(where, key, f"NaN or Inf in {bad.sum()} frame(s), first frame {np.argmax(bad)}")))
    return arr.reshape(len(arr), -1)[:, 0] if per_frame == () else arr, problems


def read_reference(gt: Path) -> dict[str, int]:
    """The ground truth's folders and their frame counts (``meta_info/meta_info.imgname.pt``)."""
    source = Source(gt)
    out = {}
    for name in folders(source):
        if not FOLDER.match(name):
            continue
        rel = f"{name}/meta_info/meta_info.imgname.pt"
        if rel not in source.names:
            raise DataError(source.where(rel), None, "missing: a ground-truth folder needs its image names")
        names = source.read(rel)
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise DataError(source.where(rel), None, f"holds {describe(names)}; a list of image paths is needed")
        out[name] = len(names)
    if not out:
        raise DataError(gt, None, "no <sXX>_<sequence>_<view> folders")
    return out


def check_submission(path: Path, task: str, setup: str, reference: dict[str, int] | None = None,
                     vertices: dict[str, int] | None = None) -> tuple[list[str], list[str], dict]:
    """(problems, notes, predictions) of a submission: every file, key, dtype, shape, frame count against the
    leaderboard's format and, with ``reference`` (folder -> frames), against the ground truth's folders;
    ``vertices`` (object name -> vertex count) checks the field task's object widths. ``predictions``:
    folder -> key -> float64 array (frames trimmed to the reference) for the folders without problems."""
    source = Source(path)
    prefix = eval_root(source)
    views = {"p1": set("12345678"), "p2": {"0"}}[setup]
    problems, notes, preds = [], [], {}
    present = folders(source, prefix)
    if reference is not None:
        problems += [str(DataError(source.where(prefix + f), None, "missing: the ground truth has this sequence and "
                                   "view and the server stops on a missing file"))
                     for f in sorted(set(reference) - set(present))]
    for name in present:
        found = FOLDER.match(name)
        here = source.where(prefix + name)
        if not found:
            notes.append(f"{here}: not a <sXX>_<sequence>_<view> folder; the server ignores it")
            continue
        if found.group(3) not in views:
            notes.append(f"{here}: view {found.group(3)} is not a view of {setup}; the server ignores it")
            continue
        if reference is not None and name not in reference:
            notes.append(f"{here}: not in the ground truth; the server ignores it")
            continue
        obj_vertices = (vertices or {}).get(found.group(2).split("_")[0])
        arrays, bad = {}, []
        for key, per_frame in PRED_KEYS[task].items():
            rel = f"{prefix}{name}/preds/{key}.pt"
            if rel not in source.names:
                bad.append(str(DataError(source.where(rel), key, "missing (the server stops on a missing file)")))
                continue
            try:
                value = source.read(rel)
            except DataError as e:
                bad.append(str(DataError(source.where(rel), key, e.problem)))
                continue
            floats = FLOATS + ("float64",) if task == "field" or key in FLOAT64_TOLERATED else FLOATS
            arr, issues = _frames(value, source.where(rel), key, per_frame, floats, obj_vertices)
            if getattr(value, "torch_dtype", "") == "float64" and "float64" in floats and task == "pose":
                notes.append(f"{source.where(rel)}: float64; the server promotes it (its own files are float16)")
            bad += issues
            if arr is not None:
                arrays[key] = arr
        counts = {k: len(v) for k, v in arrays.items()}
        want = reference.get(name) if reference is not None else None
        against = "the ground truth"
        imgname = f"{prefix}{name}/meta_info/meta_info.imgname.pt"
        if imgname not in source.names:
            notes.append(f"{source.where(imgname)}: missing; the server takes image names from its ground truth")
        else:
            names = _imgnames(source, imgname, found, notes)
            if want is None and names is not None:
                want, against = len(names), "its meta_info.imgname.pt"
        longer = []
        for key, n in counts.items():
            where = source.where(f"{prefix}{name}/preds/{key}.pt")
            if want is not None and n < want:
                bad.append(str(DataError(where, key, f"{n} frames, {against} has {want}")))
            elif want is not None and n > want:
                longer.append(f"{key} {n}")
        if longer:
            notes.append(f"{here}: longer than the {want} frames of {against} ({', '.join(longer)}); the server "
                         "trims them to its ground truth")
        if want is None and len(set(counts.values())) > 1:
            lengths = sorted(set(counts.values()))
            bad.append(str(DataError(source.where(prefix + name), None, f"files of different lengths {lengths}")))
        if task == "pose":
            for key in ("pred.mano.pose.r", "pred.mano.pose.l"):
                gram = np.einsum("...ji,...jk->...ik", arrays[key], arrays[key]) if key in arrays else np.eye(3)
                if np.abs(gram - np.eye(3)).max() > 0.1:
                    where = source.where(f"{prefix}{name}/preds/{key}.pt")
                    notes.append(f"{where}: not rotation matrices (|R^T R - I| > 0.1); the server converts them to "
                                 "axis-angle as they are")
        problems += bad
        if not bad:
            n = want if want is not None else min(counts.values())
            preds[name] = {k: v[:n] for k, v in arrays.items()}
    return problems, notes, preds


def _imgnames(source: Source, rel: str, found, notes: list) -> list | None:
    try:
        names = source.read(rel)
    except DataError as e:
        notes.append(f"{e} (the server never reads it)")
        return None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        notes.append(f"{source.where(rel)}: holds {describe(names)}, not a list of image paths (the server never "
                     "reads it)")
        return None
    sid, seq, view = found.groups()
    odd = [n for n in names if n.replace("\\", "/").split("/")[-4:-1] != [sid, seq, view]]
    if odd:
        notes.append(f"{source.where(rel)}: {len(odd)} image path(s) not under {sid}/{seq}/{view}/, e.g. {odd[0]!r} "
                     "(the server never reads them)")
    return names


def read_ground_truth(source: Source, name: str) -> dict:
    """One ground-truth folder's targets (float64; the flags 0/1) and its object name and frame count."""
    out = {}
    for key, per_frame in TARGET_KEYS.items():
        rel = f"{name}/targets/targets.{key}.pt"
        if rel not in source.names:
            raise DataError(source.where(rel), key, "missing from the ground truth")
        arr, issues = _frames(source.read(rel), source.where(rel), key, per_frame,
                              ("float16", "float32", "float64"), None)
        if issues:
            raise DataError(source.where(rel), key, issues[0].split(": ", 2)[-1])
        out[key] = arr
    n = {len(v) for v in out.values()}
    if len(n) != 1:
        raise DataError(source.where(name), "targets", f"files of different lengths {sorted(n)}")
    names = source.read(f"{name}/meta_info/meta_info.query_names.pt") if \
        f"{name}/meta_info/meta_info.query_names.pt" in source.names else None
    obj = names[0] if isinstance(names, list) and names and isinstance(names[0], str) else \
        FOLDER.match(name).group(2).split("_")[0]
    return {"targets": out, "object": obj, "frames": n.pop()}
