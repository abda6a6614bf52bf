"""Near-surface SDF training samples of one hand-object frame (the ``sdf.npy`` member).

One frame gives three sample sets, stored in this order (see :mod:`hoidata.schema`):

1. the hand set: area-weighted points on the closed hand surface plus isotropic Gaussian offsets;
2. the object set: the same for the object surface;
3. the uniform set: uniform in a cube centred on the hand root, the volume of the model's
   test-time grid, so the network also sees far-field values.

Each surface set is split over ``sigmas`` (default: half at 10 mm, which covers the band the
model must get the sign right in, half at 3 mm, which concentrates samples where the surface
detail is). All positions are camera frame, metres; signed distances are negative inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from hoidata.geometry.bvh import morton_order
from hoidata.geometry.sdf import as_points, signed_distance, validate_mesh
from hoidata.schema import NO_PART, quantize_sdf

DEFAULT_SIGMAS = (0.010, 0.003)


def split_counts(n_hand: int, n_object: int, uniform_fraction: float) -> np.ndarray:
    """Sizes (3,) int64 of the hand, object and uniform sets; they always sum to n_hand + n_object.

    With T = n_hand + n_object (rounding halves up, so the split is platform independent):

    - n_uniform = round(uniform_fraction * T);
    - the hand gives up u_hand = round(n_uniform * n_hand / T) of its points to the uniform set,
      the object the rest, u_object = n_uniform - u_hand (both shares lie in [0, n_hand] and
      [0, n_object]);
    - counts = (n_hand - u_hand, n_object - u_object, n_uniform).

    Example: the defaults 4096, 2048, 0.1 give n_uniform = 614, u_hand = 409, u_object = 205,
    so counts = (3687, 1843, 614).
    """
    for name, n in (("n_hand", n_hand), ("n_object", n_object)):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {n!r}")
    if not 0.0 <= float(uniform_fraction) <= 1.0:
        raise ValueError(f"uniform_fraction must lie in [0, 1], got {uniform_fraction!r}")
    total = int(n_hand) + int(n_object)
    n_uniform = int(np.floor(float(uniform_fraction) * total + 0.5))
    # Integer arithmetic for round(n_uniform * n_hand / total): no float ties to worry about.
    u_hand = (2 * n_uniform * int(n_hand) + total) // (2 * total) if total else 0
    u_object = n_uniform - u_hand
    return np.array([n_hand - u_hand, n_object - u_object, n_uniform], dtype=np.int64)


def surface_points(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points uniform over the mesh surface (faces picked by area, then uniform in the face).

    The draws are those of ``rng.choice(len(faces), n, p=areas / areas.sum())`` (one ``rng.random(n)``, inverted
    through the normalised cumulative areas), then ``rng.random(n)`` twice for the place in the face; the areas,
    picks and points are computed in compiled loops with numpy's operations in numpy's order (the same bits)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    areas = _face_areas(vertices, faces)
    if n > 0 and not areas.sum() > 0:
        raise ValueError("cannot sample the surface of a mesh with zero total area")
    if n == 0:
        return np.zeros((0, 3))
    cdf = (areas / areas.sum()).cumsum()
    cdf /= cdf[-1]
    keys = rng.random(n)
    order = np.argsort(keys)  # searched in increasing order: each search starts where the last one ended
    pick = np.empty(n, np.int64)
    pick[order] = cdf.searchsorted(keys[order], side="right")
    r1, r2 = rng.random(n), rng.random(n)
    return _face_points(vertices, faces, pick, r1, r2)


@numba.njit(cache=True)
def _face_areas(vertices, faces):
    """(F,) triangle areas: half the norm of (b - a) x (c - a), as np.cross and np.linalg.norm form it."""
    out = np.empty(len(faces))
    for k in range(len(faces)):
        a, b, c = faces[k, 0], faces[k, 1], faces[k, 2]
        u0, u1, u2 = vertices[b, 0] - vertices[a, 0], vertices[b, 1] - vertices[a, 1], vertices[b, 2] - vertices[a, 2]
        w0, w1, w2 = vertices[c, 0] - vertices[a, 0], vertices[c, 1] - vertices[a, 1], vertices[c, 2] - vertices[a, 2]
        c0, c1, c2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
        out[k] = 0.5 * np.sqrt((c0 * c0 + c1 * c1) + c2 * c2)
    return out


@numba.njit(cache=True)
def _face_points(vertices, faces, pick, r1, r2):
    """(n, 3): (1 - s) a + s (1 - r2) b + s r2 c in face pick[i], s = sqrt(r1[i]): uniform over a triangle."""
    out = np.empty((len(pick), 3))
    for i in range(len(pick)):
        s = np.sqrt(r1[i])
        wa, wb, wc = 1 - s, s * (1 - r2[i]), s * r2[i]
        a, b, c = faces[pick[i], 0], faces[pick[i], 1], faces[pick[i], 2]
        for d in range(3):
            out[i, d] = wa * vertices[a, d] + wb * vertices[b, d] + wc * vertices[c, d]
    return out


def near_surface_points(vertices: np.ndarray, faces: np.ndarray, n: int, sigmas, rng: np.random.Generator
                        ) -> np.ndarray:
    """(n, 3) surface points plus N(0, sigma^2 I) offsets (metres), in blocks, one per sigma in order.

    The n points are split over the sigmas as evenly as possible, earlier sigmas taking the
    remainder (n = 7 with two sigmas: 4 at sigmas[0], then 3 at sigmas[1]).
    """
    base = surface_points(vertices, faces, n, rng)
    sizes = [n // len(sigmas) + (k < n % len(sigmas)) for k in range(len(sigmas))]
    scale = np.repeat(np.asarray(sigmas, dtype=np.float64), sizes)
    return base + rng.normal(size=(n, 3)) * scale[:, None]


def _check_sampling_args(hand_root, rng, cube, sigmas) -> tuple[np.ndarray, tuple]:
    root = np.asarray(hand_root, dtype=np.float64)
    if root.shape != (3,) or not np.isfinite(root).all():
        raise ValueError(f"hand_root must be a finite (3,) vector, got shape {root.shape}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if not float(cube) > 0:
        raise ValueError(f"cube must be a positive edge length in metres, got {cube!r}")
    sigmas = tuple(float(s) for s in np.atleast_1d(sigmas))
    if not sigmas or not all(s > 0 and np.isfinite(s) for s in sigmas):
        raise ValueError(f"sigmas must be a non-empty sequence of positive metres, got {sigmas!r}")
    return root, sigmas


def sample_query_points(hand_vertices, hand_faces, obj_vertices, obj_faces, hand_root, rng: np.random.Generator,
                        n_hand: int = 4096, n_object: int = 2048, uniform_fraction: float = 0.1,
                        cube: float = 0.64, sigmas=DEFAULT_SIGMAS) -> tuple[np.ndarray, np.ndarray]:
    """SDF query points of one frame: hand set, then object set, then uniform set.

    Args:
        hand_vertices: (V_h, 3) vertices of the closed hand mesh, metres.
        hand_faces: (F_h, 3) its triangles.
        obj_vertices: (V_o, 3) object mesh vertices, metres, same frame as the hand.
        obj_faces: (F_o, 3) its triangles.
        hand_root: (3,) wrist joint, metres: the centre of the uniform cube.
        rng: the only source of randomness; the same generator state gives the same points.
        n_hand: nominal hand set size before the uniform set takes its share.
        n_object: nominal object set size, likewise.
        uniform_fraction: fraction of n_hand + n_object drawn uniformly in the cube.
        cube: edge length (m) of the axis-aligned cube for the uniform set.
        sigmas: Gaussian offset standard deviations (m, per axis) of the surface sets.

    Returns:
        points: (n_hand + n_object, 3) float64 metres, in set order.
        counts: (3,) int64 sizes of the hand, object and uniform sets; :func:`split_counts`
            documents exactly how they are derived.

    Raises:
        ValueError: bad meshes, counts, fraction, cube, sigmas, hand_root or rng.
    """
    hand_vertices, hand_faces = validate_mesh(hand_vertices, hand_faces)
    obj_vertices, obj_faces = validate_mesh(obj_vertices, obj_faces)
    root, sigmas = _check_sampling_args(hand_root, rng, cube, sigmas)
    counts = split_counts(n_hand, n_object, uniform_fraction)
    hand = near_surface_points(hand_vertices, hand_faces, int(counts[0]), sigmas, rng)
    obj = near_surface_points(obj_vertices, obj_faces, int(counts[1]), sigmas, rng)
    uniform = root + (rng.random((int(counts[2]), 3)) - 0.5) * float(cube)
    return np.concatenate([hand, obj, uniform], axis=0), counts


def compute_sdf_samples(points, hand_vertices, hand_faces, hand_face_parts, obj_vertices, obj_faces,
                        obj_watertight: bool, part_radius: float = 0.05, hand_pseudonormal: bool = False,
                        backend: str = "bvh") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact signed distances of query points to the hand and the object, and hand part labels.

    Args:
        points: (N, 3) metres.
        hand_vertices: (V_h, 3) vertices of the closed hand mesh, metres.
        hand_faces: (F_h, 3) its triangles.
        hand_face_parts: (F_h,) integer part label (0-15, MANO joint order) of each hand face.
        obj_vertices: (V_o, 3) object mesh vertices, metres.
        obj_faces: (F_o, 3) its triangles.
        obj_watertight: the object's repair report says watertight (pseudonormal sign); if False,
            the sign comes from the generalized winding number, which tolerates holes.
        part_radius: points farther than this (m) from the hand surface get no part label.
        hand_pseudonormal: take the hand's sign from the pseudonormal (about 1.5x faster for the
            hand, 1.3x for the whole call). Off by default: the closed MANO mesh is watertight, but
            posed it passes through itself (the thumb base through the palm, folds at strongly
            bent joints), and there the pseudonormal puts points on the wrong side (toy MANO:
            0.1-0.6% of near-surface points, up to 1 cm deep); the default winding-number sign
            gets the union of the overlapping parts right.
        backend: ``"bvh"`` or ``"igl"`` (:func:`hoidata.geometry.sdf.signed_distance`; same values).

    Returns:
        sdf_hand (N,) float64 m, sdf_object (N,) float64 m (negative inside), and part (N,) int8:
        the part of the hand face closest to the point where |sdf_hand| <= part_radius, else
        :data:`hoidata.schema.NO_PART`.
    """
    parts = np.asarray(hand_face_parts)
    if parts.ndim != 1 or len(parts) != len(np.asarray(hand_faces)) or not np.issubdtype(parts.dtype, np.integer):
        raise ValueError(f"hand_face_parts must be integers of shape ({len(np.asarray(hand_faces))},), "
                         f"got {parts.dtype} {parts.shape}")
    if not float(part_radius) >= 0:
        raise ValueError(f"part_radius must be >= 0 metres, got {part_radius!r}")
    points = as_points(points, "points")
    visit = morton_order(points) if backend == "bvh" else None  # the points' query order, found once for both meshes
    sdf_hand, hand_face = signed_distance(points, hand_vertices, hand_faces, bool(hand_pseudonormal), backend, visit)
    sdf_object, _ = signed_distance(points, obj_vertices, obj_faces, bool(obj_watertight), backend, visit)
    part = np.where(np.abs(sdf_hand) <= float(part_radius), parts[hand_face], NO_PART).astype(np.int8)
    return sdf_hand, sdf_object, part


