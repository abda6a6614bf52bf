"""``hoisdf score contact``: plausibility of any method's predicted hand meshes against a split's posed objects.

Inputs (docs/plausibility.md):

- ``--pred``: the HO-3D challenge layout (``pred.json``, or a ``pred.zip`` holding it: the JSON list
  ``[xyz_list, verts_list]``, 778 x 3 vertices per frame, metres, OpenGL camera frame, rows in the order of
  ``--order evaluation.txt``), or an ``.npz`` with ``verts`` (N, 778, 3) metres in the dataset's own (OpenCV)
  camera frame and ``keys`` (N,) the store's record keys (``hoidata`` writes them in every index).
- ``--store``: a ``hoidata`` store of the same split (evaluation stores included): its zarr index holds every
  record's object name and pose (model -> camera) and the object meshes, so no dataset folder is needed.
  Records that are mirrored in the store (DexYCB left hands) have their object mirrored back to the dataset's
  frame, which is the frame of the predictions.
- ``--mano``: folder with MANO_RIGHT.pkl, for the faces and the wrist cap that closes each hand.

Per frame it computes :func:`hoisdf.scoring.plausibility.frame_metrics`, prints the means and writes
every frame's numbers with ``--out FILE.json``. ``--contact-definition gsdf|grasptta`` adds an older paper's
contact, penetration and volume (:mod:`hoisdf.scoring.contact_legacy`) beside the exact ones. It follows
``hoisdf score``'s subcommand interface (``HELP``, ``add_arguments``, ``score``, ``format_result``) and is listed
there as ``contact``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from hoidata.cli_types import non_negative_int, positive_int
from hoidata.errors import DataError
from hoidata.geometry.mirror import mirror_mesh
from hoidata.reading import read_lines, read_npz
from hoidata.shapes import NUMBER_KINDS, not_finite
from hoidata.store import read_index
from hoisdf.scoring.contact_legacy import DEFINITIONS, legacy_many, legacy_summary
from hoisdf.scoring.plausibility import (
    BUDGET,
    CONTACT_THRESHOLD,
    REL_TOLERANCE,
    TOLERANCE,
    frame_metrics_many,
    summarize,
)
from hoisdf.scoring.recon_files import REACH_M
from hoisdf.scoring.submissions import OPENCV_TO_OPENGL, read_ho3d_lists

MANO_VERTS = 778
MAX_CELLS = BUDGET  # per volume and frame, as the evaluator's report


def _finite_hands(verts, path, field: str) -> np.ndarray:
    """(N, 778, 3) float64 or a DataError naming the first bad entry."""
    verts = np.asarray(verts)
    if verts.ndim != 3 or verts.shape[1:] != (MANO_VERTS, 3) or verts.dtype.kind not in NUMBER_KINDS:
        raise DataError(path, field, f"expected (N, {MANO_VERTS}, 3) numbers (MANO vertices), got {verts.shape} "
                                     f"{verts.dtype}")
    bad = np.flatnonzero(~np.isfinite(verts).all((1, 2)))
    if len(bad):
        raise DataError(path, field, f"entry {bad[0]} holds NaN or inf ({verts[bad[0]].size} numbers, "
                                     f"{not_finite(verts[bad[0]])}; {len(bad)} of {len(verts)} entries are so)")
    far = np.flatnonzero(np.abs(verts).max((1, 2)) > REACH_M)
    if len(far):
        raise DataError(path, field, f"entry {far[0]} has a vertex {float(np.abs(verts[far[0]]).max()):.3g} m from "
                                     f"the camera, beyond the {REACH_M:g} m of a physical scene ({len(far)} entries do)")
    return verts.astype(np.float64)


def read_order(path) -> list[str]:
    """``evaluation.txt``: one ``SEQ/id`` per line; duplicates are an error naming the line."""
    path = Path(path)
    ids = read_lines(path, "evaluation list")
    seen: dict[str, int] = {}
    for k, frame in enumerate(ids):
        if frame in seen:
            raise DataError(path, f"line {k + 1}", f"frame {frame!r} is listed twice (first on line {seen[frame] + 1})")
        seen[frame] = k
    return ids


def read_hands(pred, order=None) -> tuple[np.ndarray, list[str], str]:
    """Predicted hands: (vertices (N, 778, 3) metres OpenCV, ids (N,), what the ids are: "key" or "frame_id")."""
    pred = Path(pred)
    if pred.suffix == ".npz":
        data = read_npz(pred, ("verts", "keys"), "predicted hands (.npz)")
        verts, keys = _finite_hands(data["verts"], pred, "verts"), data["keys"]
        if keys.shape != (len(verts),) or keys.dtype.kind not in "UiuS":
            raise DataError(pred, "keys", f"expected ({len(verts)},) record keys (strings), got shape {keys.shape} "
                                          f"{keys.dtype}")
        return verts, [str(k) for k in keys], "key"
    if order is None:
        raise DataError(pred, None, "a pred.json has no frame ids: give its evaluation list with --order")
    _, verts = read_ho3d_lists(pred)  # names the entry of a malformed or non-finite item itself
    verts = _finite_hands(verts, pred, "verts_list")
    ids = read_order(order)
    if len(ids) != len(verts):
        raise DataError(pred, "verts_list", f"{len(verts)} entries, but {order} lists {len(ids)} frames")
    # HO-3D's SEQ/id is the store's frame id SEQ_id
    return verts @ OPENCV_TO_OPENGL.T, [i.replace("/", "_") for i in ids], "frame_id"


def match_records(index, ids: list[str], by: str, pred) -> np.ndarray:
    """Row of each id among the store's records (by record key or HO-3D frame id); one line per problem."""
    labels = index.labels
    column = labels["key"] if by == "key" else np.where(labels["dataset"] == "ho3d", labels["frame_id"], "")
    row: dict[str, int] = {}
    for r, value in enumerate(column.tolist()):
        row.setdefault(value, r)
    out = np.empty(len(ids), dtype=np.int64)
    seen: dict[str, int] = {}
    for k, value in enumerate(ids):
        if value in seen:
            raise DataError(pred, f"entry {k}", f"{by} {value!r} appears twice (first as entry {seen[value]})")
        seen[value] = k
        if value not in row:
            raise DataError(pred, f"entry {k}", f"no record with {by} {value!r} in the store {index.path.parent}")
        out[k] = row[value]
    return out


