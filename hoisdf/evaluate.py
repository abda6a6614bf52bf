"""``python -m hoisdf.evaluate --ckpt RUN --shards STORE [STORE ...] --mano DIR [--out DIR] [--vis N] ...``

Runs a trained HOISDF on stores (batched, no gradients; fp32, or bf16 autocast with ``--precision bf16``), scores
it with the published protocols (:mod:`hoisdf.scoring.metrics`), prints the paper's table layout beside a
mean-pose baseline, and writes
``OUT/metrics.json``, ``OUT/per_object.csv``, per DexYCB split the HPE result file ``dexycb_hpe_<split>.txt`` with
the toolkit's sample ids (``dexycb_hpe_<split>_subset.txt`` when it lacks some of the split's valid samples, which
the toolkit's evaluator refuses), with ``--ho3d-order evaluation.txt`` HO-3D's ``pred.json`` / ``pred.zip``, and
with ``--vis N`` result pictures ``OUT/vis/<key>.png``. ``OUT`` defaults to ``RUN/eval-<store name>``.
``metrics.json["dexycb_hpe"]`` holds the toolkit's numbers for each HPE file (:mod:`hoisdf.scoring.official`).

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
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from hoidata.atomic import write_atomic
from hoidata.cli_types import ArgumentParser, local_path, non_negative_int, positive_int
from hoidata.errors import DataError, run_cli
from hoidata.schema import FULL
from hoidata.store import RemoteStore, read_index, resolve_store
from hoidata.store.paths import refuse_repeated_stores
from hoisdf.evaluation.inference import Collected, infer, load_for_eval, resolve_device, run_folder
from hoisdf.evaluation.model_scores import (
    BASELINE_ROWS,
    baseline_scores,
    plausibility_summary,
    sample_meshes,
    score,
)
from hoisdf.evaluation.outputs import (
    checked_ho3d_order,
    clear_results,
    export,
    format_table,
    score_ho3d_files,
    write_per_object,
    write_vis,
)
from hoisdf.scoring import metrics as M
from hoisdf.scoring.official import format_ho3d_scores
from hoisdf.scoring.results_json import json_safe

UNSEEN_HO3D = "019_pitcher_base"  # excluded from HO-3D object metrics (upstream test.py)
BOX_SOURCES = (None, "gt", "predicted")  # --boxes: the model's test_boxes, or one of these


@dataclass(frozen=True)
class EvalOptions:
    """What an evaluation is asked for (the command's flags; ``python -m hoisdf.evaluate --help``).

    batch_size: samples per forward. device: default CUDA when present. vis: pictures of the first ``vis`` samples.
    limit: evaluate only the first ``limit`` samples. boxes: override the model's ``test_boxes`` ("gt" |
    "predicted"). plausibility: samples (the first ones) for the plausibility report (0: none). ho3d_order: HO-3D
    ``evaluation.txt`` -> pred.json / pred.zip; checked before any work against every HO-3D store
    (:mod:`hoisdf.scoring.ho3d_list`); a store or list that cannot give a complete submission is a DataError, never a
    missing file. baseline_store: store whose labels give the mean pose (default: the first evaluated store).
    progress: progress bars. workers: loader processes, and processes for the plausibility report. ho3d_gt: folder
    with the challenge's ``evaluation_xyz.json`` / ``evaluation_verts.json``: the written pred.json is scored against
    them (``metrics.json["ho3d_challenge"]``, ``scores.txt``). precision: "fp32" (as upstream) or "bf16" (autocast;
    geometry, ranking and head outputs stay fp32).
    """

    batch_size: int = 8
    device: str | None = None
    vis: int = 0
    limit: int | None = None
    boxes: str | None = None
    plausibility: int = 32
    ho3d_order: str | Path | None = None
    baseline_store: str | Path | None = None
    progress: bool = True
    workers: int = 4
    ho3d_gt: str | Path | None = None
    precision: str = "fp32"

    def check(self) -> None:
        """A combination no evaluation can run is a ValueError (before any work)."""
        if self.boxes not in BOX_SOURCES:
            raise ValueError(f"boxes must be 'gt' or 'predicted', got {self.boxes!r}")
        if self.ho3d_gt is not None and self.ho3d_order is None:
            raise ValueError("--ho3d-gt scores the pred.json that --ho3d-order writes: give both")


@dataclass
class Scored:
    """What :func:`score_collected` makes of the collected samples."""

    per_sample: dict  # metric -> (N,) per-sample values (NaN where a sample has no ground truth)
    summary: dict  # "all" and every object name -> metric -> mean
    counts: dict  # object name -> samples
    meshes: list  # each sample's object mesh (vertices, faces), in the frame its pose poses
    baseline: dict | None  # the mean-pose baseline's summary, None: its store has no hand labels
    baseline_store: object  # the store the mean pose came from
    plausibility: dict


def evaluate(run, stores, mano_dir, out_dir=None, options: EvalOptions | None = None, **flags) -> dict:
    """Evaluate a checkpoint on stores; write the result files to ``out_dir`` and return metrics.json's content
    (plus ``table``, the printed table). The result files an earlier run left in ``out_dir`` are removed first
    (:func:`~hoisdf.evaluation.outputs.clear_results`), so a failed run never leaves one of them looking current;
    ``metrics.json`` is written last.

    Args:
        run: run folder or checkpoint file. stores: store folders or URLs (hoidata.store.resolve_store). mano_dir:
            MANO folder. out_dir: default ``RUN/eval-<store name>``.
        options: :class:`EvalOptions`; ``flags`` replace single fields of it (``batch_size=4``).

    The steps: :func:`collect` (the model over the stores), :func:`score_collected` (metrics, baseline,
    plausibility), :func:`write_outputs` (result files), :func:`result_dict` (metrics.json's content).
    """
    from hoidata.hand import load_mano

    opts = replace(options or EvalOptions(), **flags)
    stores = [resolve_store(s) for s in ([stores] if isinstance(stores, (str, Path, RemoteStore)) else stores)]
    refuse_repeated_stores(stores, "the stores to evaluate (--shards)")  # each record is scored once
    out_dir = Path(out_dir) if out_dir else run_folder(Path(run)) / f"eval-{'+'.join(s.name for s in stores)}"
    clear_results(out_dir)  # whatever happens next, no earlier run's result file stays beside this run's
    opts.check()
    indexes = {s: read_index(s) for s in stores}
    order = (checked_ho3d_order(opts.ho3d_order, opts.ho3d_gt, indexes, opts.limit) if opts.ho3d_order is not None
             else None)
    device = resolve_device(opts.device)
    mano = load_mano(mano_dir, side="right")
    model, config, info = load_for_eval(run, mano, device, opts.boxes)
    col = collect(model, mano, config, stores, indexes, device, opts)
    scored = score_collected(col, mano, stores, indexes, opts)
    written = write_outputs(out_dir, col, scored, mano, stores, indexes, order, opts)
    result = result_dict(info, stores, device, col, scored, crop_note(config.model, col.get("upstream_crop"),
                                                                      len(col.keys)), written, opts)
    write_atomic(out_dir / "metrics.json", json.dumps(json_safe(result), indent=2).encode())  # last: the run is done
    rows = {"HOISDF (this run)": scored.summary["all"],
            **({"mean-pose baseline": scored.baseline} if scored.baseline else {})}
    return {**result, "table": format_table(rows, col.get("verts") is not None, bool(col.get("ho3d").any()))}


def collect(model, mano, config, stores: list, indexes: dict, device, opts: EvalOptions) -> Collected:
    """The model's predictions and the ground truth of the stores' records, in stored order
    (:func:`hoisdf.evaluation.inference.infer`); ``model`` any :class:`hoisdf.model.HOISDF` in eval mode."""
    return infer(model, mano, config, stores, opts.batch_size, device, opts.limit, opts.vis, opts.progress,
                 opts.workers, indexes, opts.precision)


def score_collected(col: Collected, mano, stores: list, indexes: dict, opts: EvalOptions) -> Scored:
    """Per-sample and summary metrics of the collected samples, the mean-pose baseline's (when its store has hand
    labels) and the plausibility report; object meshes come from the stores' indexes (a missing one is a
    DataError naming the first store)."""
    objects = {name: mesh for index in indexes.values() for name, mesh in index.objects.items()}
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
    base_src = resolve_store(opts.baseline_store) if opts.baseline_store else stores[0]
    base_index = indexes.get(base_src) or read_index(base_src)
    baseline = None
    if (base_index.labels["kind"] == FULL).any():
        baseline = M.summarize(baseline_scores(col, mano, base_src, obj_verts, obj_valid, base_index))["all"]
    counts = {str(name): int(c) for name, c in zip(*np.unique(names, return_counts=True))}
    plausibility = plausibility_summary(col, meshes, mano, opts.plausibility, opts.progress, opts.workers)
    return Scored(per_sample, summary, counts, meshes, baseline, base_src, plausibility)


def write_outputs(out_dir: Path, col: Collected, scored: Scored, mano, stores: list, indexes: dict, order,
                  opts: EvalOptions) -> dict:
    """The result files (toolkit files, HO-3D pred.json with ``order``, ``per_object.csv``, pictures) in
    ``out_dir``; returns what metrics.json says of them: ``files``, ``dexycb_hpe`` (and ``ho3d_challenge``)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files, hpe = export(col, stores, out_dir, order, indexes)
    written = {"files": files, "dexycb_hpe": hpe}
    if opts.ho3d_gt is not None:
        written["ho3d_challenge"] = score_ho3d_files(files, opts.ho3d_gt, out_dir)
    write_per_object(out_dir / "per_object.csv", scored.summary, scored.counts)
    if opts.vis:
        write_vis(col, scored.meshes, mano, out_dir / "vis")
    return written