@dataclass(frozen=True)
class SdfSampling:
    """How one frame's SDF samples are drawn and computed (the SDF part of the record settings,
    :meth:`hoidata.records.records.RecordSettings.sdf_sampling`); the fields are the arguments of
    :func:`sample_query_points` and :func:`compute_sdf_samples` of the same names (counts, metres)."""

    n_hand: int = 4096
    n_object: int = 2048
    uniform_fraction: float = 0.1
    cube: float = 0.64
    sigmas: tuple[float, ...] = DEFAULT_SIGMAS
    part_radius: float = 0.05
    hand_pseudonormal: bool = False
    backend: str = "bvh"


def build_sdf_record(hand_vertices, hand_faces, hand_face_parts, obj_vertices, obj_faces, obj_watertight: bool,
                     hand_root, rng: np.random.Generator, sampling: SdfSampling = SdfSampling()
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The ``sdf.npy`` array of one frame: sample, compute exact SDFs and quantize.

    Geometry as in :func:`sample_query_points` and :func:`compute_sdf_samples` (camera frame, metres): the
    closed hand mesh (vertices, faces, per-face part labels), the posed object mesh (vertices, faces, whether its
    repair report says watertight) and the hand root (3,); ``rng`` the only source of randomness; ``sampling``
    the counts, offsets, cube, part radius and distance backend. Returns the stored int16 (N, 6) array (xyz
    relative to ``hand_root``, both SDFs, part; see :func:`hoidata.schema.quantize_sdf`) and the (3,) int64 set
    counts for ``meta.json``'s ``sdf_counts``.
    """
    s = sampling
    points, counts = sample_query_points(hand_vertices, hand_faces, obj_vertices, obj_faces, hand_root, rng,
                                         s.n_hand, s.n_object, s.uniform_fraction, s.cube, s.sigmas)
    sdf_hand, sdf_object, part = compute_sdf_samples(points, hand_vertices, hand_faces, hand_face_parts,
                                                     obj_vertices, obj_faces, obj_watertight, s.part_radius,
                                                     s.hand_pseudonormal, s.backend)
    xyz = points - np.asarray(hand_root, dtype=np.float64)
    return quantize_sdf(xyz, sdf_hand, sdf_object, part), counts
