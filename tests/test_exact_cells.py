"""Exact cells of the volume octree (hoisdf.scoring.cell_volume, solids.region_volume's ``exact_cells``): the
column integral of a cube against closed forms, 1 % relative bounds on large smooth overlaps against manifold3d's
exact boolean of the same meshes, and rigour where a mesh passes through itself (irregular faces)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from hoisdf.scoring.plausibility import intersection_bounds
from hoisdf.scoring.solids import MeshSolid, Part, region_volume

ROUNDING = 1e-8  # relative slack on manifold3d's volumes


def _mesh(m: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def _polyhedral(a, b) -> float:
    """manifold3d's boolean; it merges vertices within its epsilon, so its volumes differ from the meshes' own
    (divergence theorem) by about 1e-9 relative: compared with :data:`ROUNDING` of slack."""
    return float(trimesh.Trimesh(*a, process=False).intersection(trimesh.Trimesh(*b, process=False)).volume)


def test_cube_integral_of_a_tilted_plane_and_a_corner_matches_closed_forms():
    """A big box tilted about x: inside a unit-ish cube its top face is the plane z = c + t y, so the solid's part
    of the cube is a prism of known volume; a cube beside the box gets 0, one inside it the whole cube."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.apply_translation([0.0, 0.0, -0.5])  # top face at z = 0
    angle = np.radians(10.0)
    box.apply_transform(trimesh.transformations.rotation_matrix(angle, [1.0, 0.0, 0.0]))
    solid = MeshSolid(*_mesh(box))
    edge = 0.01
    centres = np.array([[0.0123, 0.0311, 0.0017], [0.3, 0.2, 0.9], [0.01, 0.02, -0.3],
                        [-0.498, 0.1, 0.1 * np.tan(np.radians(10.0)) + 0.001]])
    vol, touched = solid.cube_volumes(centres, edge)
    t = np.tan(angle)  # the top plane after the turn: z = y tan(angle)
    y0, y1 = centres[0, 1] - edge / 2, centres[0, 1] + edge / 2
    z0 = centres[0, 2] - edge / 2
    # the integral over the square of clamp(t y - z0, 0, edge): the plane stays within the cube here
    assert 0 < t * y0 - z0 < edge and 0 < t * y1 - z0 < edge
    want = edge * (t * (y1 ** 2 - y0 ** 2) / 2 - z0 * edge)
    assert vol[0] == pytest.approx(want, rel=1e-9) and touched[0]
    assert vol[1] == 0.0 and not touched[1]
    assert vol[2] == pytest.approx(edge ** 3, rel=1e-9) and not touched[2]  # inside: the faces above count
    # by the box's side face x = -0.5 too: 0.007 of the cube's width is in the box
    y0, y1, z0 = centres[3, 1] - edge / 2, centres[3, 1] + edge / 2, centres[3, 2] - edge / 2
    assert 0 < t * y0 - z0 < edge and 0 < t * y1 - z0 < edge
    want = (centres[3, 0] + edge / 2 + 0.5) * (t * (y1 ** 2 - y0 ** 2) / 2 - z0 * edge)
    assert touched[3] and vol[3] == pytest.approx(want, rel=1e-9)


@pytest.mark.slow  # two 10,242-vertex spheres and manifold3d's boolean: a few seconds
def test_icosphere_lens_to_one_percent_against_the_exact_boolean():
    """The case that needed more than 20 M cell evaluations for 1 % with the ball bound alone (issue 32)."""
    a = trimesh.creation.icosphere(subdivisions=5, radius=0.04)
    b = trimesh.creation.icosphere(subdivisions=5, radius=0.03)
    b.apply_translation([0.05, 0.0, 0.0])
    a, b = _mesh(a), _mesh(b)
    assert len(a[0]) == 10_242
    exact = _polyhedral(a, b)  # about 19.2 cm^3
    for tolerance, rel in ((2e-7, 0.0), (1e-12, 0.01), (1e-12, 0.001)):
        est = intersection_bounds(*a, *b, tolerance=tolerance, rel_tolerance=rel)
        assert est.guaranteed and est.lower - ROUNDING * exact <= exact <= est.upper + ROUNDING * exact
        assert est.error_bound <= max(tolerance, rel * est.lower)
        assert est.cells < 200_000
    # the ball bound alone would need more than the budget for the same 1 %
    sa, sb = MeshSolid(*a), MeshSolid(*b)
    with pytest.raises(ValueError, match="larger tolerance"):
        region_volume([Part(sa), Part(sb)], np.maximum(sa.lo, sb.lo), np.minimum(sa.hi, sb.hi), 2e-7,
                      max_cells=2_000_000, exact_cells=False)


