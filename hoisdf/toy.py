"""``python -m hoisdf.toy --out toy_run``: the main job on the embedded toy data, end to end.

1. ``python -m hoidata toy-pipeline`` (a child process): procedural MANO, objects and toy DexYCB / HO-3D;
   verified train and test stores;
2. ``python -m hoisdf.train --config toy`` on the train store (a small model, CPU minutes);
3. ``python -m hoisdf.evaluate`` on the test store, against a mean-pose baseline from the train store;
4. a report folder: metrics.json, training_curve.png, result pictures, and a verdict line.

``--ablation NAME`` (sampling, feature_augmentation, cross_field, pose_regressor) replaces steps 2-4 by one
of the paper's ablation tables on the same stores: every variant trained ``--steps`` steps from the same seed,
evaluated on the test store, and ``OUT/ablation-NAME/`` with table.md, table.json and ablation.png
(:mod:`hoisdf.ablation`).

Every step resumes: data and stores that exist are kept, a finished training run is not repeated.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import hoidata
from hoidata.atomic import write_atomic
from hoidata.cli_types import ArgumentParser, local_path, non_negative_int, positive_int
from hoidata.errors import run_cli
from hoisdf.ablation import TABLES, markdown_table, run_table
from hoisdf.evaluate import evaluate
from hoisdf.evaluation.visualize import plot_training_curve
from hoisdf.train import main as train_main
from hoisdf.training.checkpoint import CHECKPOINTS, LAST

COMPARED = ("rr_mje", "pa_mje", "oce", "add_s")  # the verdict: the model must beat the baseline on these


def beats_baseline(model: dict, baseline: dict, names=COMPARED) -> dict[str, bool]:
    """Per metric (lower is better): model < baseline; metrics missing on either side are left out."""
    return {n: model[n] < baseline[n] for n in names if n in model and n in baseline}


def data_command(out: Path, workers: int, seed: int, sequences: int | None, frames: int | None,
                 debug: bool = False) -> list[str]:
    """Step 1 as a command line: ``python -m hoidata toy-pipeline`` into ``out`` (data/, store/, store_grid.png)
    with ``workers`` build processes, the toy ``seed`` and size (None: make-toy's default); ``debug``: a traceback
    instead of the one error line."""
    argv = [sys.executable, "-m", "hoidata", "toy-pipeline", "--out", str(out), "--workers", str(workers),
            "--seed", str(seed)]
    argv += [*(["--sequences", str(sequences)] if sequences else []), *(["--frames", str(frames)] if frames else [])]
    return argv + (["--debug"] if debug else [])


def run_data(argv: list[str]) -> int:
    """Run a ``hoidata`` command line in a child process and return its exit code.

    A child, not an import of ``hoidata.cli``: the model package stands beside the build, on hoidata's library
    layers only (tests/test_layout.py). The child's output streams through as it comes, and its error is its own
    one ``hoidata ...: error:`` line (exit 2); it imports the same ``hoidata`` as this process."""
    sys.stdout.flush()
    sys.stderr.flush()
    here = str(Path(hoidata.__file__).resolve().parents[1])  # the folder holding this process's hoidata
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p)}
    code = subprocess.run(argv, env=env, check=False).returncode
    if code < 0:  # killed by a signal: it printed nothing, so say it here
        name = signal.Signals(-code).name if -code in signal.valid_signals() else f"signal {-code}"
        print(f"error: {' '.join(argv[2:4])} was stopped by {name}", file=sys.stderr)
        return 128 - code
    return code


def run(out: Path, steps: int, workers: int, seed: int, sequences: int | None, frames: int | None,
        vis: int, extra: list[str], ablation: str | None = None, debug: bool = False) -> int:
    out = Path(out)
    t0 = time.perf_counter()
    argv = data_command(out, workers, seed, sequences, frames, debug)
    print(f"$ python -m hoidata {' '.join(argv[3:])}", flush=True)
    status = run_data(argv)
    if status:
        return status
    mano = out / "data" / "dexycb" / "mano"
    train_store, test_store, run_dir = out / "store" / "train", out / "store" / "test", out / "run"
    t_data = time.perf_counter() - t0
    if ablation:
        summary = run_table(ablation, train_store, test_store, mano, out / f"ablation-{ablation}", steps, seed, extra)
        print(f"\n{markdown_table(summary)}")  # what table.md holds
        print(f"wrote {out / f'ablation-{ablation}'}: table.md, table.json, ablation.png; training seconds "
              f"{summary['train_seconds']}, total {time.perf_counter() - t0:.0f} s")
        return 0
    if not (run_dir / CHECKPOINTS / LAST).is_file():
        argv = ["--shards", str(train_store), "--mano", str(mano), "--config", "toy", "--out", str(run_dir),
                f"train.max_steps={steps}", f"train.seed={seed}", *extra]
        print(f"\n$ python -m hoisdf.train {' '.join(argv)}", flush=True)
        status = train_main(argv)
        if status:
            return status
    t_train = time.perf_counter() - t0 - t_data
    report = out / "report"
    print(f"\n$ python -m hoisdf.evaluate --ckpt {run_dir} --shards {test_store} --mano {mano} --out {report} "
          f"--vis {vis} --baseline-store {train_store}", flush=True)
    result = evaluate(run_dir, [test_store], mano, report, vis=vis, baseline_store=train_store)
    plot_training_curve(run_dir / "metrics.csv", report / "training_curve.png")
    shutil.copy(out / "store_grid.png", report / "store_grid.png")
    print(result["table"])
    model, baseline = result["overall"], result["baseline"]["overall"]
    verdict = beats_baseline(model, baseline)
    timing = {"data_s": round(t_data, 1), "train_s": round(t_train, 1),
              "evaluate_s": round(time.perf_counter() - t0 - t_data - t_train, 1),
              "total_s": round(time.perf_counter() - t0, 1)}
    summary = {"beats_mean_pose_baseline": verdict, "timing": timing, "train_steps": steps,
               "model": {k: model[k] for k in COMPARED if k in model},
               "baseline": {k: baseline[k] for k in COMPARED if k in baseline}}
    write_atomic(report / "summary.json", json.dumps(summary, indent=2).encode())
    print(f"\nreport: {report}  (metrics.json, per_object.csv, training_curve.png, vis/, summary.json)")
    print("model vs mean-pose baseline (mm): " + ", ".join(
        f"{k} {model[k]:.1f} vs {baseline[k]:.1f} {'better' if v else 'NOT better'}" for k, v in verdict.items()))
    print(f"time: data {timing['data_s']} s, training {timing['train_s']} s, evaluation {timing['evaluate_s']} s, "
          f"total {timing['total_s']} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m hoisdf.toy", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=local_path, default=Path("toy_run"), help="output folder")
    p.add_argument("--steps", type=positive_int, default=700, help="training steps (batch 8)")
    p.add_argument("--workers", type=positive_int, default=2, help="worker processes for the data build")
    p.add_argument("--seed", type=non_negative_int, default=0)
    # twice make-toy's default sequences at half its frames: the same 600 DexYCB images with twice the grasps,
    # which the object's depth needs to generalise (README, "The main job")
    p.add_argument("--sequences", type=positive_int, default=10, help="toy size: sequences per subject, 5 or more (see hoidata make-toy)")
    p.add_argument("--frames", type=positive_int, default=5, help="toy size: frames per sequence and camera")
    p.add_argument("--vis", type=non_negative_int, default=8, help="result pictures to write")
    p.add_argument("--ablation", choices=sorted(TABLES), default=None,
                   help="train and compare the variants of one of the paper's ablation tables instead")
    p.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    p.add_argument("overrides", nargs="*", metavar="section.key=value", help="training overrides")
    args = p.parse_intermixed_args(argv)  # overrides before and after other options
    return run_cli("", lambda: run(args.out, args.steps, args.workers, args.seed, args.sequences, args.frames,
                                   args.vis, args.overrides, args.ablation, args.debug), args.debug)


if __name__ == "__main__":
    sys.exit(main())
