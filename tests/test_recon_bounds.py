"""The exact recon protocol's per-piece bounds (hoisdf.scoring.recon_bounds): disc areas within a triangle against
closed forms and a fine grid, and the fraction bounds of pieces near a target against exact distances sampled
densely on each piece."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from hoidata.geometry.bvh import MeshBVH
from hoisdf.scoring.recon_bounds import disc_triangle_area, piece_bounds
from hoisdf.scoring.recon_exact import Target

RIGHT = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


def grid_in(w: np.ndarray, n: int) -> np.ndarray:
    """Centres of the n^2 equal sub-triangles of w (n^2 points standing for equal areas)."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    keep = i + j < n
    up = np.stack([(i + 1 / 3) / n, (j + 1 / 3) / n], -1)[keep]
    keep_down = i + j < n - 1
    down = np.stack([(i + 2 / 3) / n, (j + 2 / 3) / n], -1)[keep_down]
    uv = np.concatenate([up, down])
    return w[0] + uv[:, :1] * (w[1] - w[0]) + uv[:, 1:] * (w[2] - w[0])


def test_disc_areas_closed_forms():
    assert disc_triangle_area(0.3, 0.3, 100.0, RIGHT) == pytest.approx(0.5, abs=1e-15)  # the disc holds it
    assert disc_triangle_area(5.0, 5.0, 1.0, RIGHT) == 0.0  # misses
    assert disc_triangle_area(0.0, 0.0, 0.25, RIGHT) == pytest.approx(np.pi * 0.25 / 4, rel=1e-14)  # a quarter
    big = RIGHT * 10
    assert disc_triangle_area(2.0, 2.0, 1.0, big) == pytest.approx(np.pi, rel=1e-14)  # inside the triangle
    assert disc_triangle_area(0.0, 0.0, 0.0, RIGHT) == 0.0 and disc_triangle_area(0.0, 0.0, -1.0, RIGHT) == 0.0


def test_disc_areas_against_a_fine_grid():
    rng = np.random.default_rng(3)
    for _ in range(40):
        w = rng.normal(size=(3, 2))
        z, r2 = rng.normal(size=2), rng.uniform(0.05, 2.0)
        area = 0.5 * abs((w[1, 0] - w[0, 0]) * (w[2, 1] - w[0, 1]) - (w[2, 0] - w[0, 0]) * (w[1, 1] - w[0, 1]))
        points = grid_in(w, 160)
        share = np.mean(((points - z) ** 2).sum(1) < r2)
        assert disc_triangle_area(z[0], z[1], r2, w) == pytest.approx(area * share, abs=0.01 * area)


def test_fraction_bounds_hold_the_area_within_each_threshold():
    """Small pieces near a bumpy closed target: per threshold, inside_lo <= the area where d < t <= inside_hi (the
    area from exact distances on a fine grid of the piece, within the grid's resolution), and the disc bounds are
    within the whole-piece ones and much narrower on the pieces that straddle a threshold."""
    m = trimesh.creation.icosphere(3, 3.0)
    target = Target(np.asarray(m.vertices) * (1 + 0.05 * np.sin(3 * np.asarray(m.vertices)[:, :1])),
                    np.asarray(m.faces))
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(150, 3))
    centres = 3.1 * centres / np.linalg.norm(centres, axis=1, keepdims=True)
    tri = centres[:, None] + rng.normal(scale=0.08, size=(150, 3, 3))
    fv, pv, _ = target.query(tri.reshape(-1, 3))
    fc, pc, _ = target.query(tri.mean(1))
    thresholds = np.array([0.1, 0.2])
    t2 = np.stack([thresholds ** 2, thresholds ** 2])
    args = (tri, fv.reshape(-1, 3), pv.reshape(-1, 3, 3), fc, pc, t2, 0.0)
    area, _, _, lo, hi = piece_bounds(*args, True)
    _, _, _, lo0, hi0 = piece_bounds(*args, False)
    bvh = MeshBVH(target.vertices, target.faces)
    straddling, width, width0 = 0, 0.0, 0.0
    for i in range(len(tri)):
        e1 = tri[i, 1] - tri[i, 0]
        e2 = tri[i, 2] - tri[i, 0]
        basis = np.stack([e1, e2])
        w = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        grid = grid_in(w, 60) @ basis + tri[i, 0]
        d = bvh.closest(np.ascontiguousarray(grid))[0]
        for t, threshold in enumerate(thresholds):
            inside = area[i] * np.mean(d < threshold)
            slack = 0.04 * area[i]  # the grid's resolution along the contour
            assert lo[i, t] - slack <= inside <= hi[i, t] + slack, (i, t, lo[i, t], inside, hi[i, t])
            assert lo0[i, t] <= lo[i, t] + 1e-15 and hi[i, t] <= hi0[i, t] + 1e-15
            if lo0[i, t] < hi0[i, t]:
                straddling += 1
                width, width0 = width + hi[i, t] - lo[i, t], width0 + hi0[i, t] - lo0[i, t]
    assert straddling >= 10 and width < 0.5 * width0, (straddling, width, width0)
