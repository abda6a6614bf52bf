"""Ground truth of ``hoisdf score recon --gt-store STORE``: each record's hand and object posed from a ``hoidata``
store, written as the named mesh files :mod:`hoisdf.scoring.recon_files` reads (``<id>_hand.obj``,
``<id>_obj.obj``, metres, camera frame; vertices written with 17 significant digits, so they read back exactly).

- frame ids: the records' ``frame_id`` (an HO-3D ``SEQ/id`` with ``/`` as ``_``); predictions are named after them;
- hand: the closed MANO mesh (778 vertices and the wrist cap's centre, ``closed_faces``) of the record's
  ``mano_pose`` / ``mano_betas`` / ``mano_transl`` with the right MANO model of ``--mano``, as ``hoidata export
  --format gsdf`` writes gSDF's ``mesh_hand``. Mirrored records (left hands seen as right ones) are left out of the
  split and counted: gSDF scores right hands only;
- object: the store's mesh of ``object_name`` posed by ``object_pose``, in the dataset's frame
  (:func:`hoisdf.scoring.score_contact.posed_objects`).

A store without hand labels (an evaluation store) can give the objects only (``--parts obj``); asking for hands is
one error naming the store and the field. MANO is the only torch user here (imported when hands are posed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.store import read_index
from hoisdf.scoring.score_contact import posed_objects

BATCH = 512  # hands posed per MANO call


def write_obj_exact(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A Wavefront OBJ whose float64 vertices read back bit for bit (``%.17g``); faces 1-based."""
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in np.asarray(vertices, dtype=np.float64)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces, dtype=np.int64)]
    path.write_text("\n".join(lines) + "\n")


def frame_ids(index) -> list[str]:
    return [str(f).replace("/", "_") for f in index.labels["frame_id"].tolist()]


def posed_hands(index, rows: np.ndarray, mano_dir, store) -> tuple[np.ndarray, np.ndarray]:
    """Closed hands (len(rows), 779, 3) metres of the records ``rows``, and the closed faces."""
    import torch

    labels = index.labels
    for name in ("mano_pose", "mano_betas", "mano_transl"):
        values = labels.get(name)
        if values is None:
            raise DataError(store, name, "the store has no hand labels (an evaluation store?): score --parts obj")
        bad = np.flatnonzero(~np.isfinite(np.asarray(values[rows], dtype=np.float64)).all(1))
        if len(bad):
            raise DataError(store, name, f"record {labels['key'][rows[bad[0]]]} has no hand label ({len(bad)} "
                                         "records lack one; an evaluation store?): score --parts obj")
    mano = right_mano(mano_dir)
    pose, betas, transl = (torch.as_tensor(np.asarray(labels[k][rows], dtype=np.float64))
                           for k in ("mano_pose", "mano_betas", "mano_transl"))
    with torch.no_grad():
        verts = mano.close(mano(pose, betas, transl).vertices).numpy()
    return verts, np.asarray(mano.closed_faces, dtype=np.int64)


_MANO: dict = {}


def right_mano(mano_dir):
    """The right MANO layer (float64) of ``mano_dir``, loaded once per process."""
    import torch

    from hoidata.hand import load_mano

    key = str(mano_dir)
    if key not in _MANO:
        _MANO[key] = load_mano(mano_dir, side="right", dtype=torch.float64)
    return _MANO[key]


def write_store_gt(store, folder: Path, parts, mano_dir=None) -> dict:
    """Write the ground truth of every right-hand record of ``store`` into ``folder``; returns what was left out:
    {"records": n, "mirrored_left_out": m}."""
    from tqdm import tqdm

    index = read_index(store)
    labels = index.labels
    mirrored = np.asarray(labels["mirrored"], bool) if "mirrored" in labels else np.zeros(len(labels["key"]), bool)
    rows = np.flatnonzero(~mirrored)
    if not len(rows):
        raise DataError(store, "mirrored", "no right-hand record (every record is a mirrored left hand)")
    ids = frame_ids(index)
    seen: dict[str, int] = {}
    for r in rows:
        if ids[r] in seen:
            raise DataError(store, "frame_id", f"frame {ids[r]!r} appears twice (records {labels['key'][seen[ids[r]]]}"
                                               f" and {labels['key'][r]})")
        seen[ids[r]] = r
    if "hand" in parts and mano_dir is None:
        raise DataError(None, "--mano", "posing the ground-truth hands of --gt-store needs the MANO folder")
    with tqdm(total=len(rows), desc="ground truth", unit="frame", disable=None, leave=False) as bar:
        for s in range(0, len(rows), BATCH):  # a batch at a time: a split's meshes need not fit in memory
            chunk = rows[s:s + BATCH]
            if "hand" in parts:
                hands, faces = posed_hands(index, chunk, mano_dir, store)
                for k, r in enumerate(chunk):
                    write_obj_exact(folder / f"{ids[r]}_hand.obj", hands[k], faces)
            if "obj" in parts:
                for r, (v, f) in zip(chunk, posed_objects(index, chunk)):
                    write_obj_exact(folder / f"{ids[r]}_obj.obj", v, f)
            bar.update(len(chunk))
    return {"records": len(rows), "mirrored_left_out": int(mirrored.sum())}
