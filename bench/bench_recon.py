"""Seconds per frame of ``hoisdf score recon``'s two protocols, side by side in one run: gSDF's sampled protocol
(:func:`hoisdf.scoring.recon_gsdf.point_scores` on 30,000 surface samples per mesh), and the exact protocol
(:func:`hoisdf.scoring.recon_exact.one_way` both ways, proven bounds) at ``--tolerance``, with its fraction bounds
by disc areas (the default) and by whole pieces (``discs=False``: a piece straddling a threshold wholly
undecided, the bounds before issue 46).

Frames: the toy MANO hand (``hoidata make-toy``'s procedural hand, closed with its wrist cap) at a random global
rotation and 0.6-1.4 times the toy grasp mean, and a toy object (each of the five in turn); each prediction is its
ground truth scaled by 1 + U(-3 %, 3 %) about its centroid, shifted 1-4 mm (hand) or 2-8 mm (object) and every
vertex moved by N(0, 0.5 mm) (the noise of a marching-cubes surface, roughly). Each row: CPU seconds of the frame
(both parts) per method, the exact protocol's distance queries and its widest half-width reached on a Chamfer
(cm^2) and an F-score. The last lines give exact / gSDF's time and extrapolate to an HO-3D evaluation split
(11,524 frames) on 2 free cores.

Run: ``python -m bench.bench_recon [--frames 6] [--tolerance 0.01] [--max-queries 4000000]``.
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
from hoisdf.scoring import recon_exact, recon_gsdf

HO3D_EVALUATION_FRAMES = 11_524


def perturbed(v: np.ndarray, rng: np.random.Generator, shift: float) -> np.ndarray:
    cen, d = v.mean(0), rng.normal(size=3)
    return ((v - cen) * (1 + rng.uniform(-0.03, 0.03)) + cen + d / np.linalg.norm(d) * rng.uniform(shift / 4, shift)
            + rng.normal(scale=0.0005, size=v.shape))


def toy_frames(count: int, seed: int = 0) -> list[dict]:
    """``count`` frames {part: (prediction (V, 3), ground truth (V, 3), faces)}, metres."""
    with tempfile.TemporaryDirectory() as tmp:
        write_toy_mano(tmp)
        mano = load_mano(tmp, side="right", dtype=torch.float64)
    rng, names, out = np.random.default_rng(seed), list(TOY_OBJECTS), []
    for i in range(count):
        pose = torch.zeros(1, 48, dtype=torch.float64)
        pose[0, :3] = torch.as_tensor(Rotation.random(random_state=seed + i).as_rotvec())
        pose[0, 3:] = mano.hands_mean * float(rng.uniform(0.6, 1.4))
        hand = mano.close(mano(pose, transl=torch.tensor([[0.03, -0.02, 0.55]])).vertices)[0].numpy()
        ov, of, _ = build_toy_object(names[i % len(names)])
        obj = ov @ Rotation.random(random_state=1000 + seed + i).as_matrix().T + hand.mean(0) + [0.0, 0.05, 0.0]
        out.append({"hand": (perturbed(hand, rng, 0.004), hand, np.asarray(mano.closed_faces)),
                    "obj": (perturbed(obj, rng, 0.008), obj, np.asarray(of))})
    return out


def sampled(frame: dict, rng: np.random.Generator) -> None:
    import trimesh

    for part, (pv, gv, f) in frame.items():
        points = [trimesh.sample.sample_surface(trimesh.Trimesh(v, f, process=False), recon_gsdf.POINTS, seed=rng)[0]
                  for v in (pv, gv)]
        recon_gsdf.point_scores(points[0] * recon_gsdf.CM, points[1] * recon_gsdf.CM, part)


def exact(frame: dict, tol: float, max_queries: int, discs: bool = True) -> tuple[int, float, float]:
    """Queries, widest Chamfer half-width, widest F half-width of one frame (both parts)."""
    queries, w_chamfer, w_f = 0, 0.0, 0.0
    for part, (pv, gv, f) in frame.items():
        thresholds = np.array([t for _, t in recon_gsdf.THRESHOLDS[part]])
        one = [recon_exact.one_way(a * recon_gsdf.CM, f, recon_exact.Target(b * recon_gsdf.CM, f), thresholds, tol,
                                   tol / 2, max_queries, discs=discs) for a, b in ((pv, gv), (gv, pv))]
        queries += sum(o["queries"] for o in one)
        w_chamfer = max(w_chamfer, sum(o["sq"][1] - o["sq"][0] for o in one) / 2)
        for k in range(len(thresholds)):
            lo = recon_exact.fscore(one[0]["frac"][0][k], one[1]["frac"][0][k])
            hi = recon_exact.fscore(one[0]["frac"][1][k], one[1]["frac"][1][k])
            w_f = max(w_f, (hi - lo) / 2)
    return queries, w_chamfer, w_f


def cpu_timed(fn):
    start = time.process_time()
    out = fn()
    return out, time.process_time() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--tolerance", type=float, default=0.01, help="exact: Chamfer cm^2 and F half-width aimed at")
    p.add_argument("--max-queries", type=int, default=recon_exact.MAX_QUERIES)
    args = p.parse_args()
    frames = toy_frames(args.frames)
    exact(frames[0], 1.0, 10_000)  # compile the kernels outside the timings
    exact(frames[0], 1.0, 10_000, False)
    print(f"{len(frames)} toy frames, {os.cpu_count()} CPUs, load before {os.getloadavg()[0]:.2f}; CPU seconds per "
          f"frame (hand + object); exact at tolerance {args.tolerance:g}")
    print(f"{'frame':>5s} | {'gsdf s':>7s} | {'exact s':>7s} {'queries':>9s} {'+-CD':>8s} {'+-F':>8s} | "
          f"{'whole pieces s':>14s} {'queries':>9s} {'+-CD':>8s} {'+-F':>8s}")
    rng, sums = np.random.default_rng(0), np.zeros(3)
    for i, frame in enumerate(frames):
        _, t_gsdf = cpu_timed(lambda: sampled(frame, rng))
        (q, wc, wf), t_new = cpu_timed(lambda: exact(frame, args.tolerance, args.max_queries))
        (q0, wc0, wf0), t_old = cpu_timed(lambda: exact(frame, args.tolerance, args.max_queries, False))
        sums += (t_gsdf, t_new, t_old)
        print(f"{i:5d} | {t_gsdf:7.2f} | {t_new:7.2f} {q:9d} {wc:8.1e} {wf:8.1e} | {t_old:14.2f} {q0:9d} "
              f"{wc0:8.1e} {wf0:8.1e}")
    mean = sums / len(frames)
    print(f"exact / gsdf: {mean[1] / mean[0]:.2f} (whole pieces: {mean[2] / mean[0]:.2f})")
    print(f"mean CPU seconds per frame: gsdf {mean[0]:.2f}, exact {mean[1]:.2f}, exact by whole pieces "
          f"{mean[2]:.2f} -> {HO3D_EVALUATION_FRAMES} frames on 2 free cores: gsdf "
          f"{mean[0] * HO3D_EVALUATION_FRAMES / 2 / 3600:.1f} h, exact {mean[1] * HO3D_EVALUATION_FRAMES / 2 / 3600:.1f} h"
          f"; load after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
