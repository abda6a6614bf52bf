"""Benchmark of the ``hoidata build-sdf`` SDF stage against its previous path and trimesh, on toy frames.

Each frame: the closed toy MANO hand (float64) in one pose (finger curl times the toy grasp mean,
random global rotation, 0.55 m from the camera) and one toy object (repaired, randomly rotated,
centred 5 cm from the hand centroid); 6144 query points from ``sample_query_points``. On the
same points and meshes, side by side, it times

- ``compute_sdf_samples`` as build-sdf calls it: the ``bvh`` backend (hand sign: winding number);
- the baseline, the same call with ``backend="igl"`` (the libigl path build-sdf used before);
- ``trimesh.proximity.signed_distance`` for the hand and the object (fresh Trimesh objects per
  call, as for a new frame; trimesh's sign is positive inside, so it is negated);
- open3d's ``RaycastingScene.compute_signed_distance`` (the ``bench`` extra: ``pip install 'hoisdf[bench]'``;
  the column reads "not installed" without it): a fresh scene per mesh per call, as for a new frame, built and
  queried with one thread (``nthreads=1``); float32 points, sign by ray parity (negative inside).

The methods run interleaved, frame by frame, in ``--rounds`` rounds (after one warm-up of each,
which also builds the kept tree shapes, as a build worker's first frames do), so load from other
jobs hits all of them alike; it reports per-frame medians, the speed-ups, and the spread of the
whole-set speed-up over the rounds. Everything runs on one core (numba and libigl single-threaded
here; trimesh is; open3d is told to). Checks on every frame: max |bvh - igl| and |bvh - brute force| on
distances, and for every method the points whose sign differs from the brute-force reference
(:func:`hoidata.geometry.sdf.brute_force_signed_distance`: exact distance, winding-number sign) on every point.

Run: ``python -m bench.bench_sdf`` (about 1-2 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np
import trimesh

from bench.common import sdf_toy_frames as toy_frames
from hoidata.geometry.sampling import compute_sdf_samples, sample_query_points
from hoidata.geometry.sdf import brute_force_signed_distance

LEGEND = """bvh: compute_sdf_samples (backend 'bvh', hand sign by winding number); igl: the same call with
backend='igl' (the previous path, the baseline); trimesh: trimesh.proximity.signed_distance, hand and object;
open3d: RaycastingScene.compute_signed_distance, one scene per mesh, nthreads=1.
x: trimesh / bvh, x-igl: trimesh / igl, bvh/igl: igl / bvh, o3d/bvh: open3d / bvh (time ratios of
per-frame medians). |bvh-igl|, |bvh-ref|: max distance difference in metres to the baseline (all points) and
to the brute-force reference (every 4th point), both meshes. sign errors: points whose sign differs from the
brute-force reference's (every point), per method in the order bvh igl trimesh open3d, as hand+object."""


def sdf_samples(frame: dict, points: np.ndarray, backend: str) -> tuple[np.ndarray, np.ndarray]:
    """compute_sdf_samples as build-sdf calls it (default settings), with the given backend."""
    sdf_hand, sdf_obj, _ = compute_sdf_samples(points, frame["hand"], frame["hand_faces"], frame["parts"],
                                               frame["obj"], frame["obj_faces"], frame["watertight"],
                                               backend=backend)
    return sdf_hand, sdf_obj


