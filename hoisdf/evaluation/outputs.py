"""What ``python -m hoisdf.evaluate`` writes: the printed table, metrics.json helpers, per_object.csv,
the official export files and the result pictures."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from hoidata.atomic import write_atomic
from hoidata.errors import DataError
from hoidata.geometry.mirror import mirror_points
from hoidata.store import read_index
from hoisdf.evaluation.inference import Collected
from hoisdf.scoring.ho3d_list import (
    check_against_ground_truth,
    check_against_store,
    ho3d_entry,
    read_evaluation_list,
)
from hoisdf.scoring.official import HO3D_EVALUATION_SIZES, dexycb_hpe_scores, toolkit_gt_mm
from hoisdf.scoring.submissions import hpe_missing_ids, read_dexycb_hpe, write_dexycb_hpe, write_ho3d_pred

TABLE = (("MJE", "rr_mje"), ("PA-MJE", "pa_mje"), ("OCE", "oce"), ("MCE", "mce"), ("ADD-S", "add_s"))
MESH_TABLE = (("MME", "mme"), ("PA-MME", "pa_mme"), ("F@5", "f5"), ("F@15", "f15"))
HO3D_TABLE = (("ST-MJE", "st_mje"), ("OME", "ome"))  # HO-3D tables: hand metrics from the server, object OME
# every file an evaluation writes into its output folder (glob patterns; clear_results removes them before a run)
RESULT_FILES = ("metrics.json", "per_object.csv", "scores.txt", "pred.json", "pred.zip", "pred_*.json", "pred_*.zip",
                "dexycb_hpe_*.txt", "vis/*.png")


def format_table(rows: dict[str, dict[str, float]], mesh: bool, ho3d: bool = False) -> str:
    """The paper's layout: one line per method, lengths in mm (F-scores as ratios); mesh and HO-3D columns
    (ST-MJE, OME) when asked for."""
    cols = TABLE + (MESH_TABLE if mesh else ()) + (HO3D_TABLE if ho3d else ())
    width = max(len(name) for name in rows) + 2
    lines = [" " * width + "".join(f"{title:>9}" for title, _ in cols)]
    for name, values in rows.items():
        cells = (f"{values.get(key, float('nan')):9.{3 if key in ('f5', 'f15') else 2}f}" for _, key in cols)
        lines.append(f"{name:<{width}}" + "".join(cells))
    return "\n".join(lines)


def write_per_object(path: Path, summary: dict, counts: dict[str, int]) -> None:
    """per_object.csv: one row per object and one for all, the sample count then every metric (written atomically)."""
    names = sorted(k for k in summary if k != "all")
    metric_names = list(summary["all"])
    with io.StringIO(newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["object", "samples", *metric_names])
        for name in [*names, "all"]:
            writer.writerow([name, counts.get(name, sum(counts.values())),
                             *(f"{summary[name][m]:.6g}" for m in metric_names)])
        write_atomic(path, f.getvalue().encode())


def export(col: Collected, stores: list, out_dir: Path, ho3d_order=None,
           indexes: dict | None = None) -> tuple[dict[str, str], dict]:
    """The official result files: per DexYCB split of each store an HPE file, and with ``ho3d_order`` (the list's
    entries, or its path) the pred.json/pred.zip of HO-3D stores. Returns (files written, ``dexycb_hpe`` scores per
    HPE file). A requested pred.json that cannot be written is a DataError.

    Mirrored records (DexYCB left hands seen as right ones) are mirrored back, so the files hold the datasets'
    own camera frames.
    """
    joints, gt = col.get("joints"), col.get("gt_joints")
    mirrored = col.get("mirrored")
    if mirrored is not None:
        flip = mirrored.astype(bool)[:, None, None]
        joints, gt = np.where(flip, mirror_points(joints), joints), np.where(flip, mirror_points(gt), gt)
    written, scores = {}, {}
    order = read_evaluation_list(ho3d_order) if isinstance(ho3d_order, (str, Path)) else ho3d_order
    for s, path in enumerate(stores):
        sel = np.flatnonzero(np.asarray(col.store) == s)
        index = (indexes or {}).get(path) or read_index(path)
        suffix = "" if len(stores) == 1 else f"_{path.name}"  # a folder's or a store URL's last part
        for name, file, score in _export_hpe(index, np.asarray(col.rows)[sel], joints[sel], gt[sel], out_dir, suffix):
            written[f"hpe:{path}:{name}"], scores[Path(file).name] = file, score
        if order is not None:
            written.update(_export_ho3d(col, sel, joints, path, out_dir, order, suffix))
    if order is not None and not any(key.startswith("ho3d") for key in written):
        raise DataError(ho3d_order if isinstance(ho3d_order, (str, Path)) else None, None,
                        "--ho3d-order: no HO-3D store among the evaluated ones; no pred.json written")
    return written, scores


def _export_hpe(index, rows: np.ndarray, joints: np.ndarray, gt: np.ndarray, out_dir: Path, suffix: str):
    """Yield (toolkit split name, file, toolkit scores) for each DexYCB split among ``rows`` of a store.

    The ids are the records' ``sample_index``. A file holding every sample the toolkit counts as valid is
    ``dexycb_hpe_<split>.txt``; otherwise (a setting's subset, ``--limit``, frames the build skipped) it is
    ``dexycb_hpe_<split>_subset.txt`` and one line says so: the toolkit's hpe_eval.py stops at the first missing id.
    """
    lab = index.labels
    split_of = np.where(lab["dataset"][rows] == "dexycb", lab["split"][rows], "")
    for split in sorted(set(split_of.tolist()) - {""}):
        pick = np.flatnonzero(split_of == split)
        ids = lab["sample_index"][rows[pick]].astype(np.int64)
        info = index.provenance.get("toolkit_splits", {}).get(split) or {}
        name = info.get("name") or f"unknown_{split}"
        missing = hpe_missing_ids(ids, info.get("size"), index.skipped)
        known = ids >= 0
        complete = missing is not None and len(missing) == 0 and known.all()
        file = out_dir / f"dexycb_hpe_{name}{suffix}{'' if complete else '_subset'}.txt"
        write_dexycb_hpe(file, ids[known], joints[pick][known])
        _, pred_mm = read_dexycb_hpe(file, unit="mm")  # the numbers as the toolkit reads them
        score = {"split": name, "complete": bool(complete), "samples": int(known.sum()),
                 **dexycb_hpe_scores(pred_mm, toolkit_gt_mm(gt[pick][known]))}
        if not complete:
            why = (f"{len(missing)} of the split's {info['size']} samples are neither in it nor marked invalid "
                   "(joint_3d -1)" if missing is not None else "the store does not record the toolkit's split size")
            score["missing"] = None if missing is None else len(missing)
            print(f"{file.name}: a subset of {name} ({why}; the toolkit's hpe_eval.py refuses such a file, "
                  f"metrics.json['dexycb_hpe'] has the toolkit's numbers for it)")
        yield name, str(file), score


def _export_ho3d(col: Collected, sel: np.ndarray, joints: np.ndarray, path, out_dir: Path, order: list[str],
                 suffix: str) -> dict[str, str]:
    """pred.json and pred.zip of one HO-3D store in ``order`` (``evaluation.txt``'s entries); a store that is not
    an HO-3D one is noted and skipped, a list its predictions cannot fill is a DataError."""
    if not col.get("ho3d").astype(bool)[sel].all():
        print(f"--ho3d-order: {path} is not an HO-3D store; no pred.json written for it")
        return {}
    verts = col.get("verts")
    ids = [ho3d_entry(col.frame_ids[i]) for i in sel]
    v = verts[sel] if verts is not None else np.zeros((len(sel), 0, 3))
    written = {}
    for ext in (".json", ".zip"):
        file = out_dir / f"pred{suffix}{ext}"
        try:
            written[f"ho3d{ext}:{path}"] = str(write_ho3d_pred(file, ids, joints[sel], v, order=order))
        except ValueError as err:
            raise DataError(file, None, f"not written: {err}") from None
    fits = [v for v, n in HO3D_EVALUATION_SIZES.items() if n == len(order)]
    print(f"pred.json: {len(order)} samples in the order of --ho3d-order: " + (
        f"the size of the HO-3D {fits[0]} challenge's evaluation split" if fits else
        "not the size of a challenge split (v2 11,524, v3 20,137), so the server would refuse it"))
    return written


def checked_ho3d_order(path, gt_folder, indexes: dict, limit: int | None = None) -> list[str]:
    """``--ho3d-order``'s list, checked before any work (:mod:`hoisdf.scoring.ho3d_list`): well-formed, exactly
    the frames of every HO-3D store among ``indexes`` (store -> StoreIndex, in evaluation order), not cut by
    ``limit``, and with ``gt_folder`` the ground truth's own list in its order. Returns its entries."""
    order = read_evaluation_list(path)
    done, ho3d = 0, []
    for store, index in indexes.items():
        done += len(index.keys)
        if len(index.keys) and (np.asarray(index.labels["dataset"]) == "ho3d").all():
            ho3d.append(store)
            if limit is not None and limit < done:
                raise DataError(path, None, f"--limit {limit} leaves out frames of {store}; a submission needs a "
                                            "prediction for every line: leave --limit out")
            check_against_store(order, path, store, index.labels["frame_id"], index.skipped)
    if not ho3d:
        raise DataError(path, None, f"--ho3d-order: none of the stores is an HO-3D store "
                                    f"({', '.join(str(s) for s in indexes)}); no pred.json can be written")
    if gt_folder is not None:
        check_against_ground_truth(order, path, gt_folder)
    return order


def clear_results(out_dir: Path) -> None:
    """Remove the result files an earlier evaluation left in ``out_dir`` (:data:`RESULT_FILES`, and the temporary
    files of their atomic writes), so that none of them can pass for a result of the run that follows."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return
    for pattern in RESULT_FILES:
        folder, _, name = pattern.rpartition("/")
        for found in [*(out_dir / folder).glob(name), *(out_dir / folder).glob(f".{name}.*.tmp")]:
            if found.is_file() or found.is_symlink():
                found.unlink()


def score_ho3d_files(files: dict[str, str], gt_folder, out_dir: Path) -> dict:
    """Score the pred.json among ``files`` (export's result) against the challenge's ground truth in ``gt_folder``
    and write ``out_dir/scores.txt`` as the server's eval.py does; returns the scores plus the pred file's name."""
    from hoisdf.scoring.official import score_ho3d_submission, write_scores_txt

    preds = [path for key, path in files.items() if key.startswith("ho3d.json:")]
    if len(preds) != 1:
        raise DataError(gt_folder, None, f"--ho3d-gt scores one HO-3D store's pred.json; {len(preds)} were written")
    scores = score_ho3d_submission(preds[0], gt_folder)
    write_scores_txt(out_dir / "scores.txt", scores)
    return {**scores, "pred_file": Path(preds[0]).name}


def write_vis(col: Collected, meshes: list, mano, folder: Path) -> None:
    """``folder/<key>.png``: result over the input image | query points coloured by predicted SDF; ``meshes``:
    each sample's object mesh (``hoisdf.evaluate.sample_meshes``)."""
    from hoisdf.evaluation.visualize import result_panel, save_grid

    a = {k: col.get(k) for k in ("joints", "gt_joints", "verts", "gt_verts", "obj_pose", "gt_obj_pose")}
    where = {key: i for i, key in enumerate(col.keys)}
    for key, item in col.vis.items():
        i = where[key]
        panels = result_panel(item["img"], item["K"], a["joints"][i], a["gt_joints"][i],
                              None if a["verts"] is None else a["verts"][i], a["gt_verts"][i], mano.faces,
                              a["obj_pose"][i], a["gt_obj_pose"][i], meshes[i][0], item["points"],
                              item["sdf"])
        save_grid(panels, folder / f"{col.keys[i]}.png")
