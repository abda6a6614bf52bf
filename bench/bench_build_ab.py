"""One-worker build-sdf throughput of two source trees side by side: this checkout against another one.

Usage: python -m bench.bench_build_ab --baseline DIR [--frames 240] [--rounds 3] [--root DATA]

DIR is another checkout of the project (``git worktree add /tmp/base <commit>``). Writes a toy DexYCB once
(with this checkout's writer, unless --root is given), then alternates the two trees over --rounds rounds (this
one first in even rounds, the baseline first in odd ones): each round runs, per tree, a fresh Python process
with that tree first on the path, which builds the frames once untimed (imports, numba kernels, GL set-up) and then once timed with 1 worker (default settings of
``pipelines/toy.toml``, train and val frames, 8 records per shard). Reports the medians, every run, the
ratio per round, the CPU time per frame of the timed build (``time.process_time`` of the child: its own threads
included, the waiting on other jobs excluded, so it moves less with the machine's load than the wall time), and
whether the two trees wrote byte-identical shards.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.common import toy_root

HERE = Path(__file__).resolve().parent
CHILD = """
import json, shutil, sys, time
from pathlib import Path
try:
    from hoidata.build_sdf import build_store
    from hoidata.records import load_build_config
except ImportError:  # a tree from before the build had its engine and records floors (issue 34)
    from hoidata.pipeline.runner import build_store
    from hoidata.pipeline.settings import load_build_config
root, out = Path(sys.argv[1]), Path(sys.argv[2])
cfg = load_build_config("toy", ['dataset.splits=["train", "val"]', "store.records_per_shard=8"])
build_store(cfg, root, root / "mano", root / "models", out / "warm-up", workers=1, progress=False)
start, cpu = time.perf_counter(), time.process_time()
summary = build_store(cfg, root, root / "mano", root / "models", out / "store", workers=1, progress=False)
print(json.dumps({"seconds": time.perf_counter() - start, "cpu": time.process_time() - cpu,
                  "records": summary.written if hasattr(summary, "written") else summary.records}))
"""


def run_tree(tree: Path, root: Path, out: Path) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=str(tree), PYOPENGL_PLATFORM="egl")
    done = subprocess.run([sys.executable, "-c", CHILD, str(root), str(out)], cwd=tree, env=env, check=True,
                          capture_output=True, text=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["shards"] = {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
                        for p in sorted((out / "store").glob("shard-*.tar"))}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, help="another checkout of the project")
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--root", default=None)
    args = parser.parse_args()
    trees = {"this": HERE.parent, "baseline": Path(args.baseline).resolve()}
    work = Path(tempfile.mkdtemp(prefix="bench_build_ab_"))
    try:
        if args.root:
            root = Path(args.root)
        else:
            root = toy_root(args.frames, work)
        runs = {name: [] for name in trees}
        for r in range(args.rounds):  # the order alternates, so a trend in the load favours neither tree
            for name, tree in (list(trees.items()) if r % 2 == 0 else list(trees.items())[::-1]):
                runs[name].append(run_tree(tree, root, work / name))
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"1 worker, median of {args.rounds} interleaved rounds; load average after the runs {load} (1, 5, 15 min)")
        print(f"{'tree':>9} {'records':>8} {'seconds':>8} {'frames/s':>9} {'CPU ms/frame':>13} {'CPU frames/s':>13}  runs (s)")
        for name, results in runs.items():
            t = float(np.median([r["seconds"] for r in results]))
            cpu = float(np.median([r["cpu"] for r in results])) / results[0]["records"]
            print(f"{name:>9} {results[0]['records']:>8} {t:>8.2f} {results[0]['records'] / t:>9.2f} "
                  f"{1e3 * cpu:>13.1f} {1 / cpu:>13.1f}  " + " ".join(f"{r['seconds']:.2f}" for r in results))
        ratios = [b["seconds"] / a["seconds"] for a, b in zip(runs["this"], runs["baseline"])]
        print("this / baseline frames/s per round: " + " ".join(f"{x:.2f}" for x in ratios)
              + f" (median {np.median(ratios):.2f})")
        same = all(r["shards"] == runs["this"][0]["shards"] for rs in runs.values() for r in rs)
        print(f"shards byte-identical across trees and rounds: {same} ({len(runs['this'][0]['shards'])} shards)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
