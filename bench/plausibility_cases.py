"""Intersection volume on analytic cases: exact value, :func:`hoisdf.scoring.plausibility.intersection_bounds`,
and what the surface-voxel script of the hand-object literature reports on the same meshes.

The surface-voxel script (obman_train ``mano_train/netscripts/intersect.py`` ``intersect_vox``, copied by GanHand
``utils/obman_utils.py`` and GraspTTA ``metric/intersect.py``; read, not run): trimesh voxelizes the *object's
surface* at a pitch (``mesh.voxelized(pitch)``, the cells its subdivided surface passes through), takes the cell
centres, counts those the hand mesh ``contains`` (trimesh's ray test) and multiplies the count by pitch^3.
Only a layer about one cell thick along the object's surface inside the hand is counted, not the solid overlap,
so the number is roughly (object surface inside the hand) x pitch; :func:`surface_voxel_volume` restates that
method with the same two trimesh calls.

Cases (metres; the "hand" is the mesh whose inside is tested, the "object" the one voxelized):

- two spheres of radius 1 cm, centres 1.25 cm apart: a lens, pi (4 r + d) (2 r - d)^2 / 12;
- a 4 cm cube and a sphere of radius 1 cm centred 5 mm outside one face: a cap, pi h^2 (3 r - h) / 3, h = 5 mm;
- a cylinder of radius 5 mm through a 2 cm thick box, its axis 30 degrees off the box's normal:
  pi r^2 t / cos(30 deg).

The meshes are fine (icospheres of 5120 faces, 128-sided cylinders); the polyhedral value (manifold3d's exact
boolean) differs from the analytic one by the faceting. Run: ``python -m bench.plausibility_cases`` (about a
minute on one core at the default; ``--tolerance`` in m^3, ``cells``: cell-centre evaluations).
"""

from __future__ import annotations

import argparse

import trimesh

from bench.analytic_solids import (  # noqa: F401 - the cases and sizes this script and its test use
    CAP_H,
    CAP_R,
    CYL_R,
    LENS_D,
    LENS_R,
    SLAB_T,
    TILT,
    cases,
)


def polyhedral_volume(hand, obj) -> float:
    """Exact volume of the intersection of the two (watertight) polyhedra: manifold3d's boolean, m^3."""
    return float(trimesh.Trimesh(*hand, process=False).intersection(trimesh.Trimesh(*obj, process=False)).volume)


def surface_voxel_volume(hand, obj, pitch: float) -> float:
    """The literature's surface-voxel estimate (see the module docstring), m^3, for a voxel pitch in metres."""
    points = trimesh.Trimesh(*obj, process=False).voxelized(pitch=pitch).points
    return float(trimesh.Trimesh(*hand, process=False).contains(points).sum()) * pitch ** 3


def table(tolerance: float, pitches=(0.005, 0.001)) -> list[dict]:
    """One row per case: volumes in cm^3 (analytic, polyhedral, ours with its bound, surface-voxel per pitch)."""
    from hoisdf.scoring.plausibility import intersection_bounds

    rows = []
    for name, case in cases().items():
        est = intersection_bounds(*case["hand"], *case["object"], tolerance=tolerance)
        row = {"case": name, "analytic": case["analytic"] * 1e6,
               "polyhedral": polyhedral_volume(case["hand"], case["object"]) * 1e6,
               "ours": est.volume * 1e6, "bound": est.error_bound * 1e6, "cells": est.cells}
        for p in pitches:
            row[f"surface voxel {p * 1e3:g} mm"] = surface_voxel_volume(case["hand"], case["object"], p) * 1e6
        rows.append(row)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tolerance", type=float, default=1e-7, help="m^3 (default 1e-7 = 0.1 cm^3)")
    args = p.parse_args()
    rows = table(args.tolerance)
    keys = [k for k in rows[0] if k != "case"]
    print(f"intersection volume, cm^3 (ours: tolerance {args.tolerance * 1e6:g} cm^3)")
    print(f"{'case':24s}" + "".join(f"{k:>22s}" for k in keys))
    for r in rows:
        print(f"{r['case']:24s}" + "".join(f"{r[k]:22d}" if k == "cells" else f"{r[k]:22.4f}" for k in keys))


if __name__ == "__main__":
    main()
