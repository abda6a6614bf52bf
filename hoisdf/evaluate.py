"""``python -m hoisdf.evaluate --ckpt RUN --shards STORE [STORE ...] --mano DIR [--out DIR] [--vis N] ...``

Runs a trained HOISDF on stores (batched, no gradients, bf16 autocast on CUDA), scores it with the published
protocols (:mod:`hoisdf.metrics`), prints the paper's table layout beside a mean-pose baseline, and writes
``OUT/metrics.json``, ``OUT/per_object.csv``, the DexYCB HPE result file ``dexycb_hpe.txt``, with
``--ho3d-order evaluation.txt`` HO-3D's ``pred.json`` / ``pred.zip``, and with ``--vis N`` result pictures
``OUT/vis/<key>.png``. ``OUT`` defaults to ``RUN/eval-<store name>``.

Protocol: the network sees the deterministic central crop; hand outputs are wrist-relative and placed with the
ground-truth wrist (as HOISDF; so MJE and root-relative MJE coincide up to the predicted wrist, which is 0).
Joint metrics compare with the records' ``joints_3d``, mesh metrics with the ground-truth MANO vertices.
The mean-pose baseline predicts, for every sample, the mean wrist-relative joints (and vertices) of a store
(``--baseline-store``, e.g. the training store; by default the evaluated one, which peeks at its labels), placed
at the same wrist, and the object at the network's anchor ``obj_center`` with the identity rotation.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from hoidata.errors import DataError
from hoidata.geometry.mirror import mirror_mesh
from hoidata.store import read_index
from hoisdf import metrics as M
from hoisdf.augment import augment_batch
from hoisdf.checkpoint import CHECKPOINTS, find_checkpoint, load_checkpoint
from hoisdf.config import config_from_dict
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.eval_outputs import export, format_table, json_safe, write_per_object, write_vis
from hoisdf.export import DEXYCB_TIP_JOINTS, HO3D_TIP_VERTICES
from hoisdf.losses import hand_targets, mirrored_shape_mano
from hoisdf.plausibility import plausibility_report

UNSEEN_HO3D = "019_pitcher_base"  # excluded from HO-3D object metrics (upstream test.py)
BASELINE_ROWS = 10000  # at most this many label rows (evenly spaced) make the mean pose
SDF_KEYS = ("hand_points", "hand_sdf", "obj_points", "obj_sdf", "hand_rows", "obj_rows")


@dataclass
class Collected:
    """Per-sample predictions and ground truth (N samples): ``arrays`` hold numpy float64, metres, camera frame."""

    keys: list[str] = field(default_factory=list)
    store: list[int] = field(default_factory=list)  # index into the evaluated stores
    rows: list[int] = field(default_factory=list)  # row of the record in its store's index (stored order)
    names: list[str] = field(default_factory=list)  # object names
    frame_ids: list[str] = field(default_factory=list)
    arrays: dict[str, list] = field(default_factory=dict)  # joints, gt_joints, root, obj_pose, ... (chunks)
    vis: dict[str, dict] = field(default_factory=dict)  # key -> image, K and query points of the first samples

    def add(self, **chunks) -> None:
        for k, v in chunks.items():
            self.arrays.setdefault(k, []).append(np.asarray(v, dtype=np.float64))

    def get(self, name: str) -> np.ndarray | None:
        chunks = self.arrays.get(name)
        return np.concatenate(chunks) if chunks else None

    def sort(self) -> None:
        """Put the samples in stored order (store, then index row), whatever order the loader workers gave."""
        order = np.lexsort((self.rows, self.store))
        for name in ("keys", "store", "rows", "names", "frame_ids"):
            setattr(self, name, [getattr(self, name)[i] for i in order])
        self.arrays = {k: [self.get(k)[order]] for k in self.arrays}


def resolve_device(device: str | torch.device | None) -> torch.device:
    return torch.device(device) if device else torch.device("cuda" if torch.cuda.is_available() else "cpu")


def run_folder(ckpt: Path) -> Path:
    """The run folder of a checkpoint path (``RUN/checkpoints/x.pt`` -> ``RUN``) or of a run folder."""
    ckpt = Path(ckpt)
    if ckpt.is_dir():
        return ckpt
    return ckpt.parent.parent if ckpt.parent.name == CHECKPOINTS else ckpt.parent


def load_for_eval(run, mano, device: torch.device, boxes: str | None = None):
    """(model in eval mode, TrainConfig, info dict with checkpoint path, epoch and step) from a run or .pt."""
    from hoisdf.model import build_model

    path = find_checkpoint(run)
    payload = load_checkpoint(path)
    config = config_from_dict(payload["config"])
    settings = replace(config.model, weights="", **({"test_boxes": boxes} if boxes else {}))
    model = build_model(settings, mano)
    model.load_state_dict(payload["model"])
    progress = payload.get("progress", {})
    info = {"checkpoint": str(path), "epoch": progress.get("epoch"), "global_step": progress.get("global_step"),
            "test_boxes": settings.test_boxes}
    return model.to(device).eval(), config, info


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def _keep_vis(col: Collected, batch: dict, out: dict, limit: int) -> None:
    """Keep the network input image, its K and the query points (camera frame) of the first samples."""
    for i in range(min(len(batch["key"]), limit - len(col.vis))):
        img = (batch["img"][i].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().cpu().numpy()
        points = [out["hand_query"][i] + batch["hand_root"][i], out["obj_query"][i] + batch["obj_center"][i]]
        sdf = [out["hand_query_sdf"][i], out["obj_query_sdf"][i]]
        col.vis[batch["key"][i]] = {"img": img, "K": _np(batch["K"][i]), "points": _np(torch.cat(points)),
                                    "sdf": _np(torch.cat(sdf))}


def predict_batch(model, mano, mirrored, batch: dict, config) -> tuple[dict, dict[str, np.ndarray]]:
    """One loader batch (on the model's device) -> (network input batch and raw outputs, per-sample arrays:
    joints, verts (when predicted), gt_joints, gt_verts, root, obj_pose, gt_obj_pose, obj_center; metres,
    camera frame, the predicted hand placed at the ground-truth wrist)."""
    device = batch["img"].device
    batch = augment_batch({k: v for k, v in batch.items() if k not in SDF_KEYS}, config.augment, None, train=False)
    with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=device.type == "cuda"):
        out = model(batch, points="field")
    gt = hand_targets(mano, mirrored, batch)  # full precision, outside autocast
    root = batch["hand_root"].float()[:, None]
    pose = torch.eye(4, device=device).repeat(len(root), 1, 1)
    pose[:, :3, :3], pose[:, :3, 3] = out["obj_rotation"].float(), out["obj_translation"].float()
    arrays = {"joints": out["joints"].float() + root, "gt_joints": batch["joints_3d"], "root": root[:, 0],
              "gt_verts": gt["verts"].float() + root, "obj_pose": pose, "gt_obj_pose": batch["object_pose"],
              "obj_center": batch["obj_center"]}
    if "verts" in out:
        arrays["verts"] = out["verts"].float() + root
    return (batch, out), {k: _np(v) for k, v in arrays.items()}


def infer(model, mano, config, stores: list, batch_size: int, device: torch.device, limit: int | None = None,
          vis: int = 0, progress: bool = True, workers: int = 0, indexes: dict | None = None) -> Collected:
    """Predictions and ground truth of the records of ``stores``, returned in stored order (store after store).

    ``workers`` loader processes decode records (shards are split between them, so with ``limit`` the first
    samples are the first ones the loader delivers); ``vis`` keeps pictures' inputs of the first samples.
    ``indexes``: already read store indexes by store path.
    """
    mano.to(device)
    mirrored, col = mirrored_shape_mano(mano), Collected()
    bar = tqdm(desc="evaluating", unit="img", disable=not progress)
    for s, store in enumerate(stores):
        index = (indexes or {}).get(store) or read_index(store)
        rows, lab = {k: i for i, k in enumerate(index.keys)}, index.labels
        bar.total = (bar.total or 0) + min(len(rows), (limit or len(rows) + len(col.keys)) - len(col.keys))
        data = build_dataset([StoreSpec(store)], batch_size, n_hand=1, n_object=1, training=False)
        for batch in make_loader(data, min(workers, len(index.shards)), pin_memory=device.type == "cuda"):
            n = len(batch["key"]) if limit is None else min(len(batch["key"]), limit - len(col.keys))
            if n <= 0:
                break
            batch = {k: v[:n].to(device) if torch.is_tensor(v) else v[:n] for k, v in batch.items()}
            (batch, out), arrays = predict_batch(model, mano, mirrored, batch, config)
            missing = [k for k in batch["key"] if k not in rows]
            if missing:
                raise DataError(store, missing[0], "record missing from the store index")
            r = np.array([rows[k] for k in batch["key"]])
            col.add(**arrays, ho3d_tips=lab["tip_convention"][r] == "ho3d", ho3d=lab["dataset"][r] == "ho3d",
                    mirrored=lab["mirrored"][r])
            col.keys += batch["key"]
            col.store += [s] * n
            col.rows += r.tolist()
            col.names += [str(x) for x in lab["object_name"][r]]
            col.frame_ids += [str(x) for x in lab["frame_id"][r]]
            _keep_vis(col, batch, out, vis)
            bar.update(n)
    bar.close()
    if not col.keys:
        raise DataError(stores[0] if stores else None, None, "no records to evaluate")
    col.sort()
    _use_ho3d_tips(col)
    return col


def _use_ho3d_tips(col: Collected) -> None:
    """Records whose joints follow HO-3D's fingertip vertices get predicted tips taken from the same vertices."""
    verts, sel = col.get("verts"), col.get("ho3d_tips").astype(bool)
    if verts is None or not sel.any():
        return
    joints = col.get("joints")
    joints[np.ix_(sel, DEXYCB_TIP_JOINTS)] = verts[sel][:, list(HO3D_TIP_VERTICES)]
    col.arrays["joints"] = [joints]


