"""Intersection volume of the toy's deeply penetrating hands, side by side in one run: the octree with exact cells
(:func:`hoisdf.scoring.solids.region_volume`, ``exact_cells`` on) at ``--rel`` (1 %), the same octree with the
ball bound only (the method before exact cells) within the evaluator's budget, and the literature's surface-voxel
script at 5 mm on MANO's open mesh (obman_train / GraspTTA ``intersect_vox``, restated in
:func:`hoisdf.scoring.contact_legacy.surface_voxel_volume`).

Frames: the toy MANO hand (``hoidata make-toy``'s procedural hand, closed with its wrist cap) at a random global
rotation and 0.6-1.4 times the toy grasp mean, with a toy object (each of the five in turn) centred at the palm:
whole objects sunk into the hand, 10-200 cm^3 of overlap. Each row: seconds per frame (wall, one process) and the
volume with its rigorous bound. A reference at 0.1 % (exact cells) checks that the 1 % results are within 1 %.
Then ``--split-frames`` other frames, every metric at the scorer's settings (:func:`~hoisdf.scoring.plausibility.
frame_metrics`), give the extrapolation to an HO-3D evaluation split (11,524 frames): CPU seconds per frame in this
process (what two free cores divide), and wall time on ``--workers`` processes (``frame_metrics_many``) at the
machine's load.

Run: ``python -m bench.bench_volume [--frames 10] [--rel 0.01] [--split-frames 40] [--workers 2]``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hoidata.hand import load_mano
from hoidata.toy.hand import write_toy_mano
from hoidata.toy.objects import TOY_OBJECTS, build_toy_object
from hoisdf.scoring import plausibility
from hoisdf.scoring.contact_legacy import surface_voxel_volume
from hoisdf.scoring.solids import MeshSolid, Part, region_volume

HO3D_EVALUATION_FRAMES = 11_524


def toy_frames(count: int, seed: int = 0, offsets=(0.0,)) -> list[tuple]:
    """``count`` (hand_v, hand_f, obj_v, obj_f, object name), metres: the object centred at the palm (offset 0:
    deeply penetrating), or moved from there by ``offsets[i % len(offsets)]`` metres in a random direction."""
    with tempfile.TemporaryDirectory() as tmp:
        write_toy_mano(tmp)
        mano = load_mano(tmp, side="right", dtype=torch.float64)
    rng = np.random.default_rng(seed)
    names = list(TOY_OBJECTS)
    out = []
    for i in range(count):
        pose = torch.zeros(1, 48, dtype=torch.float64)
        pose[0, :3] = torch.as_tensor(Rotation.random(random_state=seed + i).as_rotvec())
        pose[0, 3:] = mano.hands_mean * float(rng.uniform(0.6, 1.4))
        hand = mano.close(mano(pose, transl=torch.tensor([[0.03, -0.02, 0.55]])).vertices)[0].numpy()
        ov, of, _ = build_toy_object(names[i % len(names)])
        rot = Rotation.random(random_state=1000 + seed + i).as_matrix()
        palm = hand[:778].mean(0) + rng.normal(scale=0.005, size=3)
        away = rng.normal(size=3)
        palm = palm + offsets[i % len(offsets)] * away / np.linalg.norm(away)
        out.append((hand, np.asarray(mano.closed_faces), ov @ rot.T + palm, of, names[i % len(names)]))
    return out


def volume(frame, rel: float, exact: bool, max_cells: int):
    hv, hf, ov, of, _ = frame
    hand, obj = MeshSolid(hv, hf), MeshSolid(ov, of)
    lo, hi = np.maximum(hand.lo, obj.lo), np.minimum(hand.hi, obj.hi)
    return region_volume([Part(obj), Part(hand)], lo, hi, 1e-12, rel, max_cells, strict=False, exact_cells=exact)


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--rel", type=float, default=0.01)
    p.add_argument("--split-frames", type=int, default=40)
    p.add_argument("--workers", type=int, default=2)
    args = p.parse_args()
    frames = toy_frames(args.frames)
    volume(frames[0], 0.5, True, plausibility.BUDGET)  # compile the kernels outside the timings
    print(f"{len(frames)} toy frames, {os.cpu_count()} CPUs, load before {os.getloadavg()[0]:.2f}; volumes cm^3")
    head = (f"{'object':20s} {'reference':>10s} | {'exact cells':>11s} {'bound':>7s} {'s':>6s} | "
            f"{'ball only':>10s} {'bound':>7s} {'s':>6s} | {'voxels 5mm':>10s} {'s':>6s}")
    print(head)
    sums = np.zeros(3)
    for frame in frames:
        ref = volume(frame, 0.001, True, 10 * plausibility.BUDGET)
        new, t_new = timed(lambda: volume(frame, args.rel, True, plausibility.BUDGET))
        old, t_old = timed(lambda: volume(frame, args.rel, False, plausibility.BUDGET))
        vox, t_vox = timed(lambda: surface_voxel_volume(*frame[:4]))
        assert ref.lower <= new.upper and new.lower <= ref.upper, "bounds that do not overlap"
        within = abs(new.volume - ref.volume) <= args.rel * ref.volume + ref.error_bound
        sums += (t_new, t_old, t_vox)
        print(f"{frame[4]:20s} {ref.volume * 1e6:10.3f} | {new.volume * 1e6:11.3f} {new.error_bound * 1e6:7.3f} "
              f"{t_new:6.2f} | {old.volume * 1e6:10.3f} {old.error_bound * 1e6:7.3f} {t_old:6.2f} | "
              f"{vox * 1e6:10.3f} {t_vox:6.2f}" + ("" if within else "  (off by more than --rel)"))
    mean = sums / len(frames)
    print(f"mean seconds per frame: exact cells {mean[0]:.3f}, ball only {mean[1]:.3f}, surface voxels {mean[2]:.3f}")

    split = toy_frames(args.split_frames, seed=100)
    samples = [f[:4] for f in split]
    settings = dict(tolerance=plausibility.TOLERANCE, rel_tolerance=args.rel, n_points=778,
                    max_cells=plausibility.BUDGET)
    cpu = time.process_time()
    _, wall = timed(lambda: [plausibility.frame_metrics(*s, **settings) for s in samples])
    cpu = (time.process_time() - cpu) / len(samples)
    print(f"{len(samples)} frames, every metric (rel {args.rel:g}), this process: {wall / len(samples):.3f} s wall, "
          f"{cpu:.3f} s CPU per frame -> {HO3D_EVALUATION_FRAMES} frames on 2 free cores: "
          f"{cpu * HO3D_EVALUATION_FRAMES / 2 / 60:.1f} min (CPU time / 2)")
    _, wall = timed(lambda: plausibility.frame_metrics_many(samples, args.workers, **settings))
    print(f"the same on {args.workers} processes: {wall:.1f} s wall ({wall / len(samples):.3f} s per frame, with "
          f"the processes' start) -> {wall / len(samples) * HO3D_EVALUATION_FRAMES / 60:.1f} min at this load; "
          f"load after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
