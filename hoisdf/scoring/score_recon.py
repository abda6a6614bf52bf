"""``hoisdf score recon``: hand and object reconstruction scores of any method's meshes against the ground truth.

    hoisdf score recon --pred SDF_MESH_DIR (--gt GT_DIR | --gt-store STORE --mano DIR) [--protocol gsdf|exact]
                       [--seed S] [--repeats K]
                       [--drop-failures] [--parts hand,obj] [--ids FILE] [--workers N]

The ground truth is a folder of meshes (:mod:`hoisdf.scoring.recon_files`) or posed from a store's labels
(:mod:`hoisdf.scoring.recon_store`).

Protocols (docs/scoring.md, "Reconstruction"): ``gsdf`` is gSDF's ``_evaluate`` operation for operation
(:mod:`hoisdf.scoring.recon_gsdf`), its draws seeded per frame by ``--seed`` (``--repeats K``: K seeds, the
spread of the unseeded protocol); ``exact`` is the same quantities as surface integrals with a rigorous bound
(:mod:`hoisdf.scoring.recon_exact`). Every frame of the ground truth counts: a missing, unreadable or empty
prediction is a failure scored with F = 0 and the Chamfer of a prediction collapsed to the ground truth's
centroid (:func:`~hoisdf.scoring.recon_exact.centroid_penalty`); ``--drop-failures`` reports the old survivor
mean instead, labelled so. Imports no model code.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
from pathlib import Path

import numpy as np

from hoidata.cli_types import non_negative_int, positive_int
from hoidata.errors import DataError
from hoisdf.scoring import recon_exact, recon_gsdf
from hoisdf.scoring.recon_files import PARTS, check_mesh, gt_files, gt_mesh, named_files, read_ids

HELP = "hand and object Chamfer distance and F-scores of any method's meshes (gSDF's protocol, or exact)"
CHAMFER_TOLERANCE = 1e-3  # cm^2, half-width aimed at by the exact protocol
F_TOLERANCE = 1e-3


def metric_names(part: str) -> list[str]:
    return ["chamfer"] + [name for name, _ in recon_gsdf.THRESHOLDS[part]]


def _frame(job) -> dict:
    """One frame, every part: failure reason, gSDF's raw numbers per seed (gsdf) or values and bounds (exact)."""
    ident, files, protocol, seeds, settings = job
    out = {}
    for part, (pred_path, gt_path) in files.items():
        gv, gf = gt_mesh(gt_path)
        mesh, why = check_mesh(pred_path)
        out[part] = {"failure": why, "penalty": recon_exact.centroid_penalty(gv * recon_gsdf.CM, gf)}
        if protocol == "exact" and mesh is not None:
            thresholds = [t for _, t in recon_gsdf.THRESHOLDS[part]]
            out[part]["exact"] = recon_exact.pair_scores((mesh[0] * recon_gsdf.CM, mesh[1]), (gv * recon_gsdf.CM, gf),
                                                         thresholds, metric_names(part)[1:], **settings)
    if protocol == "gsdf":
        for seed in seeds:
            rng = recon_gsdf.frame_rng(seed, ident)  # one stream per frame: hand, then object, as _evaluate
            for part, (pred_path, gt_path) in files.items():
                out[part].setdefault("raw", []).append(recon_gsdf.part_scores(pred_path, gt_path, part, rng))
    return out


def _run_frames(jobs: list, workers: int) -> list[dict]:
    from tqdm import tqdm

    pool = None
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn"))
    with pool or contextlib.nullcontext():
        results = pool.map(_frame, jobs, chunksize=1) if pool else map(_frame, jobs)
        return list(tqdm(results, total=len(jobs), desc="frames", unit="frame", disable=None))


def _frame_values(record: dict, part: str, seed_index: int) -> tuple[dict, dict | None, str]:
    """(numbers counted over all frames, numbers as gSDF reports them or None, failure reason)."""
    names, rec = metric_names(part), record[part]
    if "raw" in rec:
        raw = rec["raw"][seed_index]
        why = rec["failure"] or ("" if raw is not None else "gSDF's evaluation raised")
        values = {n: raw[n] for n in names} if raw is not None else None
    else:
        why = rec["failure"]
        values = {n: rec["exact"][n][0] for n in names} if "exact" in rec else None
    counted = {n: (0.0 if n != "chamfer" else rec["penalty"]) for n in names} if why else dict(values)
    return counted, values, why