def _masked(fn, mask: np.ndarray, *arrays) -> dict[str, np.ndarray]:
    """Per-sample metrics of ``fn`` on the rows in ``mask``; the other rows are NaN."""
    n = len(mask)
    if not mask.any():
        return {k: np.full(n, np.nan) for k in fn(*[np.zeros_like(a[:1]) for a in arrays])}
    out = {}
    for k, v in fn(*[a[mask] for a in arrays]).items():
        out[k] = np.full(n, np.nan)
        out[k][mask] = v
    return out


def score(joints, gt_joints, verts, gt_verts, obj_pose, gt_obj_pose, obj_verts: list, obj_valid) -> dict:
    """Per-sample metrics (N,) in metres / ratios: :func:`hoisdf.metrics.joint_metrics`, ``mesh_metrics`` when
    ``verts`` is not None, ``object_metrics``. Samples without finite GT joints, or with ``obj_valid`` False,
    get NaN for the hand resp. object metrics (and are skipped by the means)."""
    hand_ok = np.isfinite(gt_joints).all((1, 2)) & np.isfinite(joints).all((1, 2))
    out = _masked(M.joint_metrics, hand_ok, joints, gt_joints)
    if verts is not None:
        out.update(_masked(M.mesh_metrics, hand_ok & np.isfinite(verts).all((1, 2)), verts, gt_verts))
    obj_ok = np.asarray(obj_valid, bool) & np.isfinite(obj_pose).all((1, 2))
    fn = lambda p, g, idx: M.object_metrics(p, g, [obj_verts[i] for i in idx])
    return {**out, **_masked(fn, obj_ok, obj_pose, gt_obj_pose, np.arange(len(obj_pose)))}