def posed_objects(index, rows: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each record's object mesh posed in the dataset's camera frame (metres)."""
    labels, out = index.labels, []
    for r in rows:
        name, pose = str(labels["object_name"][r]), np.asarray(labels["object_pose"][r], dtype=np.float64)
        if name not in index.objects:
            raise DataError(index.path, "objects", f"no mesh for {name!r} (record {labels['key'][r]})")
        if not np.isfinite(pose).all():
            raise DataError(index.path, "object_pose", f"record {labels['key'][r]} has no object pose")
        v, f = index.objects[name]
        mirrored = bool(labels["mirrored"][r]) if "mirrored" in labels else False
        if mirrored:  # the store poses the mirrored model in the mirrored frame
            v, f = mirror_mesh(np.asarray(v), np.asarray(f))
        posed = np.asarray(v, dtype=np.float64) @ pose[:3, :3].T + pose[:3, 3]
        if not np.abs(posed).max() <= REACH_M:
            raise DataError(index.path, "object_pose", f"record {labels['key'][r]} poses its object beyond the "
                                                       f"{REACH_M:g} m of a physical scene")
        out.append(mirror_mesh(posed, np.asarray(f)) if mirrored else (posed, np.asarray(f, dtype=np.int64)))
    return out


def score_contact(pred, store, mano_dir, order=None, tolerance: float = TOLERANCE, rel_tolerance: float = REL_TOLERANCE,
                  threshold: float = CONTACT_THRESHOLD, limit: int | None = None, workers: int = 1,
                  max_cells: int = MAX_CELLS, definition: str = "exact") -> dict:
    """Per-frame and mean plausibility of the predicted hands (see the module docstring).

    Args:
        pred: pred.json / pred.zip / .npz.
        store: store folder.
        mano_dir: MANO folder.
        order: evaluation.txt (pred.json only).
        tolerance: volume error bound, m^3.
        rel_tolerance: or this fraction of the volume.
        threshold: contact distance, metres.
        limit: only the first ``limit`` frames (a subset, said so in the result).
        workers: processes (0 or 1: this one).
        max_cells: evaluation budget per volume and frame.
        definition: also an older paper's contact, depth and volume, beside the exact ones: "gsdf" or
            "grasptta" (:mod:`hoisdf.scoring.contact_legacy`); "exact": only the exact ones.

    Returns:
        {"mean": ..., "frames": [{"id": ..., metrics}], "subset": bool, "settings": {...}}, and with an older
        definition "legacy": {"definition", "mean"}; each frame then also holds its numbers as ``<definition>_*``.
    """
    from hoidata.hand import load_mano
    from hoidata.hand.topology import close_vertices

    verts, ids, by = read_hands(pred, order)
    index = read_index(store)
    rows = match_records(index, ids, by, pred)
    total = len(ids)
    if limit is not None:
        verts, ids, rows = verts[:limit], ids[:limit], rows[:limit]
    mano = load_mano(mano_dir, side="right")
    closed = close_vertices(np.asarray(verts, dtype=np.float64), np.asarray(mano.wrist_loop))
    faces = np.asarray(mano.closed_faces, dtype=np.int64)
    samples = [(closed[k], faces, *obj) for k, obj in enumerate(posed_objects(index, rows))]
    frames = frame_metrics_many(samples, workers, tolerance=tolerance, threshold=threshold, n_points=MANO_VERTS,
                                rel_tolerance=rel_tolerance, max_cells=max_cells)
    out = {"mean": summarize(frames, tolerance), "subset": len(frames) < total, "frames_total": total,
           "frames": [{"id": i, **f} for i, f in zip(ids, frames)],
           "settings": {"pred": str(pred), "store": str(store), "tolerance_m3": tolerance,
                        "rel_tolerance": rel_tolerance,
                        "contact_threshold_m": threshold, "max_cells": max_cells, "contact_definition": definition}}
    if definition != "exact":
        legacy = legacy_many(definition, samples, workers, MANO_VERTS)
        for frame, extra in zip(out["frames"], legacy):
            frame.update({f"{definition}_{k}": v for k, v in extra.items()})
        out["legacy"] = {"definition": definition, "mean": legacy_summary(legacy)}
    return out


HELP = "penetration depth, intersection volume, contact ratio, IVU and self-penetration of predicted hand meshes"


def format_result(result: dict) -> str:
    """The printed table of :func:`score`'s result."""
    m, st = result["mean"], result["settings"]
    rows = [("frames", f"{m['num_samples']}" + (f" of {result['frames_total']} (a subset)" if result["subset"] else "")),
            ("penetration depth (mm)", f"{m['penetration_depth_mm']:.3f}"),
            ("intersection volume (cm^3)", f"{m['intersection_volume_cm3']:.4f}  (rigorous bound "
                                           f"{m['intersection_error_cm3']:.4f} on average; asked: max("
                                           f"{st['tolerance_m3'] * 1e6:g} cm^3, {st['rel_tolerance']:g} x volume))"),
            ("contact ratio", f"{m['contact_ratio']:.4f}"),
            ("contact area (cm^2)", f"{m['contact_area_cm2']:.3f}"),
            ("IVU (cm)", f"{m['ivu_cm']:.4f}  ({m['ivu_frames']} frames in contact)"),
            ("self-penetration (cm^3)", f"{m['self_penetration_cm3']:.4f}")]
    if "legacy" in result:
        d, lm = result["legacy"]["definition"], result["legacy"]["mean"]
        rows += [(f"{d} definition", "(its own script's numbers on these meshes; exact ones above)"),
                 (f"  contact ratio ({d})", f"{lm['contact_ratio']:.4f}  (exact {m['contact_ratio']:.4f})"),
                 (f"  penetration (mm, {d})",
                  f"{lm['penetration_depth_mm']:.3f}  (exact {m['penetration_depth_mm']:.3f})"),
                 (f"  volume (cm^3, {d})", f"{lm['intersection_volume_cm3']:.4f}  "
                                           f"(exact {m['intersection_volume_cm3']:.4f})")]
    if m["frames_over_tolerance"]:
        rows.append(("over the tolerance", f"{m['frames_over_tolerance']} frames (budget --max-cells; their bounds "
                                           "are in --out)"))
    return "\n".join(f"{k:28s} {v}" for k, v in rows)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """This subcommand's options (``hoisdf score`` adds ``--out`` and ``--debug``)."""
    p.add_argument("--pred", required=True, type=Path, help="pred.json / pred.zip (HO-3D layout) or hands .npz")
    p.add_argument("--store", required=True, help="hoidata store of the split (object poses and meshes)")
    p.add_argument("--mano", required=True, type=Path, help="folder with MANO_RIGHT.pkl")
    p.add_argument("--order", type=Path, default=None, help="evaluation.txt: the frame of each pred.json row")
    p.add_argument("--tolerance", type=float, default=TOLERANCE * 1e6, metavar="CM3",
                   help=f"error bound of each volume, cm^3 (default {TOLERANCE * 1e6:g})")
    p.add_argument("--rel-tolerance", type=float, default=REL_TOLERANCE, metavar="F",
                   help=f"or this fraction of the volume, whichever is larger (default {REL_TOLERANCE:g}; 0: off)")
    p.add_argument("--threshold", type=float, default=CONTACT_THRESHOLD * 1e3, metavar="MM",
                   help=f"contact distance, mm (default {CONTACT_THRESHOLD * 1e3:g})")
    p.add_argument("--max-cells", type=positive_int, default=MAX_CELLS, metavar="N",
                   help=f"evaluation budget per volume and frame (default {MAX_CELLS:,}); a frame over it keeps a "
                        "wider, still rigorous bound")
    p.add_argument("--limit", type=positive_int, default=None, metavar="N", help="only the first N frames")
    p.add_argument("--workers", type=non_negative_int, default=1, help="processes (default 1)")
    p.add_argument("--contact-definition", choices=DEFINITIONS, default="exact",
                   help="also an older paper's contact, penetration and volume beside the exact ones: gsdf (gSDF's "
                        "tools/eval_contact.py: contact only when a vertex is inside, 5 mm grid volume) or grasptta "
                        "(GraspTTA / obman_train: surface voxels, contact within 5 mm); default exact: only the exact")


def score(args) -> dict:
    """The subcommand's numbers from parsed options (:func:`score_contact`, options in cm^3 and mm)."""
    if not args.tolerance > 0 or args.rel_tolerance < 0 or not args.threshold >= 0:
        raise DataError(None, None, "--tolerance must be positive, --rel-tolerance and --threshold non-negative")
    result = score_contact(args.pred, args.store, args.mano, args.order, args.tolerance * 1e-6, args.rel_tolerance,
                           args.threshold * 1e-3, args.limit, args.workers, args.max_cells, args.contact_definition)
    note = f"a subset: {len(result['frames'])} of {result['frames_total']} frames" if result["subset"] else ""
    return {**result, "samples": len(result["frames"]), **({"note": note} if note else {})}