def result_dict(info: dict, stores: list, device, col: Collected, scored: Scored, note: str | None, written: dict,
                opts: EvalOptions) -> dict:
    """metrics.json's content, built here only: the checkpoint ``info``, the stores, the scores, the baseline, the
    plausibility report, the notes and what :func:`write_outputs` wrote."""
    flags = col.get("upstream_crop")
    per_sample, base_src = scored.per_sample, scored.baseline_store
    return {
        **info, "stores": [str(s) for s in stores], "device": str(device), "samples": len(col.keys),
        "precision": {"mode": opts.precision, "dtypes": col.dtypes},
        "counts": {"per_object": scored.counts, "hand_metrics": int(np.isfinite(per_sample["rr_mje"]).sum()),
                   "object_metrics": int(np.isfinite(per_sample["oce"]).sum())},
        "overall": scored.summary["all"], "per_object": {k: v for k, v in scored.summary.items() if k != "all"},
        "baseline": {"method": "mean wrist-relative joints/verts placed at the GT wrist; object at obj_center, "
                               "identity rotation", "mean_pose_from": str(base_src), "rows_max": BASELINE_ROWS,
                     "peeks_at_evaluated_labels": base_src.resolve() in [s.resolve() for s in stores],
                     "overall": scored.baseline or {"skipped": f"{base_src} has no hand labels; --baseline-store TRAIN"}},
        "plausibility": scored.plausibility,
        "units": "mm for lengths, ratios for AUC and F-scores",
        "upstream_crop_records": 0 if flags is None else int((flags > 0.5).sum()),
        "notes": [note] if note else [],
        **written,
    }