def mean_hand(store, mano, max_rows: int = BASELINE_ROWS, index=None) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean wrist-relative GT joints (21, 3) and MANO vertices (778, 3) over a store's labels (metres), and
    the number of rows used (at most ``max_rows``, evenly spaced; rows without finite joints are skipped)."""
    lab = (index or read_index(store)).labels
    n = len(lab["key"])
    rows = np.unique(np.linspace(0, n - 1, min(n, max_rows)).round().astype(np.int64)) if n else np.zeros(0, int)
    rows = rows[np.isfinite(lab["joints_3d"][rows]).all((1, 2)) & np.isfinite(lab["mano_pose"][rows]).all(1)]
    if len(rows) == 0:
        raise DataError(store, "joints_3d", "no record with finite hand labels for the mean-pose baseline")
    joints = lab["joints_3d"][rows].astype(np.float64)
    device = mano.v_template.device
    mirrored, total = mirrored_shape_mano(mano), np.zeros((778, 3))
    for start in range(0, len(rows), 2048):
        sel = rows[start:start + 2048]
        batch = {k: torch.as_tensor(lab[k][sel]).to(device) for k in ("mano_pose", "mano_betas", "mirrored")}
        total += _np(hand_targets(mano, mirrored, batch)["verts"]).astype(np.float64).sum(0)
    return (joints - joints[:, :1]).mean(0), total / len(rows), len(rows)


def sample_meshes(objects: dict, names: list[str], mirrored) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each sample's object mesh (vertices, faces) in the frame its ``object_pose`` poses: a mirrored record
    poses the x-mirrored model (``hoidata.records.mirror_frame``), so it gets the mirrored vertices with the
    faces flipped to stay outward wound. Meshes are shared between samples, not copied."""
    cache, out = {}, []
    for name, flip in zip(names, np.asarray(mirrored, bool)):
        if (name, flip) not in cache:
            cache[name, flip] = mirror_mesh(*objects[name]) if flip else objects[name]
        out.append(cache[name, flip])
    return out