def with_trimesh(frame: dict, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # trimesh caches its BVH on the mesh object; a new frame has new meshes, so build them here.
    hand = trimesh.Trimesh(frame["hand"], frame["hand_faces"], process=False)
    obj = trimesh.Trimesh(frame["obj"], frame["obj_faces"], process=False)
    return -trimesh.proximity.signed_distance(hand, points), -trimesh.proximity.signed_distance(obj, points)


def open3d_module():
    """open3d, or None when it is not installed (a benchmark-only dependency: the ``bench`` extra)."""
    try:
        import open3d
    except ImportError:
        return None
    return open3d


def with_open3d(o3d, frame: dict, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """open3d's signed distances to the hand and the object: a fresh scene per mesh (a new frame), one thread."""
    query = o3d.core.Tensor(np.asarray(points, dtype=np.float32))
    out = []
    for v, f in ((frame["hand"], frame["hand_faces"]), (frame["obj"], frame["obj_faces"])):
        scene = o3d.t.geometry.RaycastingScene(nthreads=1)
        scene.add_triangles(o3d.core.Tensor(np.asarray(v, dtype=np.float32)),
                            o3d.core.Tensor(np.asarray(f, dtype=np.uint32)))
        out.append(scene.compute_signed_distance(query, nthreads=1).numpy().astype(np.float64))
    return out[0], out[1]


def timed(fn) -> tuple[object, float, float]:
    """(result, wall time in ms, CPU time of this process in ms) of one call."""
    start, cpu = time.perf_counter(), time.process_time()
    result = fn()
    return result, 1e3 * (time.perf_counter() - start), 1e3 * (time.process_time() - cpu)


METHODS = ("bvh", "igl", "trimesh", "open3d")


def run_method(name: str, frame: dict, points: np.ndarray, o3d=None):
    if name == "trimesh":
        return with_trimesh(frame, points)
    return with_open3d(o3d, frame, points) if name == "open3d" else sdf_samples(frame, points, name)


def checks(frame: dict, points: np.ndarray, results: dict) -> dict:
    """Distance differences of bvh and every method's sign errors against the brute-force reference (LEGEND)."""
    meshes = ((frame["hand"], frame["hand_faces"]), (frame["obj"], frame["obj_faces"]))
    gap_igl = max(float(np.abs(b - i).max()) for b, i in zip(results["bvh"], results["igl"]))
    refs = [brute_force_signed_distance(points, v, f)[0] for v, f in meshes]
    gap_ref = max(float(np.abs(got[::4] - ref[::4]).max()) for got, ref in zip(results["bvh"], refs))
    errors = {name: [int(np.sum((got < 0) != (ref < 0))) for got, ref in zip(results[name], refs)]
              for name in results}
    return {"gap_igl": gap_igl, "gap_ref": gap_ref, "errors": errors}


def error_cell(errors: dict, methods) -> str:
    return " ".join(f"{errors[m][0]}+{errors[m][1]}" if m in errors else "-" for m in methods)


def spread(values) -> str:
    return f"{np.median(values):.0f} ({np.min(values):.0f}-{np.max(values):.0f})"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timed rounds over all frames")
    parser.add_argument("--n-hand", type=int, default=4096)
    parser.add_argument("--n-object", type=int, default=2048)
    args = parser.parse_args(argv)
    o3d = open3d_module()
    methods = METHODS if o3d is not None else METHODS[:-1]
    with tempfile.TemporaryDirectory() as workdir:
        frames = toy_frames(workdir, args.frames)
    clouds = [sample_query_points(f["hand"], f["hand_faces"], f["obj"], f["obj_faces"], f["root"],
                                  np.random.default_rng(k), args.n_hand, args.n_object)[0]
              for k, f in enumerate(frames)]
    for frame, points in zip(frames, clouds, strict=True):  # warm-up: compile, kept tree shapes
        for name in methods:
            run_method(name, frame, points, o3d)
    times = {name: np.zeros((args.rounds, len(frames))) for name in methods}
    cpu = {name: np.zeros((args.rounds, len(frames))) for name in methods}
    results = [{} for _ in frames]
    for r in range(args.rounds):
        for j, (frame, points) in enumerate(zip(frames, clouds, strict=True)):
            for name in methods:
                results[j][name], times[name][r, j], cpu[name][r, j] = timed(
                    lambda n=name, f=frame, p=points: run_method(n, f, p, o3d))
    version = f"open3d {o3d.__version__}" if o3d is not None else "open3d not installed (pip install 'hoisdf[bench]')"
    print(f"{len(clouds[0])} points per frame; ms per frame, median of {args.rounds} interleaved rounds; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} (1, 5, 15 min); {version}")
    head = (f"{'frame':<36}{'bvh':>7}{'igl':>7}{'trimesh':>9}{'open3d':>14}{'x':>6}{'x-igl':>7}{'bvh/igl':>9}"
            f"{'o3d/bvh':>9}{'|bvh-igl|':>11}{'|bvh-ref|':>11}  sign errors (bvh igl trimesh open3d)")
    print(head + "\n" + "-" * len(head))
    med = {name: np.median(t, axis=0) for name, t in times.items()}

    def row(name: str, b: float, i: float, t: float, o: float | None, tail: str) -> str:
        o3d_cells = f"{o:14.1f}{o / b:9.2f}" if o is not None else f"{'not installed':>14}{'-':>9}"
        return (f"{name:<36}{b:7.1f}{i:7.1f}{t:9.0f}{o3d_cells[:14]}{t / b:6.0f}{t / i:7.0f}{i / b:9.2f}"
                f"{o3d_cells[14:]}{tail}")

    totals = {name: [0, 0] for name in methods}
    for j, frame in enumerate(frames):
        c = checks(frame, clouds[j], results[j])
        for name, (h, o) in c["errors"].items():
            totals[name][0] += h
            totals[name][1] += o
        o = med["open3d"][j] if o3d is not None else None
        print(row(frame["name"], med["bvh"][j], med["igl"][j], med["trimesh"][j], o,
                  f"{c['gap_igl']:11.1e}{c['gap_ref']:11.1e}  {error_cell(c['errors'], METHODS)}"))
    sums = {name: med[name].sum() for name in methods}
    print(row("all frames (sum of medians)", sums["bvh"], sums["igl"], sums["trimesh"], sums.get("open3d"),
              f"{'':22}  {error_cell(totals, METHODS)}"))
    per_round = {name: t.sum(axis=1) for name, t in times.items()}

    def ratio(a: str, b: str, digits: int) -> str:
        x = per_round[a] / per_round[b]
        return f"{a}/{b} {np.median(x):.{digits}f} ({np.min(x):.{digits}f}-{np.max(x):.{digits}f})"

    extra = f", {ratio('open3d', 'bvh', 2)}" if o3d is not None else ", open3d/bvh: open3d not installed"
    print(f"whole-set speed-up per round, median (min-max) over {args.rounds} rounds: {ratio('trimesh', 'bvh', 0)}, "
          f"{ratio('trimesh', 'igl', 0)}, {ratio('igl', 'bvh', 2)}{extra}")
    cpu_frame = {name: float(np.median(t.sum(axis=1))) / len(frames) for name, t in cpu.items()}
    print("CPU time per frame (process_time, this process, all its threads; mean over the frames, median over the "
          "rounds), ms: " + ", ".join(f"{name} {ms:.1f}" for name, ms in cpu_frame.items())
          + "".join(f"; {name}/bvh {cpu_frame[name] / cpu_frame['bvh']:.2f}" for name in methods if name != "bvh"))
    print(LEGEND)


if __name__ == "__main__":
    main()
