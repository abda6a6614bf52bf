"""Cluster engines and remote stores, side by side in one run: what they cost over the local tools.

Usage: python -m bench.bench_cluster [--frames 192] [--records-per-shard 8] [--rounds 3] [--passes 3] [--json out.json]
       [--root DIR]  (an existing toy DexYCB with its mano and models folders, instead of writing one)

1. build-sdf wall time on the same toy DexYCB frames (default record settings) with
   - the local pool (``--workers 2``),
   - submitit's local executor (``--launcher slurm --slurm-executor local``: 2 array tasks of 1 worker each, each
     a fresh process that unpickles the job),
   - Ray (``--launcher ray``, a local instance of 2 CPUs): once including ``ray.init``, once on a running instance;
   every store checked byte-identical to the local one. Overhead per shard job = (engine - local) / shards.
2. Loader samples/s over one store, read from its folder and from a loopback HTTP server (``python -m
   http.server`` in its own process, 127.0.0.1), alternating for ``--rounds`` rounds (evaluation order, ``--passes``
   passes each, default 3, batch 8), with 0 and 2 loader workers.
3. The fixed cost every part pays before its first shard: reading the frame list (``read_frames``) and the input
   fingerprints (``build_inputs``), per frame, twice (the second with a warm page cache).
The machine's load average is printed before and after.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import toy_root
from hoidata.engine.ray_tasks import run_ray
from hoidata.build_sdf import build_inputs, build_store, read_frames
from hoidata.records.settings import load_build_config
from hoidata.engine.slurm import SlurmOptions, submit_parts
from hoisdf.data import StoreSpec, build_dataset, make_loader


def shard_bytes(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.glob("shard-*.tar"))}


def build_rows(root: Path, work: Path, per: int) -> list[dict]:
    import ray

    cfg = load_build_config("toy", ['dataset.splits=["train", "val"]', f"store.records_per_shard={per}"])
    task = functools.partial(build_store, cfg, root, root / "mano", root / "models")

    def timed(name, run):
        out = work / name.replace(" ", "_")
        start = time.perf_counter()
        summary = run(out)
        return {"engine": name, "seconds": time.perf_counter() - start, "records": summary.written,
                "shards": summary.units_written, "out": out}

    rows = [timed("local pool", lambda out: task(out, workers=2, progress=False))]

    def slurm_local(out):
        results = submit_parts(functools.partial(task, out), SlurmOptions(2, 1, 30, executor="local"), out, "bench")
        return type("S", (), {"written": sum(r.written for r in results),
                              "units_written": sum(r.units_written for r in results)})()

    rows.append(timed("submitit local", slurm_local))
    rows.append(timed("ray (with init)", lambda out: task(out, workers=2, progress=False,
                                                         executor=functools.partial(run_ray, address=None))))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        rows.append(timed("ray (running)", lambda out: task(out, workers=2, progress=False, executor=run_ray)))
    finally:
        ray.shutdown()
    reference = shard_bytes(rows[0]["out"])
    for row in rows:
        row["identical"] = shard_bytes(row["out"]) == reference
    return rows


def reading_cost(root: Path) -> list[tuple[int, float, float]]:
    """(frames, ms per frame reading the frame list, ms per frame fingerprinting the inputs), twice."""
    cfg = load_build_config("toy", ['dataset.splits=["train", "val"]'])
    rows = []
    for _ in range(2):
        start = time.perf_counter()
        frames, _ = read_frames(cfg, root, root / "mano")
        middle = time.perf_counter()
        build_inputs(frames, root, root / "mano", root / "models")
        end = time.perf_counter()
        rows.append((len(frames), 1e3 * (middle - start) / len(frames), 1e3 * (end - middle) / len(frames)))
    return rows


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def samples_per_second(location, workers: int, passes: int) -> tuple[float, int]:
    """Samples per second of ``passes`` passes over a store (the index read and shard sizes asked once)."""
    data = build_dataset([StoreSpec(location)], 8, n_hand=600, n_object=200, training=False)
    start, n = time.perf_counter(), 0
    for _ in range(passes):
        for batch in make_loader(data, workers):
            n += len(batch["key"])
    return n / (time.perf_counter() - start), n


def loader_rows(folder: Path, rounds: int, passes: int = 3) -> list[dict]:
    port = free_port()
    server = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1", "--directory",
                               str(folder.parent)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}/{folder.name}"
    try:
        for _ in range(100):  # wait until it answers
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.1)
        results = {}
        for _ in range(rounds):
            for workers in (0, 2):
                for name, location in (("folder", folder), ("http", url)):
                    rate, n = samples_per_second(location, workers, passes)
                    results.setdefault((name, workers), []).append(rate)
        return [{"source": name, "workers": w, "samples": n, "median samples/s": sorted(r)[len(r) // 2],
                 "all": [round(x, 1) for x in r]} for (name, w), r in results.items()]
    finally:
        server.terminate()
        server.wait(10)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=192)
    parser.add_argument("--records-per-shard", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--passes", type=int, default=3, help="passes over the store per loader measurement")
    parser.add_argument("--json", default=None)
    parser.add_argument("--root", type=Path, default=None, help="an existing toy DexYCB (default: write one)")
    args = parser.parse_args()
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    work = Path(tempfile.mkdtemp(prefix="bench_cluster_"))
    try:
        load = [os.getloadavg()[0]]
        root = args.root or toy_root(args.frames, work)
        builds = build_rows(root, work, args.records_per_shard)
        load.append(os.getloadavg()[0])
        base = builds[0]
        print(f"build-sdf, {base['records']} toy frames, {base['shards']} shards of {args.records_per_shard}, "
              f"2 CPUs per engine")
        print(f"{'engine':<16} {'seconds':>8} {'frames/s':>9} {'per core':>9} {'extra s':>8} {'per shard':>9} "
              "identical")
        for row in builds:
            extra = row["seconds"] - base["seconds"]
            print(f"{row['engine']:<16} {row['seconds']:>8.1f} {row['records'] / row['seconds']:>9.2f} "
                  f"{row['records'] / row['seconds'] / 2:>9.2f} {extra:>8.1f} {extra / base['shards']:>9.2f} "
                  f"{row['identical']}")
        loads = loader_rows(builds[0]["out"], args.rounds, args.passes)
        load.append(os.getloadavg()[0])
        print(f"\nloader, {args.passes} passes in evaluation order, batch 8, {args.rounds} alternating rounds (median)")
        print(f"{'source':<7} {'workers':>7} {'samples':>8} {'samples/s':>10}  all rounds")
        for row in loads:
            print(f"{row['source']:<7} {row['workers']:>7} {row['samples']:>8} {row['median samples/s']:>10.1f}  "
                  f"{row['all']}")
        reading = reading_cost(root)
        print("\nper part, before its first shard: " + "; ".join(
            f"{n} frames: read {r:.2f} ms/frame, fingerprint {f:.2f} ms/frame" for n, r, f in reading))
        print(f"\nload average (1 min): {', '.join(f'{x:.2f}' for x in load)} (start, after builds, after loader)")
        if args.json:
            rows = [{k: v for k, v in r.items() if k != "out"} for r in builds]
            Path(args.json).write_text(json.dumps({"builds": rows, "loader": loads, "reading": reading, "load": load},
                                                  indent=2))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