def plausibility_of(verts, poses, meshes: list, mano, progress: bool = True) -> dict:
    """Penetration depth, intersection volume and contact ratio of closed hands (N, 778, 3) against the object
    meshes (N (vertices, faces), see :func:`sample_meshes`) posed by ``poses`` (N, 4, 4); see
    :func:`hoisdf.plausibility.plausibility_report`."""
    import trimesh

    if len(verts) == 0:
        return plausibility_report([])
    closed = mano.close(torch.as_tensor(verts, dtype=torch.float32)).cpu().numpy().astype(np.float64)
    faces = np.asarray(mano.closed_faces)
    unique = {id(m): m for m in meshes}.values()
    watertight = all(trimesh.Trimesh(*m, process=False).is_watertight for m in unique)
    samples = ((closed[i], faces, v @ poses[i][:3, :3].T + poses[i][:3, 3], f) for i, (v, f) in enumerate(meshes))
    samples = tqdm(samples, total=len(meshes), desc="plausibility", disable=not progress, leave=False)
    return {**plausibility_report(samples, obj_watertight=watertight), "object_sign": "pseudonormal" if watertight
            else "winding number"}


def _baseline(col: Collected, mano, store, obj_verts: list, obj_valid, index=None) -> dict[str, np.ndarray]:
    """Per-sample metrics of the mean-pose baseline (see the module docstring) on the collected samples."""
    mean_j, mean_v, _ = mean_hand(store, mano, index=index)
    root, verts = col.get("root")[:, None], col.get("verts")
    pose = np.tile(np.eye(4), (len(root), 1, 1))
    pose[:, :3, 3] = col.get("obj_center")
    return score(mean_j + root, col.get("gt_joints"), None if verts is None else mean_v + root, col.get("gt_verts"),
                 pose, col.get("gt_obj_pose"), obj_verts, obj_valid)