@pytest.mark.slow  # manifold3d's boolean of fine spheres and the octree at 0.1 %: a few seconds
def test_sphere_in_a_box_to_one_percent_against_the_exact_boolean():
    """A sphere poking out of a cube's top face (box faces in the planes of the octree's outer cells)."""
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    for shift in ([0.003, 0.002, 0.015], [0.0, 0.0, 0.0], [0.011, -0.007, 0.019]):
        ball = trimesh.creation.icosphere(subdivisions=5, radius=0.01)
        ball.apply_translation(shift)
        exact = _polyhedral(_mesh(ball), _mesh(box))
        for rel in (0.01, 0.001):
            est = intersection_bounds(*_mesh(ball), *_mesh(box), tolerance=1e-12, rel_tolerance=rel)
            slack = ROUNDING * exact
            assert est.lower - slack <= exact <= est.upper + slack and est.error_bound <= rel * est.lower, (shift, rel)
            assert abs(est.volume - exact) <= rel * exact


@pytest.mark.slow  # manifold3d booleans and a 1 % octree with irregular cells: a few seconds
def test_a_mesh_through_itself_keeps_rigorous_bounds():
    """Two overlapping cubes as one closed mesh (their faces cross; w = 2 where they overlap): the solid |w| > 1/2
    is their union. Faces that cross are irregular, cells near them keep the ball bound, and the bounds still
    hold the exact volume of (union) x sphere."""
    c1 = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    c2 = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    c2.apply_translation([0.008, 0.006, 0.004])
    soup = (np.concatenate([c1.vertices, c2.vertices]), np.concatenate([c1.faces, c2.faces + len(c1.vertices)]))
    solid = MeshSolid(*soup)
    assert solid.closed and solid.regular()[1] is not None  # crossing faces found
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.012)
    ball.apply_translation([0.01, 0.008, 0.006])
    exact = float(trimesh.boolean.union([c1, c2]).intersection(ball).volume)
    est = intersection_bounds(*_mesh(ball), *soup, tolerance=1e-12, rel_tolerance=0.01)
    assert est.lower - ROUNDING * exact <= exact <= est.upper + ROUNDING * exact
    assert est.error_bound <= 0.01 * est.lower
    # an inward-wound mesh is the same solid (w = -1 inside)
    inward = intersection_bounds(*_mesh(ball), c1.vertices, c1.faces[:, ::-1], tolerance=1e-12, rel_tolerance=0.01)
    exact_c1 = float(c1.intersection(ball).volume)
    assert inward.lower - ROUNDING * exact_c1 <= exact_c1 <= inward.upper + ROUNDING * exact_c1


@pytest.mark.slow  # three manifold3d booleans and three 1 % volumes: a few seconds
def test_the_analytic_cases_to_one_percent():
    """bench/analytic_solids' lens, cap and tilted cylinder at 1 %: the exact boolean inside the bounds."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "analytic_solids.py"
    spec = importlib.util.spec_from_file_location("analytic_solids", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    for name, case in module.cases().items():
        exact = _polyhedral(case["hand"], case["object"])
        est = intersection_bounds(*case["hand"], *case["object"], tolerance=1e-12, rel_tolerance=0.01)
        slack = ROUNDING * exact
        assert est.lower - slack <= exact <= est.upper + slack and est.error_bound <= 0.01 * est.lower, name
