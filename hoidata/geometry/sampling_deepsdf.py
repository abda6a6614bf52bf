"""SDF samples drawn as the authors' training files were (``record.sdf_points = "deepsdf"``).

HOISDF trains on AlignSDF's per-frame sample files (``tool/pre_process_sdf.py`` of amathislab/HOISDF reads them),
which AlignSDF's ``PreprocessMesh`` makes with DeepSDF's procedure, once per entity (hand, object), in a frame
shared by both:

- **normalisation**: the centre of the axis-aligned box around both meshes' vertices, and a radius R = 1.03 x the
  largest vertex distance from it (the unit sphere of the normalised frame, with a 3 % margin). PreprocessMesh
  takes the box's far z from the hand's *y* maximum and the object's z maximum: in the camera frame that is the
  object's far z, so when the hand reaches further back than the object the centre sits nearer the camera. This
  module keeps that slip (:func:`joint_normalisation`), since it shapes the files the authors trained on;
- **per entity, a block of n rows**: ``47 n // 50`` near-surface rows, half from area-weighted surface points
  offset by isotropic N(0, 0.005) (normalised units, i.e. sigma = 0.0707 R), half from the same surface points
  offset by N(0, 0.0005) (sigma = 0.0224 R); then ``n - 47 n // 50`` rows uniform in the normalised cube [-1, 1]^3
  (the centre +- R). AlignSDF's n is 20,000: 9,400 surface points, 18,800 near rows, 1,200 uniform;
- **distances**: to both meshes, signed (negative inside). AlignSDF approximates them from a point cloud rendered
  from 100 views and drops a point whose 11 nearest cloud normals disagree on its side; here they are exact
  (:func:`hoidata.geometry.sampling.compute_sdf_samples`), so no row is dropped for an ambiguous sign;
- **the loader's filter**: ``pre_process_sdf.py`` keeps rows whose distances to *both* meshes are below 2 in
  normalised units (2 R metres); so does :func:`deepsdf_record`.

The stored record keeps the two blocks as its hand and object sets and an empty uniform set (``sdf_counts`` =
[hand block, object block, 0]), so the training loader's hand pool is the hand block and its object pool the
object block, as upstream's ``__getitem__`` draws them. All positions are camera frame, metres.
"""

from __future__ import annotations

import numpy as np

from hoidata.geometry.sampling import SdfSampling, compute_sdf_samples, surface_points
from hoidata.geometry.sdf import validate_mesh
from hoidata.schema import quantize_sdf

BUFFER = 1.03  # PreprocessMesh's margin on the farthest vertex
VARIANCES = (0.005, 0.0005)  # normalised units squared: PreprocessMesh's variance and variance / 10
NEAR_SHARE = (47, 50)  # near-surface rows per block: n * 47 // 50 (two per surface point), the rest uniform
FILTER = 2.0  # normalised units: pre_process_sdf.py keeps rows with both |sdf| below this


def joint_normalisation(hand_vertices: np.ndarray, obj_vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre (3,), R) of PreprocessMesh's frame shared by hand and object: metres, camera frame.

    The box's far z is max(hand y max, object z max), PreprocessMesh's expression (see the module docstring);
    R = 1.03 x the largest distance of a vertex of either mesh from the centre, so both lie inside the sphere.
    """
    hand, obj = np.asarray(hand_vertices, np.float64), np.asarray(obj_vertices, np.float64)
    low = np.minimum(hand.min(0), obj.min(0))
    high = np.maximum(hand.max(0), obj.max(0))
    high[2] = max(hand.max(0)[1], obj.max(0)[2])
    centre = (low + high) / 2.0
    radius = max(np.linalg.norm(hand - centre, axis=1).max(), np.linalg.norm(obj - centre, axis=1).max()) * BUFFER
    return centre, float(radius)


def block_sizes(n: int) -> tuple[int, int]:
    """(surface points, uniform rows) of a block of nominal size ``n``: the block has 2 x surface + uniform rows
    (n, or n - 1 when 47 n // 50 is odd, as PreprocessMesh's integer halving gives)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"a block needs a positive integer row count, got {n!r}")
    near = int(n) * NEAR_SHARE[0] // NEAR_SHARE[1]
    return near // 2, int(n) - near


def entity_points(vertices: np.ndarray, faces: np.ndarray, n: int, centre: np.ndarray, radius: float,
                  rng: np.random.Generator) -> np.ndarray:
    """One entity's query points (rows, 3), metres: surface points + N(0, 0.005 R^2), the same surface points +
    N(0, 0.0005 R^2), then uniform in the cube centre +- R (:func:`block_sizes` rows of each)."""
    n_surface, n_uniform = block_sizes(n)
    base = surface_points(vertices, faces, n_surface, rng)
    near = [base + rng.normal(size=base.shape) * (np.sqrt(v) * radius) for v in VARIANCES]
    uniform = np.asarray(centre, np.float64) + (rng.random((n_uniform, 3)) * 2.0 - 1.0) * radius
    return np.concatenate(near + [uniform])


def deepsdf_record(hand_vertices, hand_faces, hand_face_parts, obj_vertices, obj_faces, obj_watertight: bool,
                   hand_root, rng: np.random.Generator, sampling: SdfSampling = SdfSampling()
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The ``sdf.npy`` array of one frame drawn as the authors' files: the hand block (``sampling.n_hand`` rows
    nominal) then the object block (``sampling.n_object``), exact distances, rows with a distance of 2 R or more
    to either mesh dropped. Arguments as :func:`hoidata.geometry.sampling.build_sdf_record`, which this replaces
    for the ``deepsdf`` setting (``sampling``'s uniform_fraction, cube and sigmas are not used: the normalised
    frame fixes them). Returns the stored int16 (N, 6) array and the (3,) int64 ``sdf_counts``
    [kept hand rows, kept object rows, 0]."""
    hand_vertices, hand_faces = validate_mesh(hand_vertices, hand_faces)
    obj_vertices, obj_faces = validate_mesh(obj_vertices, obj_faces)
    root = np.asarray(hand_root, np.float64)
    if root.shape != (3,) or not np.isfinite(root).all():
        raise ValueError(f"hand_root must be a finite (3,) vector, got shape {root.shape}")
    centre, radius = joint_normalisation(hand_vertices, obj_vertices)
    blocks = [entity_points(v, f, n, centre, radius, rng)
              for v, f, n in ((hand_vertices, hand_faces, sampling.n_hand), (obj_vertices, obj_faces, sampling.n_object))]
    points = np.concatenate(blocks)
    sdf_hand, sdf_obj, part = compute_sdf_samples(points, hand_vertices, hand_faces, hand_face_parts, obj_vertices,
                                                  obj_faces, obj_watertight, sampling.part_radius,
                                                  sampling.hand_pseudonormal, sampling.backend)
    keep = (np.abs(sdf_hand) < FILTER * radius) & (np.abs(sdf_obj) < FILTER * radius)
    n_hand_block = len(blocks[0])
    counts = np.array([keep[:n_hand_block].sum(), keep[n_hand_block:].sum(), 0], np.int64)
    stored = quantize_sdf(points[keep] - root, sdf_hand[keep], sdf_obj[keep], part[keep])
    return stored, counts