def _plausibility(col: Collected, meshes: list, mano, count: int, progress: bool) -> dict:
    """Plausibility of the predicted hand/object and, for reference, of the ground truth, first ``count`` samples."""
    verts, k = col.get("verts"), min(count, len(col.keys))
    if verts is None or k == 0:
        return {"skipped": "no predicted hand mesh" if verts is None else "--plausibility 0"}
    return {name: plausibility_of(col.get(v)[:k], col.get(p)[:k], meshes[:k], mano, progress)
            for name, v, p in (("model", "verts", "obj_pose"), ("ground_truth", "gt_verts", "gt_obj_pose"))}


def evaluate(run, stores, mano_dir, out_dir=None, batch_size: int = 8, device=None, vis: int = 0,
             limit: int | None = None, boxes: str | None = None, plausibility: int = 32, ho3d_order=None,
             baseline_store=None, progress: bool = True, workers: int = 4) -> dict:
    """Evaluate a checkpoint on stores; write the result files to ``out_dir`` and return metrics.json's content
    (plus ``table``, the printed table).

    Args:
        run: run folder or checkpoint file. stores: store folders. mano_dir: MANO folder.
        out_dir: default ``RUN/eval-<store name>``. device: default CUDA when present.
        vis: pictures of the first ``vis`` samples. limit: evaluate only the first ``limit`` samples.
        boxes: override the model's ``test_boxes`` ("gt" | "predicted").
        plausibility: samples (the first ones) for the plausibility report (0: none).
        ho3d_order: HO-3D ``evaluation.txt`` -> pred.json / pred.zip. baseline_store: store whose labels
            give the mean pose (default: the first evaluated store). workers: loader processes.
    """
    from hoidata.hand import load_mano

    stores = [Path(s) for s in ([stores] if isinstance(stores, (str, Path)) else stores)]
    if boxes not in (None, "gt", "predicted"):
        raise ValueError(f"boxes must be 'gt' or 'predicted', got {boxes!r}")
    device = resolve_device(device)
    mano = load_mano(mano_dir, side="right")
    model, config, info = load_for_eval(run, mano, device, boxes)
    out_dir = Path(out_dir) if out_dir else run_folder(Path(run)) / f"eval-{'+'.join(s.name for s in stores)}"
    indexes = {s: read_index(s) for s in stores}
    objects = {name: mesh for index in indexes.values() for name, mesh in index.objects.items()}
    col = infer(model, mano, config, stores, batch_size, device, limit, vis, progress, workers, indexes)
    missing = sorted(set(col.names) - set(objects))
    if missing:
        raise DataError(stores[0], "objects", f"no mesh in the store index for {missing}")
    names = np.asarray(col.names)
    obj_valid = ~(col.get("ho3d").astype(bool) & (names == UNSEEN_HO3D))
    meshes = sample_meshes(objects, col.names, col.get("mirrored"))
    obj_verts = [v for v, _ in meshes]
    per_sample = score(col.get("joints"), col.get("gt_joints"), col.get("verts"), col.get("gt_verts"),
                       col.get("obj_pose"), col.get("gt_obj_pose"), obj_verts, obj_valid)
    summary = M.summarize(per_sample, names)
    base_src = Path(baseline_store) if baseline_store else stores[0]
    base_summary = M.summarize(_baseline(col, mano, base_src, obj_verts, obj_valid, indexes.get(base_src)))["all"]
    counts = {str(name): int(c) for name, c in zip(*np.unique(names, return_counts=True))}
    result = {
        **info, "stores": [str(s) for s in stores], "device": str(device), "samples": len(col.keys),
        "counts": {"per_object": counts, "hand_metrics": int(np.isfinite(per_sample["rr_mje"]).sum()),
                   "object_metrics": int(np.isfinite(per_sample["oce"]).sum())},
        "overall": summary["all"], "per_object": {k: v for k, v in summary.items() if k != "all"},
        "baseline": {"method": "mean wrist-relative joints/verts placed at the GT wrist; object at obj_center, "
                               "identity rotation", "mean_pose_from": str(base_src), "rows_max": BASELINE_ROWS,
                     "peeks_at_evaluated_labels": base_src.resolve() in [s.resolve() for s in stores],
                     "overall": base_summary},
        "plausibility": _plausibility(col, meshes, mano, plausibility, progress),
        "units": "mm for lengths, ratios for AUC and F-scores",
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    result["files"] = export(col, stores, out_dir, ho3d_order, indexes)
    write_per_object(out_dir / "per_object.csv", summary, counts)
    (out_dir / "metrics.json").write_text(json.dumps(json_safe(result), indent=2))
    if vis:
        write_vis(col, meshes, mano, out_dir / "vis")
    rows = {"HOISDF (this run)": summary["all"], "mean-pose baseline": base_summary}
    return {**result, "table": format_table(rows, col.get("verts") is not None, bool(col.get("ho3d").any()))}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m hoisdf.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ckpt", required=True, type=Path, help="run folder (its checkpoints/last.pt) or a .pt file")
    p.add_argument("--shards", nargs="+", required=True, type=Path, metavar="STORE", help="stores to evaluate")
    p.add_argument("--mano", required=True, type=Path, help="folder with MANO_RIGHT.pkl")
    p.add_argument("--out", type=Path, default=None, help="output folder (default RUN/eval-<store name>)")
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--vis", type=int, default=0, metavar="N", help="write vis/<key>.png for the first N samples")
    p.add_argument("--limit", type=int, default=None, metavar="N", help="evaluate only the first N samples")
    p.add_argument("--boxes", choices=("gt", "predicted"), default=None,
                   help="2D boxes that filter the inference grid (default: the model's test_boxes)")
    p.add_argument("--plausibility", type=int, default=32, metavar="N", help="samples for the plausibility report")
    p.add_argument("--ho3d-order", type=Path, default=None, metavar="evaluation.txt",
                   help="write HO-3D pred.json/pred.zip in this frame order")
    p.add_argument("--baseline-store", type=Path, default=None, metavar="STORE",
                   help="store whose mean hand pose is the baseline (e.g. the training store)")
    p.add_argument("--workers", type=int, default=4, help="loader processes decoding records (0: none)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if min(args.batch_size, args.limit or 1) < 1 or min(args.vis, args.plausibility, args.workers) < 0:
        print("error: --batch-size and --limit must be >= 1, --vis, --plausibility, --workers >= 0", file=sys.stderr)
        return 2
    try:
        result = evaluate(args.ckpt, args.shards, args.mano, args.out, args.batch_size, args.device, args.vis,
                          args.limit, args.boxes, args.plausibility, args.ho3d_order, args.baseline_store,
                          progress=not args.no_progress, workers=args.workers)
    except (DataError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{result['samples']} samples, checkpoint {result['checkpoint']} (epoch {result['epoch']}), "
          f"boxes {result['test_boxes']}; lengths in mm")
    print(result["table"])
    for who, plaus in result["plausibility"].items():
        if isinstance(plaus, dict):
            print(f"plausibility, {who} ({plaus['num_samples']} samples): penetration "
                  f"{plaus['penetration_depth_mm']:.2f} mm, intersection {plaus['intersection_volume_cm3']:.2f} cm^3, "
                  f"contact ratio {plaus['contact_ratio']:.2f}")
    print(f"baseline mean pose from {result['baseline']['mean_pose_from']}"
          + (" (the evaluated store's own labels)" if result["baseline"]["peeks_at_evaluated_labels"] else ""))
    print("wrote", ", ".join([*(Path(p).name for p in result["files"].values()), "metrics.json", "per_object.csv"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
