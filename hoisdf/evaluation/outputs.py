"""What ``python -m hoisdf.evaluate`` writes: the printed table, metrics.json helpers, per_object.csv,
the official export files and the result pictures."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.geometry.mirror import mirror_points
from hoidata.store import read_index
from hoisdf.evaluation.inference import Collected
from hoisdf.evaluation.submissions import write_dexycb_hpe, write_ho3d_pred

TABLE = (("MJE", "rr_mje"), ("PA-MJE", "pa_mje"), ("OCE", "oce"), ("MCE", "mce"), ("ADD-S", "add_s"))
MESH_TABLE = (("MME", "mme"), ("PA-MME", "pa_mme"), ("F@5", "f5"), ("F@15", "f15"))
HO3D_TABLE = (("ST-MJE", "st_mje"), ("OME", "ome"))  # HO-3D tables: hand metrics from the server, object OME


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


def json_safe(x):
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x.item() if isinstance(x, np.generic) else x


def write_per_object(path: Path, summary: dict, counts: dict[str, int]) -> None:
    names = sorted(k for k in summary if k != "all")
    metric_names = list(summary["all"])
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["object", "samples", *metric_names])
        for name in [*names, "all"]:
            writer.writerow([name, counts.get(name, sum(counts.values())),
                             *(f"{summary[name][m]:.6g}" for m in metric_names)])


def export(col: Collected, stores: list, out_dir: Path, ho3d_order=None, indexes: dict | None = None) -> dict[str, str]:
    """HPE file per store and, with ``ho3d_order``, pred.json/pred.zip of HO-3D stores.

    HPE ids are the records' rows in their store's index: the toolkit's sample index when the store holds
    the whole split in the toolkit's order with no skipped frame (a warning is printed otherwise). Mirrored
    records (DexYCB left hands seen as right ones) are mirrored back, so the file holds the toolkit's frame.
    """
    written, joints, verts = {}, col.get("joints"), col.get("verts")
    mirrored = col.get("mirrored")
    if mirrored is not None:
        joints = np.where(mirrored.astype(bool)[:, None, None], mirror_points(joints), joints)
    store, ho3d = np.asarray(col.store), col.get("ho3d").astype(bool)
    order = None
    if ho3d_order:
        if not Path(ho3d_order).is_file():
            raise DataError(ho3d_order, None, "HO-3D evaluation list not found")
        order = [ln.strip() for ln in Path(ho3d_order).read_text().splitlines() if ln.strip()]
    for s, path in enumerate(stores):
        sel = np.flatnonzero(store == s)
        name = "dexycb_hpe.txt" if len(stores) == 1 else f"dexycb_hpe_{Path(path).name}.txt"
        written[f"hpe:{path}"] = str(write_dexycb_hpe(out_dir / name, np.asarray(col.rows)[sel], joints[sel]))
        if ((indexes or {}).get(path) or read_index(path)).skipped:
            print(f"warning: {path} skipped frames at build time: {name}'s ids (index rows) are not the toolkit's")
        if order is None:
            continue
        if not ho3d[sel].all():
            print(f"--ho3d-order: {path} is not an HO-3D store; no pred.json written for it")
            continue
        ids = ["/".join(col.frame_ids[i].rsplit("_", 1)) for i in sel]  # SEQ_id -> SEQ/id
        v = verts[sel] if verts is not None else np.zeros((len(sel), 0, 3))
        stem = "pred" if len(stores) == 1 else f"pred_{Path(path).name}"
        try:
            for suffix in (".json", ".zip"):
                written[f"ho3d{suffix}:{path}"] = str(write_ho3d_pred(out_dir / f"{stem}{suffix}", ids, joints[sel],
                                                                      v, order=order))
        except ValueError as err:
            print(f"--ho3d-order: {path}: not written: {err}")
    return written


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
