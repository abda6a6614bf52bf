"""The analytic intersection cases the plausibility benchmarks share (a library module: no ``__main__``).

Cases (metres; the "hand" is the mesh whose inside is tested, the "object" the other one): two spheres of radius
1 cm, centres 1.25 cm apart (a lens); a 4 cm cube and a sphere of radius 1 cm centred 5 mm outside one face (a
cap); a cylinder of radius 5 mm through a 2 cm thick box, its axis 30 degrees off the box's normal. See
:mod:`bench.plausibility_cases` for the formulas and the comparison they serve.
"""

from __future__ import annotations

import numpy as np
import trimesh

LENS_R, LENS_D = 0.01, 0.0125
CAP_R, CAP_H = 0.01, 0.005
CYL_R, SLAB_T, TILT = 0.005, 0.02, np.radians(30.0)


def _mesh(m: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def cases() -> dict[str, dict]:
    """{name: {"hand": (V, F), "object": (V, F), "analytic": m^3}} for the three analytic cases."""
    out = {}
    a = trimesh.creation.icosphere(subdivisions=4, radius=LENS_R)
    b = trimesh.creation.icosphere(subdivisions=4, radius=LENS_R)
    b.apply_translation([LENS_D, 0.0, 0.0])
    out["two spheres (lens)"] = {"hand": _mesh(a), "object": _mesh(b),
                                 "analytic": np.pi * (4 * LENS_R + LENS_D) * (2 * LENS_R - LENS_D) ** 2 / 12}
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    ball = trimesh.creation.icosphere(subdivisions=4, radius=CAP_R)
    ball.apply_translation([0.0, 0.0, 0.02 + CAP_R - CAP_H])
    out["box and sphere (cap)"] = {"hand": _mesh(ball), "object": _mesh(box),
                                   "analytic": np.pi * CAP_H ** 2 * (3 * CAP_R - CAP_H) / 3}
    slab = trimesh.creation.box(extents=(0.06, 0.06, SLAB_T))
    cyl = trimesh.creation.cylinder(radius=CYL_R, height=0.08, sections=128)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(TILT, [1.0, 0.0, 0.0]))
    out["cylinder through box"] = {"hand": _mesh(cyl), "object": _mesh(slab),
                                   "analytic": np.pi * CYL_R ** 2 * SLAB_T / np.cos(TILT)}
    return out