def summarize(records: list[dict], ids: list[str], parts, seed_index: int = 0) -> dict:
    """Per part: means over every frame (failures penalised), survivor means (gSDF's tools/eval.py), medians,
    failure count and reasons; the exact protocol's mean bound per number."""
    out = {}
    for part in parts:
        names = metric_names(part)
        counted, raw, failed = {n: [] for n in names}, {n: [] for n in names}, []
        bounds = {n: [] for n in names}
        for ident, rec in zip(ids, records):
            c, values, why = _frame_values(rec, part, seed_index)
            for n in names:
                counted[n].append(c[n])
                raw[n].append(None if values is None else values[n])
                if "exact" in rec[part] and not why:
                    bounds[n].append(rec[part]["exact"][n][1])
            if why:
                failed.append({"id": ident, "why": why})
        if "raw" not in records[0][part]:  # exact: a failure is dropped, whatever it would have given
            raw = {n: [None if any(f["id"] == i for f in failed) else v for i, v in zip(ids, raw[n])] for n in names}
        part_out = {n: float(np.mean(counted[n])) for n in names}
        part_out["chamfer_median"] = float(np.median(counted["chamfer"]))
        part_out["survivor"] = {n: recon_gsdf.survivor_mean(raw[n]) for n in names}
        part_out["survivor"]["chamfer_median"] = recon_gsdf.survivor_median(raw["chamfer"])
        part_out["survivor"]["frames"] = sum(v is not None and not np.isnan(v) for v in raw["chamfer"])
        part_out.update(frames=len(ids), failures=len(failed), failed=failed,
                        penalty={"f": 0.0, "chamfer": "the ground truth's centroid-point Chamfer (cm^2)"})
        if any(bounds[n] for n in names):
            part_out["bound"] = {n: float(np.mean(bounds[n])) for n in names}
        out[part] = part_out
    return out


def score_recon(pred, gt, protocol: str = "gsdf", seed: int = 0, repeats: int = 1, parts=PARTS, ids_file=None,
                workers: int = 1, tol_chamfer: float = CHAMFER_TOLERANCE, tol_f: float = F_TOLERANCE,
                max_queries: int = recon_exact.MAX_QUERIES) -> dict:
    """The numbers of ``hoisdf score recon`` (see the module docstring); ``parts``: a subset of ('hand', 'obj')."""
    pred = Path(pred)
    if not pred.is_dir():
        raise DataError(pred, None, "prediction folder not found")
    files, layout = gt_files(gt, parts)
    ids = sorted(set().union(*(files[p] for p in parts)))
    if ids_file is not None:
        wanted = read_ids(ids_file)
        unknown = [i for i in wanted if i not in ids]
        if unknown:
            raise DataError(ids_file, f"line {wanted.index(unknown[0]) + 1}",
                            f"no ground-truth mesh for frame {unknown[0]!r} in {gt}")
        ids = wanted
    preds = {p: named_files(pred, p) for p in parts}
    if not any(i in preds[p] for p in parts for i in ids):
        raise DataError(pred, None, f"no prediction for any of the {len(ids)} frames (expected <id>_hand.ply / "
                                    f"<id>_obj.ply with ids such as {ids[0]!r})")
    extra = sorted(set().union(*(preds[p] for p in parts)) - set(ids))
    seeds = [seed + k for k in range(repeats)] if protocol == "gsdf" else []
    settings = {"tol_chamfer": tol_chamfer, "tol_f": tol_f, "max_queries": max_queries}
    # a missing prediction is looked for where gSDF looks (and fails): <id>_<part>.ply
    jobs = [(i, {p: (preds[p].get(i, pred / f"{i}_{p}.ply"), files[p][i]) for p in parts}, protocol, seeds, settings)
            for i in ids]
    records = _run_frames(jobs, workers)
    result = {"protocol": protocol, "parts": summarize(records, ids, parts), "samples": len(ids),
              "ignored_predictions": len(extra),
              "settings": {"pred": str(pred), "gt": str(gt), "gt_layout": layout, "parts": list(parts)}}
    if protocol == "gsdf":
        result["settings"].update(seed=seed, points=recon_gsdf.POINTS)
        if repeats > 1:
            per_seed = [summarize(records, ids, parts, k) for k in range(repeats)]
            result["repeats"] = {"seeds": seeds, **{p: _spread(per_seed, p) for p in parts}}
    else:
        result["settings"].update(tolerance_chamfer_cm2=tol_chamfer, tolerance_f=tol_f, max_queries=max_queries)
        result["unconverged"] = sum(not r[p]["exact"]["converged"] for r in records for p in parts if "exact" in r[p])
    result["frames"] = [{"id": i, **{p: _frame_json(r, p) for p in parts}} for i, r in zip(ids, records)]
    return result


