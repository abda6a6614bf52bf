"""How each stage's cost grows: a table, log-log slopes and a PNG plot, in one run.

Series (each point timed ``--rounds`` times, the least CPU time of this thread or process kept: the work, less what
other jobs on a shared machine add; the loader's samples/s are wall-clock, its workers being other processes):

- SDF against query points: ``compute_sdf_samples`` (hand and object, build-sdf's call) on one toy frame
  (``bench_sdf``'s first: the closed toy MANO hand and a toy object) for ``--points`` points from
  ``sample_query_points`` (hand, object and uniform sets in the build's proportions);
- SDF against mesh faces: ``signed_distance`` (winding-number sign, the hand's path) of 6,144 near-surface points to
  a closed bumpy sphere of ``--faces`` faces (icosphere subdivisions, radius 5 cm +- 15 %), the tree shape kept
  (a later frame's cost), and the first call's tree build apart;
- build time and store bytes against frames: ``build_store`` with one worker on toy DexYCB trees of ``--frames``
  frames (every split; after one untimed build of 12, so start-up is not counted), and the bytes of its store;
- loader samples/s against workers: ``make_loader(build_dataset(...))`` over the largest store (batch 8), at
  ``--workers``;
- exact recon time against mesh size: ``pair_scores`` at tolerance 0.01 of a perturbed icosphere (radius 3 cm,
  shifted 2 mm, 0.3 mm vertex noise) against it, ``--recon-faces`` faces.

Each series' slope is the least-squares fit of log(cost) on log(size); a cost series whose slope is above
``LINEAR`` (a rate's below 1 / LINEAR) is named as worse than linear (bench/README.md explains each).

Run: ``python -m bench.bench_scaling [--out FOLDER]`` (writes ``scaling.png`` and ``scaling.md`` there; 30 minutes on
2 busy cores at the defaults, most of it writing the 4,800-frame toy tree).
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

LINEAR = 1.1  # a slope above this is worse than linear


def least_time(fn, rounds: int, clock=time.thread_time) -> float:
    """The least of ``rounds`` timings of fn() in seconds (``clock``: this thread's CPU time unless told)."""
    best = np.inf
    for _ in range(rounds):
        start = clock()
        fn()
        best = min(best, clock() - start)
    return best


def sdf_points(counts, rounds: int) -> list[float]:
    from bench.common import sdf_toy_frames
    from hoidata.geometry.sampling import compute_sdf_samples, sample_query_points

    with tempfile.TemporaryDirectory() as workdir:
        f = sdf_toy_frames(workdir, 1)[0]
    out = []
    for n in counts:
        n_hand = int(round(n * 2 / 3))
        points, _ = sample_query_points(f["hand"], f["hand_faces"], f["obj"], f["obj_faces"], f["root"],
                                        np.random.default_rng(0), n_hand, n - n_hand)
        call = lambda p=points: compute_sdf_samples(p, f["hand"], f["hand_faces"], f["parts"], f["obj"],
                                                    f["obj_faces"], f["watertight"])
        call()
        out.append(least_time(call, rounds))
    return out


def bumpy_sphere(faces: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed icosphere with at least ``faces`` faces (20 4^k), radius 5 cm modulated by +- 15 %, metres."""
    import trimesh

    k = int(np.ceil(np.log(faces / 20) / np.log(4)))
    m = trimesh.creation.icosphere(k, 1.0)
    v = np.asarray(m.vertices)
    r = 0.05 * (1 + 0.15 * np.sin(5 * v[:, 0]) * np.sin(4 * v[:, 1] + 1) * np.cos(3 * v[:, 2]))
    return v * r[:, None], np.asarray(m.faces)


def sdf_faces(counts, rounds: int) -> tuple[list[int], list[float], list[float]]:
    """(faces, seconds per query set with the tree shape kept, seconds of the first call: the tree built)."""
    from hoidata.geometry import bvh
    from hoidata.geometry.sampling import sample_query_points
    from hoidata.geometry.sdf import signed_distance

    sizes, steady, first = [], [], []
    for n in counts:
        v, f = bumpy_sphere(n)
        points, _ = sample_query_points(v, f, v, f, v.mean(0), np.random.default_rng(1), 4096, 2048, cube=0.2)
        bvh._TOPOLOGIES.clear()
        first.append(least_time(lambda: signed_distance(points, v, f, watertight=False), 1))
        steady.append(least_time(lambda: signed_distance(points, v, f, watertight=False), rounds))
        sizes.append(len(f))
        bvh._TOPOLOGIES.clear()
    return sizes, steady, first


def builds(counts, work: Path) -> tuple[list[int], list[float], list[float], Path]:
    """(records, CPU seconds of one-worker builds, store bytes, the largest store)."""
    from bench.common import toy_root
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    records, seconds, sizes, store = [], [], [], None
    cfg = load_build_config("toy", ["store.records_per_shard=64"])
    warm = toy_root(12, work / "warm")  # untimed: imports, numba kernels, the renderer's start-up, as in bench_build
    build_store(cfg, warm, warm / "mano", warm / "models", work / "warm_store", workers=1, progress=False)
    shutil.rmtree(work / "warm")
    shutil.rmtree(work / "warm_store")
    for n in counts:
        root = toy_root(n, work / f"toy{n}")
        out = work / f"store{n}"
        start = time.process_time()
        summary = build_store(cfg, root, root / "mano", root / "models", out, workers=1, progress=False)
        seconds.append(time.process_time() - start)
        records.append(summary.written)
        sizes.append(sum(p.stat().st_size for p in out.rglob("*") if p.is_file()))
        shutil.rmtree(root)
        if store is not None:
            shutil.rmtree(store)
        store = out
    return records, seconds, sizes, store


def loader_rates(store: Path, workers, batches: int = 20) -> list[float]:
    """Samples/s of the training loader over ``batches`` batches of 8 after an untimed first (start-up excluded)."""
    from hoisdf.data import StoreSpec, build_dataset, make_loader

    out = []
    for w in workers:
        data = build_dataset([StoreSpec(store)], 8, 8 * (batches + 1) * 4, 0, 600, 200, 0.05, 64, training=True)
        it = iter(make_loader(data, w))
        next(it)
        start, n = time.perf_counter(), 0
        for _ in range(batches):
            n += len(next(it)["key"])
        out.append(n / (time.perf_counter() - start))
        del it
    return out


def recon_sizes(counts, rounds: int) -> tuple[list[int], list[float]]:
    import trimesh

    from hoisdf.scoring import recon_exact

    sizes, seconds = [], []
    for n in counts:
        k = int(np.ceil(np.log(n / 20) / np.log(4)))
        m = trimesh.creation.icosphere(k, 3.0)
        gt, f = np.asarray(m.vertices), np.asarray(m.faces)
        rng = np.random.default_rng(k)
        pred = gt + [0.2, 0.0, 0.0] + rng.normal(scale=0.03, size=gt.shape)
        call = lambda: recon_exact.pair_scores((pred, f), (gt, f), [0.1, 0.5], ["f_1mm", "f_5mm"], 0.01, 0.01)
        call()
        sizes.append(len(f))
        seconds.append(least_time(call, rounds, time.process_time))
    return sizes, seconds


def slope(x, y) -> float:
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def plot(series: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 4, figsize=(18, 8))
    for ax, s in zip(axes.flat, series):
        ax.loglog(s["x"], s["y"], "o-")
        ax.set_title(f"{s['name']}: slope {s['slope']:.2f}", fontsize=9)
        ax.set_xlabel(s["x_label"])
        ax.set_ylabel(s["y_label"])
        ax.grid(True, which="both", alpha=0.3)
    for ax in list(axes.flat)[len(series):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def table(series: list[dict], header: str) -> str:
    lines = [header, "", "| series | size | cost | log-log slope | reading |", "|---|---|---|---|---|"]
    for s in series:
        worse = s["slope"] > LINEAR if s["kind"] == "cost" else s["slope"] < 1 / LINEAR
        reading = ("worse than linear" if worse else "linear or better") if s["kind"] == "cost" else (
            "below linear (more processes than the growth shows)" if worse else "linear")
        sizes = ", ".join(f"{x:g}" for x in s["x"])
        costs = ", ".join(f"{y:.3g}" for y in s["y"])
        lines.append(f"| {s['name']} | {s['x_label']}: {sizes} | {s['y_label']}: {costs} | {s['slope']:.2f} | "
                     f"{reading} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("bench_scaling"), help="folder for scaling.png and scaling.md")
    p.add_argument("--points", type=int, nargs="+", default=[1000, 4000, 16000, 64000])
    p.add_argument("--faces", type=int, nargs="+", default=[1280, 5120, 20480, 81920])
    p.add_argument("--frames", type=int, nargs="+", default=[48, 480, 4800])
    p.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--recon-faces", type=int, nargs="+", default=[320, 1280, 5120, 20480])
    p.add_argument("--rounds", type=int, default=3)
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    series = []

    def add(name, kind, x_label, y_label, x, y):
        series.append(dict(name=name, kind=kind, x_label=x_label, y_label=y_label, x=list(x), y=list(y),
                           slope=slope(x, y)))
        print(f"{name}: {', '.join(f'{a:g} -> {b:.3g}' for a, b in zip(x, y))}; slope {series[-1]['slope']:.2f}",
              flush=True)

    add("SDF vs query points", "cost", "points", "s", args.points, sdf_points(args.points, args.rounds))
    faces, steady, first = sdf_faces(args.faces, args.rounds)
    add("SDF vs mesh faces (tree kept)", "cost", "faces", "s", faces, steady)
    add("SDF tree build vs mesh faces", "cost", "faces", "s", faces, first)
    sizes, seconds = recon_sizes(args.recon_faces, max(1, args.rounds - 2))
    add("exact recon vs mesh faces", "cost", "faces", "s", sizes, seconds)
    work = Path(tempfile.mkdtemp(prefix="bench_scaling_"))
    try:
        records, build_s, store_bytes, store = builds(args.frames, work)
        add("build (1 worker) vs frames", "cost", "records", "CPU s", records, build_s)
        add("store bytes vs frames", "cost", "records", "bytes", records, store_bytes)
        rates = loader_rates(store, args.workers)
        add("loader vs processes", "rate", "1 + workers", "samples/s", [1 + w for w in args.workers], rates)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    header = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; load average "
              f"{load_before[0]:.2f} before, {os.getloadavg()[0]:.2f} after (1 min)")
    text = table(series, header)
    plot(series, args.out / "scaling.png")
    (args.out / "scaling.md").write_text(text + "\n")
    print(text)
    worse = [s["name"] for s in series if (s["slope"] > LINEAR if s["kind"] == "cost" else s["slope"] < 1 / LINEAR)]
    print("worse than linear: " + (", ".join(worse) if worse else "none"))
    print(f"wrote {args.out / 'scaling.png'} and {args.out / 'scaling.md'}")


if __name__ == "__main__":
    main()