def crop_note(model_settings, flags, n: int) -> str | None:
    """One line when a model that computes as upstream's does (``model.pixel_convention == "upstream"``, e.g.
    imported released weights) is evaluated on records that are not upstream's test crops (``flags``: per-sample
    1 / 0, or None); else None. The setting is read defensively: runs from before it have no such field."""
    convention = getattr(model_settings, "pixel_convention", None)
    if convention is None and isinstance(model_settings, dict):
        convention = model_settings.get("pixel_convention")
    others = n if flags is None else int(n - (np.asarray(flags) > 0.5).sum())
    if convention != "upstream" or others == 0:
        return None
    return (f"note: the model follows upstream's pixel convention, but {others} of {n} records are not upstream test "
            "crops: it sees other pixels, boxes and object anchor than upstream's (rebuild the store with "
            "record.crop=\"upstream\", docs/stores.md)")


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="python -m hoisdf.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ckpt", required=True, type=Path, help="run folder (its checkpoints/last.pt) or a .pt file")
    p.add_argument("--shards", nargs="+", required=True, type=str, metavar="STORE",
                   help="stores to evaluate: folders or http(s)://, s3://, gs:// URLs")
    p.add_argument("--mano", required=True, type=Path, help="folder with MANO_RIGHT.pkl")
    p.add_argument("--out", type=local_path, default=None, help="output folder (default RUN/eval-<store name>)")
    p.add_argument("--batch-size", type=positive_int, default=8)
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--vis", type=non_negative_int, default=0, metavar="N", help="write vis/<key>.png for the first N samples")
    p.add_argument("--limit", type=positive_int, default=None, metavar="N", help="evaluate only the first N samples")
    p.add_argument("--boxes", choices=("gt", "predicted"), default=None,
                   help="2D boxes that filter the inference grid (default: the model's test_boxes)")
    p.add_argument("--plausibility", type=non_negative_int, default=32, metavar="N",
                   help="samples for the plausibility report (0: none)")
    p.add_argument("--ho3d-order", type=Path, default=None, metavar="evaluation.txt",
                   help="write HO-3D pred.json/pred.zip in this frame order")
    p.add_argument("--ho3d-gt", type=Path, default=None, metavar="DIR",
                   help="score pred.json against DIR/evaluation_xyz.json and evaluation_verts.json as the challenge "
                        "server does (metrics.json['ho3d_challenge'], scores.txt); needs --ho3d-order")
    p.add_argument("--baseline-store", default=None, metavar="STORE",
                   help="store whose mean hand pose is the baseline (e.g. the training store)")
    p.add_argument("--workers", type=non_negative_int, default=4,
                   help="loader processes decoding records, and processes for the plausibility report (0: this process)")
    p.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                   help="fp32 (default, as upstream) or bf16 autocast (geometry stays fp32; metrics.json "
                        "records the dtype of every stage)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_cli("", lambda: _run(args), args.debug)