def _spread(per_seed: list[dict], part: str) -> dict:
    """Mean, standard deviation (ddof 1), min and max over seeds of each mean (all frames, and survivors)."""
    out = {}
    for key in metric_names(part):
        for label, pick in (("", lambda s: s[part][key]), ("survivor_", lambda s: s[part]["survivor"][key])):
            v = np.array([pick(s) for s in per_seed], dtype=np.float64)
            out[label + key] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)), "min": float(v.min()),
                                "max": float(v.max())}
    return out


def _frame_json(record: dict, part: str) -> dict:
    counted, _, why = _frame_values(record, part, 0)
    out = {k: float(v) for k, v in counted.items()}
    if "exact" in record[part]:
        out["bound"] = {n: float(record[part]["exact"][n][1]) for n in metric_names(part)}
    return {**out, "failure": why} if why else out


def add_arguments(p: argparse.ArgumentParser) -> None:
    """This subcommand's options (``hoisdf score`` adds ``--out`` and ``--debug``)."""
    p.add_argument("--pred", required=True, type=Path, metavar="DIR", help="predicted meshes <id>_hand.ply|obj, "
                   "<id>_obj.ply|obj, metres (gSDF's sdf_mesh/ folder)")
    p.add_argument("--gt", type=Path, metavar="DIR", help="ground-truth meshes, named the same way "
                   "or as gSDF's test export (mesh_hand/<id>.obj, mesh_obj/<id>.obj)")
    p.add_argument("--gt-store", metavar="STORE", help="or: the ground truth posed from a hoidata "
                   "store's labels (frame ids: its frame_id; right hands only; needs --mano for hands)")
    p.add_argument("--mano", type=Path, metavar="DIR", help="MANO folder (MANO_RIGHT.pkl), for --gt-store's hands")
    p.add_argument("--protocol", choices=("gsdf", "exact"), default="gsdf",
                   help="gsdf: gSDF's sampled evaluation, seeded; exact: surface integrals with a bound")
    p.add_argument("--seed", type=non_negative_int, default=0, help="gsdf: seed of the surface samples (default 0)")
    p.add_argument("--repeats", type=positive_int, default=1, metavar="K",
                   help="gsdf: also score with seeds S..S+K-1 and report the spread of the means")
    p.add_argument("--drop-failures", action="store_true",
                   help="headline numbers over the frames that scored only (gSDF's tools/eval.py), labelled so")
    p.add_argument("--parts", default="hand,obj", help="hand, obj or hand,obj (default)")
    p.add_argument("--ids", type=Path, default=None, metavar="FILE", help="score these frame ids (one per line)")
    p.add_argument("--workers", type=non_negative_int, default=1, help="processes (default 1)")
    p.add_argument("--chamfer-tolerance", type=float, default=CHAMFER_TOLERANCE, metavar="CM2",
                   help=f"exact: half-width aimed at per Chamfer, cm^2 (default {CHAMFER_TOLERANCE:g})")
    p.add_argument("--f-tolerance", type=float, default=F_TOLERANCE, metavar="F",
                   help=f"exact: half-width aimed at per F-score (default {F_TOLERANCE:g})")
    p.add_argument("--max-queries", type=positive_int, default=recon_exact.MAX_QUERIES, metavar="N",
                   help="exact: distance queries per direction and part of a frame; past it the bound is wider")


