"""Speed of the plausibility report, side by side in one run: every centre asked (the baseline) against children
inheriting their parent's inside/outside (:func:`hoisdf.scoring.solids._child_hints`), on one process and on
``--workers`` processes (:func:`hoisdf.scoring.plausibility.frame_metrics_many`).

Frames: the three analytic cases of :mod:`bench.analytic_solids` (a sphere, a cube, a cylinder standing for the
hand) shifted by a few millimetres, ``--frames`` in all, at ``--tolerance`` m^3. Every variant must report the
same numbers (checked); the table gives wall seconds, CPU seconds of this process and the load average.

Run: ``python -m bench.bench_plausibility [--frames 6] [--workers 2] [--tolerance 3e-8]``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.analytic_solids import cases
from hoisdf.scoring import solids
from hoisdf.scoring.plausibility import frame_metrics_many


def frames(count: int) -> list[tuple]:
    """``count`` (hand_v, hand_f, obj_v, obj_f) samples, the analytic cases in turn, each shifted along x."""
    base = list(cases().values())
    out = []
    for i in range(count):
        case = base[i % len(base)]
        hv, hf = case["hand"]
        out.append((hv + [0.001 * (i // len(base)), 0.0, 0.0], hf, *case["object"]))
    return out


def _asked_everywhere(parts, per_part, open_, radius):
    return [(np.zeros(8 * int(open_.sum()), bool), np.repeat(m[open_], 8)) for m in per_part[0]]


def run(samples, workers: int, tolerance: float, inherit: bool) -> tuple[list, float, float]:
    real = solids._child_hints
    if not inherit:  # only this process: worker processes import the module afresh (inherit there)
        solids._child_hints = _asked_everywhere
    try:
        wall, cpu = time.perf_counter(), time.process_time()
        result = frame_metrics_many(samples, workers, tolerance=tolerance)
        return result, time.perf_counter() - wall, time.process_time() - cpu
    finally:
        solids._child_hints = real


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--tolerance", type=float, default=3e-8)
    args = p.parse_args()
    samples = frames(args.frames)
    print(f"{args.frames} frames, tolerance {args.tolerance * 1e6:g} cm^3, {os.cpu_count()} CPUs, "
          f"load before {os.getloadavg()[0]:.2f}")
    rows, reference = [], None
    for name, workers, inherit in (("every centre asked, 1 process (baseline)", 1, False),
                                   ("inherited, 1 process", 1, True),
                                   (f"inherited, {args.workers} processes", args.workers, True)):
        result, wall, cpu = run(samples, workers, args.tolerance, inherit)
        volumes = [f["intersection_volume_cm3"] for f in result]
        reference = reference or volumes
        assert volumes == reference, f"{name}: other volumes {volumes} vs {reference}"
        rows.append((name, wall, cpu))
    print(f"{'variant':44s} {'wall s':>8s} {'CPU s (here)':>13s} {'speed-up':>9s}")
    for name, wall, cpu in rows:
        print(f"{name:44s} {wall:8.1f} {cpu:13.1f} {rows[0][1] / wall:8.2f}x")
    print(f"load after {os.getloadavg()[0]:.2f}; volumes (cm^3) {[round(v, 4) for v in reference]}")


if __name__ == "__main__":
    main()
