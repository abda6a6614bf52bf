"""Benchmark of the ``hoidata build-sdf`` SDF stage against trimesh, on toy frames.

Each frame: the closed toy MANO hand (float64) in one pose (finger curl times the toy grasp mean,
random global rotation, 0.55 m from the camera) and one toy object (repaired, randomly rotated,
centred 5 cm from the hand centroid); 6144 query points from ``sample_query_points``. On the
same points and meshes, side by side, it times

- ``compute_sdf_samples`` as used by build-sdf (hand sign: winding number, the default),
- the same with ``hand_pseudonormal=True`` (hand sign: pseudonormal),
- ``trimesh.proximity.signed_distance`` for the hand and the object (fresh Trimesh objects per
  call, as for a new frame; trimesh's sign is positive inside, so it is negated),

reporting the median wall-clock ms per frame (after one warm-up of every method),
the speed-up, max |difference| to trimesh and sign disagreements. Where signs disagree, the
brute-force reference (:func:`hoidata.geometry.sdf.brute_force_signed_distance`) says who is right.

Run: ``/work/venv/bin/python bench/bench_sdf.py`` (about 1-2 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from hoidata.geometry.sampling import compute_sdf_samples, sample_query_points
from hoidata.geometry.sdf import brute_force_signed_distance
from hoidata.hand import load_mano
from hoidata.hand.toy import write_toy_mano
from hoidata.objects import (
    TOY_OBJECTS,
    load_object_mesh,
    repair_mesh,
    write_toy_objects,
)

CURLS = (0.0, 0.5, 0.8, 1.0, 1.2)
CAMERA_T = np.array([0.03, -0.02, 0.55])


LEGEND = """ours: compute_sdf_samples (hand sign by winding number); ours-pn: hand_pseudonormal=True;
x, x-pn: trimesh time / ours time. |d|-gap: max over both meshes of ||ours| - |trimesh||;
ours-ref: max ||ours| - |brute force|| on the 20 points per mesh with the largest gap.
signs: 'n/k' = n points whose sign differs from trimesh, k of them decided for ours by the
brute-force reference; hand (winding), hand (pseudonormal), object."""


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


def ours(frame: dict, points: np.ndarray, hand_pseudonormal: bool) -> tuple[np.ndarray, np.ndarray]:
    sdf_hand, sdf_obj, _ = compute_sdf_samples(points, frame["hand"], frame["hand_faces"], frame["parts"],
                                               frame["obj"], frame["obj_faces"], frame["watertight"],
                                               hand_pseudonormal=hand_pseudonormal)
    return sdf_hand, sdf_obj


def with_trimesh(frame: dict, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # trimesh caches its BVH on the mesh object; a new frame has new meshes, so build them here.
    hand = trimesh.Trimesh(frame["hand"], frame["hand_faces"], process=False)
    obj = trimesh.Trimesh(frame["obj"], frame["obj_faces"], process=False)
    return -trimesh.proximity.signed_distance(hand, points), -trimesh.proximity.signed_distance(obj, points)


def timed(fn, repeats: int):
    """(result of the last call, median wall time in ms)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return result, 1e3 * float(np.median(times))


def referee(points, ours_sdf, other_sdf, vertices, faces) -> tuple[int, int]:
    """(sign disagreements, how many of them the brute-force reference decides for ours)."""
    differ = np.flatnonzero((ours_sdf < 0) != (other_sdf < 0))
    if len(differ) == 0:
        return 0, 0
    ref, _ = brute_force_signed_distance(points[differ], vertices, faces)
    return len(differ), int(np.sum((ref < 0) == (ours_sdf[differ] < 0)))


def magnitude_check(points, ours_sdf, other_sdf, vertices, faces, n_worst: int = 20) -> tuple[float, float]:
    """(max ||ours| - |trimesh||, max |ours| - |reference| error on the n_worst points of that)."""
    gap = np.abs(np.abs(ours_sdf) - np.abs(other_sdf))
    worst = np.argsort(gap)[-n_worst:]
    ref, _ = brute_force_signed_distance(points[worst], vertices, faces)
    return float(gap.max()), float(np.abs(np.abs(ours_sdf[worst]) - np.abs(ref)).max())


def bench_frame(frame: dict, points: np.ndarray, repeats: int, repeats_ours: int) -> dict:
    (h, o), t_ours = timed(lambda: ours(frame, points, False), repeats_ours)
    (hp, _), t_pseudo = timed(lambda: ours(frame, points, True), repeats_ours)
    (th, to), t_tm = timed(lambda: with_trimesh(frame, points), repeats)
    hand, obj = (frame["hand"], frame["hand_faces"]), (frame["obj"], frame["obj_faces"])
    gap_h, err_h = magnitude_check(points, h, th, *hand)
    gap_o, err_o = magnitude_check(points, o, to, *obj)
    signs = [referee(points, h, th, *hand), referee(points, hp, th, *hand), referee(points, o, to, *obj)]
    return dict(ours=t_ours, pseudo=t_pseudo, trimesh=t_tm, gap=max(gap_h, gap_o), err=max(err_h, err_o),
                signs=" ".join(f"{n}/{k}" for n, k in signs))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of trimesh per frame")
    parser.add_argument("--repeats-ours", type=int, default=9, help="timed runs of ours per frame (cheap)")
    parser.add_argument("--n-hand", type=int, default=4096)
    parser.add_argument("--n-object", type=int, default=2048)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as workdir:
        frames = toy_frames(workdir, args.frames)
    clouds = [sample_query_points(f["hand"], f["hand_faces"], f["obj"], f["obj_faces"], f["root"],
                                  np.random.default_rng(k), args.n_hand, args.n_object)[0]
              for k, f in enumerate(frames)]
    ours(frames[0], clouds[0], False), ours(frames[0], clouds[0], True), with_trimesh(frames[0], clouds[0])  # warm-up
    print(f"{len(clouds[0])} points per frame; ms per frame, median of {args.repeats_ours} (ours) "
          f"and {args.repeats} (trimesh) runs")
    head = (f"{'frame':<38}{'ours':>8}{'ours-pn':>9}{'trimesh':>9}{'x':>6}{'x-pn':>6}"
            f"{'|d|-gap m':>11}{'ours-ref m':>12}  signs")
    print(head + "\n" + "-" * (len(head) + 20))
    rows = []
    for frame, points in zip(frames, clouds, strict=True):
        r = bench_frame(frame, points, args.repeats, args.repeats_ours)
        rows.append(r)
        print(f"{frame['name']:<38}{r['ours']:8.1f}{r['pseudo']:9.1f}{r['trimesh']:9.0f}{r['trimesh'] / r['ours']:6.0f}"
              f"{r['trimesh'] / r['pseudo']:6.0f}{r['gap']:11.1e}{r['err']:12.1e}  {r['signs']}")
    total = {k: sum(r[k] for r in rows) for k in ("ours", "pseudo", "trimesh")}
    print(f"{'all frames (sum of medians)':<38}{total['ours']:8.1f}{total['pseudo']:9.1f}{total['trimesh']:9.0f}"
          f"{total['trimesh'] / total['ours']:6.0f}{total['trimesh'] / total['pseudo']:6.0f}")
    print(LEGEND)


if __name__ == "__main__":
    main()