def options_from_args(args) -> EvalOptions:
    """The command's flags as :class:`EvalOptions` (each option is the flag of the same name)."""
    values = {f.name: getattr(args, f.name) for f in fields(EvalOptions) if f.name != "progress"}
    return EvalOptions(**values, progress=not args.no_progress)


def _run(args) -> int:
    result = evaluate(args.ckpt, args.shards, args.mano, args.out, options_from_args(args))
    print(f"{result['samples']} samples, checkpoint {result['checkpoint']} (epoch {result['epoch']}), "
          f"boxes {result['test_boxes']}; lengths in mm")
    print(result["table"])
    for note in result["notes"]:
        print(note)
    if result["counts"]["hand_metrics"] == 0:
        print("no hand ground truth in these records (nan above); an HO-3D evaluation split is scored by --ho3d-gt "
              "or the challenge server")
    for who, plaus in result["plausibility"].items():
        if isinstance(plaus, dict) and "skipped" not in plaus:
            print(f"plausibility, {who} ({plaus['num_samples']} samples): penetration "
                  f"{plaus['penetration_depth_mm']:.2f} mm, intersection {plaus['intersection_volume_cm3']:.2f} cm^3 "
                  f"(bound {plaus['intersection_error_cm3']:.2f} on average), "
                  f"contact ratio {plaus['contact_ratio']:.2f}")
    if "skipped" not in result["baseline"]["overall"]:
        print(f"baseline mean pose from {result['baseline']['mean_pose_from']}"
              + (" (the evaluated store's own labels)" if result["baseline"]["peeks_at_evaluated_labels"] else ""))
    if "ho3d_challenge" in result:
        print(format_ho3d_scores(result["ho3d_challenge"]))
    extra = ["scores.txt"] if "ho3d_challenge" in result else []
    print("wrote", ", ".join([*(Path(p).name for p in result["files"].values()), *extra, "metrics.json",
                              "per_object.csv"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
