"""Benchmark of the ``hoidata build-sdf`` SDF stage against its previous path and trimesh, on toy frames.

Each frame: the closed toy MANO hand (float64) in one pose (finger curl times the toy grasp mean,
random global rotation, 0.55 m from the camera) and one toy object (repaired, randomly rotated,
centred 5 cm from the hand centroid); 6144 query points from ``sample_query_points``. On the
same points and meshes, side by side, it times

- ``compute_sdf_samples`` as build-sdf calls it: the ``bvh`` backend (hand sign: winding number);
- the baseline, the same call with ``backend="igl"`` (the libigl path build-sdf used before);
- ``trimesh.proximity.signed_distance`` for the hand and the object (fresh Trimesh objects per
  call, as for a new frame; trimesh's sign is positive inside, so it is negated).

The methods run interleaved, frame by frame, in ``--rounds`` rounds (after one warm-up of each,
which also builds the kept tree shapes, as a build worker's first frames do), so load from other
jobs hits all of them alike; it reports per-frame medians, the speed-ups, and the spread of the
whole-set speed-up over the rounds. Everything runs on one core (numba and libigl single-threaded
here; trimesh is). Checks on every frame: max |bvh - igl| and |bvh - brute force| on distances,
sign disagreements between bvh and igl, and against trimesh (decided by the brute-force reference,
:func:`hoidata.geometry.sdf.brute_force_signed_distance`).

Run: ``python -m bench.bench_sdf`` (about 1-2 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from hoidata.geometry.sampling import compute_sdf_samples, sample_query_points
from hoidata.geometry.sdf import brute_force_signed_distance
from hoidata.hand import load_mano
from hoidata.objects import load_object_mesh, repair_mesh
from hoidata.toy.hand import write_toy_mano
from hoidata.toy.objects import TOY_OBJECTS, write_toy_objects

CURLS = (0.0, 0.5, 0.8, 1.0, 1.2)
CAMERA_T = np.array([0.03, -0.02, 0.55])


LEGEND = """bvh: compute_sdf_samples (backend 'bvh', hand sign by winding number); igl: the same call with
backend='igl' (the previous path, the baseline); trimesh: trimesh.proximity.signed_distance, hand and object.
x: trimesh / bvh, x-igl: trimesh / igl, bvh/igl: igl / bvh (time ratios of per-frame medians).
|bvh-igl|, |bvh-ref|: max distance difference in metres to the baseline (all points) and to the
brute-force reference (every 4th point), both meshes. signs: 'd i/k' = d points whose sign differs between
bvh and igl; i whose sign differs from trimesh, k of them decided for bvh by the brute-force reference
(hand, then object)."""


def toy_frames(workdir: str, n_frames: int) -> list[dict]:
    """Frame k: pose CURLS[k % 5] with a random rotation, object k % 5; camera frame, metres."""
    write_toy_mano(workdir)
    mano = load_mano(workdir, dtype=torch.float64)
    objects = [repair_mesh(load_object_mesh(p)) for p in write_toy_objects(f"{workdir}/models")]
    frames = []
    for k in range(n_frames):
        pose = torch.zeros(1, 48, dtype=torch.float64)
        pose[0, :3] = torch.as_tensor(Rotation.random(random_state=k).as_rotvec())
        pose[0, 3:] = mano.hands_mean * CURLS[k % len(CURLS)]
        out = mano(pose, transl=torch.as_tensor(CAMERA_T)[None])
        hand = mano.close(out.vertices)[0].numpy()
        mesh, report = objects[k % len(objects)]
        rot = Rotation.random(random_state=100 + k).as_matrix()
        offset = Rotation.random(random_state=200 + k).apply([0.05, 0.0, 0.0])
        obj = np.asarray(mesh.vertices) @ rot.T + hand.mean(0) + offset
        frames.append(dict(name=f"curl {CURLS[k % len(CURLS)]:.1f} + {list(TOY_OBJECTS)[k % len(objects)]}",
                           hand=hand, hand_faces=np.asarray(mano.closed_faces), parts=mano.closed_face_parts,
                           root=out.joints[0, 0].numpy(), obj=obj, obj_faces=np.asarray(mesh.faces),
                           watertight=report.watertight))
    return frames


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


def timed(fn) -> tuple[object, float]:
    """(result, wall time in ms) of one call."""
    start = time.perf_counter()
    result = fn()
    return result, 1e3 * (time.perf_counter() - start)


def referee(points, ours_sdf, other_sdf, vertices, faces) -> tuple[int, int]:
    """(sign disagreements, how many of them the brute-force reference decides for ours)."""
    differ = np.flatnonzero((ours_sdf < 0) != (other_sdf < 0))
    if len(differ) == 0:
        return 0, 0
    ref, _ = brute_force_signed_distance(points[differ], vertices, faces)
    return len(differ), int(np.sum((ref < 0) == (ours_sdf[differ] < 0)))


METHODS = ("bvh", "igl", "trimesh")


def run_method(name: str, frame: dict, points: np.ndarray):
    return with_trimesh(frame, points) if name == "trimesh" else sdf_samples(frame, points, name)


def checks(frame: dict, points: np.ndarray, results: dict) -> dict:
    """Distance differences and sign disagreements of one frame (see LEGEND)."""
    meshes = ((frame["hand"], frame["hand_faces"]), (frame["obj"], frame["obj_faces"]))
    gap_igl = max(float(np.abs(b - i).max()) for b, i in zip(results["bvh"], results["igl"]))
    gap_ref = 0.0
    for got, (v, f) in zip(results["bvh"], meshes):
        ref, _ = brute_force_signed_distance(points[::4], v, f)
        gap_ref = max(gap_ref, float(np.abs(got[::4] - ref).max()))
    signs = []
    for k, (v, f) in enumerate(meshes):
        bvh, igl, tm = results["bvh"][k], results["igl"][k], results["trimesh"][k]
        n, decided = referee(points, bvh, tm, v, f)
        signs.append(f"{int(np.sum((bvh < 0) != (igl < 0)))} {n}/{decided}")
    return {"gap_igl": gap_igl, "gap_ref": gap_ref, "signs": " ".join(signs)}


def spread(values) -> str:
    return f"{np.median(values):.0f} ({np.min(values):.0f}-{np.max(values):.0f})"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timed rounds over all frames")
    parser.add_argument("--n-hand", type=int, default=4096)
    parser.add_argument("--n-object", type=int, default=2048)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as workdir:
        frames = toy_frames(workdir, args.frames)
    clouds = [sample_query_points(f["hand"], f["hand_faces"], f["obj"], f["obj_faces"], f["root"],
                                  np.random.default_rng(k), args.n_hand, args.n_object)[0]
              for k, f in enumerate(frames)]
    for frame, points in zip(frames, clouds, strict=True):  # warm-up: compile, kept tree shapes
        for name in METHODS:
            run_method(name, frame, points)
    times = {name: np.zeros((args.rounds, len(frames))) for name in METHODS}
    results = [{} for _ in frames]
    for r in range(args.rounds):
        for j, (frame, points) in enumerate(zip(frames, clouds, strict=True)):
            for name in METHODS:
                results[j][name], times[name][r, j] = timed(lambda n=name, f=frame, p=points: run_method(n, f, p))
    print(f"{len(clouds[0])} points per frame; ms per frame, median of {args.rounds} interleaved rounds; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} (1, 5, 15 min)")
    head = (f"{'frame':<36}{'bvh':>7}{'igl':>7}{'trimesh':>9}{'x':>6}{'x-igl':>7}{'bvh/igl':>9}"
            f"{'|bvh-igl|':>11}{'|bvh-ref|':>11}  signs")
    print(head + "\n" + "-" * (len(head) + 12))
    med = {name: np.median(t, axis=0) for name, t in times.items()}
    for j, frame in enumerate(frames):
        c = checks(frame, clouds[j], results[j])
        b, i, t = med["bvh"][j], med["igl"][j], med["trimesh"][j]
        print(f"{frame['name']:<36}{b:7.1f}{i:7.1f}{t:9.0f}{t / b:6.0f}{t / i:7.0f}{i / b:9.2f}"
              f"{c['gap_igl']:11.1e}{c['gap_ref']:11.1e}  {c['signs']}")
    b, i, t = (med[name].sum() for name in METHODS)
    print(f"{'all frames (sum of medians)':<36}{b:7.1f}{i:7.1f}{t:9.0f}{t / b:6.0f}{t / i:7.0f}{i / b:9.2f}")
    per_round = {name: t.sum(axis=1) for name, t in times.items()}
    print(f"whole-set speed-up per round, median (min-max) over {args.rounds} rounds: "
          f"trimesh/bvh {spread(per_round['trimesh'] / per_round['bvh'])}, "
          f"trimesh/igl {spread(per_round['trimesh'] / per_round['igl'])}, "
          f"igl/bvh {np.median(per_round['igl'] / per_round['bvh']):.2f} "
          f"({np.min(per_round['igl'] / per_round['bvh']):.2f}-{np.max(per_round['igl'] / per_round['bvh']):.2f})")
    print(LEGEND)


if __name__ == "__main__":
    main()