def score(args) -> dict:
    """The subcommand's numbers from parsed options (:func:`score_recon`)."""
    parts = tuple(p.strip() for p in args.parts.split(","))
    if not parts or any(p not in PARTS for p in parts) or len(set(parts)) != len(parts):
        raise DataError(None, "--parts", f"expected hand, obj or hand,obj, got {args.parts!r}")
    if not (args.chamfer_tolerance > 0 and args.f_tolerance > 0):
        raise DataError(None, "--chamfer-tolerance/--f-tolerance", "must be positive")
    if args.protocol == "exact" and args.repeats > 1:
        raise DataError(None, "--repeats", "the exact protocol draws nothing: repeats apply to --protocol gsdf")
    if (args.gt is None) == (args.gt_store is None):
        raise DataError(None, "--gt/--gt-store", "give the ground truth one way: a mesh folder or a store")
    run = lambda gt: score_recon(args.pred, gt, args.protocol, args.seed, args.repeats, parts, args.ids, args.workers,
                                 args.chamfer_tolerance, args.f_tolerance, args.max_queries)
    if args.gt_store is None:
        result = run(args.gt)
    else:
        from hoisdf.scoring.recon_store import write_store_gt

        if not Path(args.pred).is_dir():  # before posing a split's meshes
            raise DataError(args.pred, None, "prediction folder not found")
        with tempfile.TemporaryDirectory(prefix="hoisdf-recon-gt-") as tmp:
            made = write_store_gt(args.gt_store, Path(tmp), parts, args.mano)
            result = run(tmp)
        result["settings"].update(gt=str(args.gt_store), gt_layout="posed from a store", **made)
    result["drop_failures"] = bool(args.drop_failures)
    return result


UNITS = {"chamfer": "cm^2", "chamfer_median": "cm^2"}


def format_result(result: dict) -> str:
    """The printed table: per part, each number over every frame (or the survivors with --drop-failures)."""
    drop, exact = result.get("drop_failures"), result["protocol"] == "exact"
    head = (f"protocol {result['protocol']}" + ("" if exact else f" (seed {result['settings']['seed']}, "
            f"{recon_gsdf.POINTS} points per mesh)") + f", {result['samples']} frames")
    lines = [head]
    for part, p in result["parts"].items():
        label = (f"survivor mean over {p['survivor']['frames']} frames: FAILURES DROPPED, as gSDF's tools/eval.py"
                 if drop else "mean over every frame, failures penalised (F 0, centroid-point Chamfer)")
        first = f" (first: {p['failed'][0]['id']}: {p['failed'][0]['why']})" if p["failed"] else ""
        lines.append(f"  {part}: {p['failures']} of {p['frames']} predictions failed{first}; {label}")
        values = p["survivor"] if drop else p
        for name in [*metric_names(part), "chamfer_median"]:
            text = f"{values[name]:.6f}"
            if exact and name in p.get("bound", {}):
                text += f"  +- {p['bound'][name]:.1e} (mean bound)"
            lines.append(f"    {name:<16}{text} {UNITS.get(name, '')}".rstrip())
        spread = result.get("repeats", {}).get(part)
        if spread:
            key = "survivor_" if drop else ""
            lines.append(f"    over {len(result['repeats']['seeds'])} seeds (std, min..max): " + "; ".join(
                f"{n} {spread[key + n]['std']:.2e}, {spread[key + n]['min']:.6f}..{spread[key + n]['max']:.6f}"
                for n in metric_names(part)))
    if result["settings"].get("mirrored_left_out"):
        lines.append(f"  {result['settings']['mirrored_left_out']} mirrored (left-hand) records of the store left out")
    if result.get("ignored_predictions"):
        lines.append(f"  {result['ignored_predictions']} predicted frames are not in the ground truth: ignored")
    if exact and result.get("unconverged"):
        lines.append(f"  {result['unconverged']} part-frames ran out of --max-queries: their bounds are wider")
    return "\n".join(lines)
