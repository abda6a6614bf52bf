"""The AlignSDF / gSDF per-frame SDF files: ``sdf_hand/<name>.npz``, ``sdf_obj/<name>.npz``, ``norm/<name>.npz``.

Format (written by ``zerchen/AlignSDF:scripts/sample_points/src/PreprocessMesh.cpp`` ``writeSDFToNPZ`` and
``writeNormalizeToNPZ``; read by ``zerchen/gSDF:datasets/sdf_dataset.py`` ``SDFDataset.unpack_sdf`` and
``zerchen/AlignSDF:utils/sdf_utils.py`` ``unpack_sdf_samples``):

- ``norm``: ``offset`` float32 (3,) and ``scale`` float32 (1,); a camera-frame point (metres) is
  ``xyz / scale - offset`` and a metric distance is ``sdf / scale``. The normalisation centres the union
  bounding box of hand and object and scales the farthest vertex to 1 / 1.03 (a 3 % buffer).
- ``sdf_hand`` / ``sdf_obj``: ``pos`` (Np, 4) and ``neg`` (Nn, 4) float32 rows (x, y, z, signed distance to
  this file's mesh), normalised, split by that distance (> 0 in ``pos``, <= 0 in ``neg``; negative inside);
  ``pos_other`` / ``neg_other`` (N, 1) float32, the signed distance to the other mesh; ``lab_pos`` /
  ``lab_neg`` int32 (N, 4), the own mesh's face labels, and ``lab_pos_other`` / ``lab_neg_other`` the
  other mesh's (the nearest face). Hand labels are AlignSDF's four columns: 0 coarse part (0 palm,
  1 thumb .. 5 little), 1 fine part (0 palm, then 3 per finger, thumb first, distal first), 2 contact
  region (written 0: AlignSDF's painted regions are not reproduced; no loader reads this column), 3 the
  wrist-seal flag. Object labels are 0. gSDF and AlignSDF read column 0, HOISDF column 1.

The points: AlignSDF's counts, per mesh 9,400 area-weighted surface points each offset twice by isotropic
Gaussian noise (variances 0.005 and 0.0005 in normalised units), plus 1,200 uniform in the normalised cube
[-1, 1]^3, all 20,000 kept (our distances are exact, so no point is dropped for an ambiguous sign); or
the rows of a built store (:func:`store_rows`).
"""

from __future__ import annotations

import numpy as np

from hoidata.geometry.sampling import surface_points
from hoidata.geometry.sdf import signed_distance
from hoidata.hand.topology import NUM_PARTS

BUFFER = 1.03  # PreprocessMesh's normalisation margin
SURFACE_POINTS = 9400  # 47/50 of 20,000 near-surface samples, two per surface point
UNIFORM_POINTS = 1200
VARIANCES = (0.005, 0.0005)  # normalised units squared (PreprocessMesh's variance and variance / 10)
SDF_KEYS = ("pos", "neg", "pos_other", "neg_other", "lab_pos", "lab_neg", "lab_pos_other", "lab_neg_other")

# MANO joint (0 wrist, then index, middle, pinky, ring, thumb, three each, proximal first) -> AlignSDF's
# finger order (thumb, index, middle, ring, little)
_FINGER_OF_MANO = {0: 1, 1: 2, 2: 4, 3: 3, 4: 0}


def part_label_table(n_parts: int = NUM_PARTS) -> np.ndarray:
    """(n_parts, 4) int32 AlignSDF label rows per MANO part: column 0 coarse = finger + 1 (0 for the
    wrist/palm), column 1 fine = finger * 3 + (2 - level) + 1 with level 0 proximal .. 2 distal (0 for the
    palm); columns 2 and 3 are filled in by :func:`hand_labels`."""
    table = np.zeros((n_parts, 4), np.int32)
    for part in range(1, n_parts):
        finger, level = _FINGER_OF_MANO[(part - 1) // 3], (part - 1) % 3
        table[part, :2] = finger + 1, finger * 3 + (2 - level) + 1
    return table


def hand_labels(closest_face: np.ndarray, face_parts: np.ndarray, n_open_faces: int) -> np.ndarray:
    """AlignSDF hand labels (N, 4) int32 of samples from their closest hand face (N,) and the closed hand's
    face parts (F,) (MANO joint order); column 3 is 1 where that face is one of the wrist cap's (index >=
    ``n_open_faces``, the faces that close MANO)."""
    closest_face = np.asarray(closest_face, dtype=np.int64)
    out = part_label_table()[np.asarray(face_parts, dtype=np.int64)[closest_face]]
    out[:, 3] = (closest_face >= n_open_faces).astype(np.int32)
    return out


def closest_faces(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Index (N,) of the closest face of a mesh to each point (libigl's AABB tree; no sign computed)."""
    import igl

    if len(points) == 0:
        return np.zeros(0, np.int64)
    _, face, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(points, np.float64),
                                                 np.ascontiguousarray(vertices, np.float64),
                                                 np.ascontiguousarray(faces, np.int64))
    return np.asarray(face, np.int64)


def normalisation(hand_vertices: np.ndarray, obj_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(offset float32 (3,), scale float32 (1,)) of PreprocessMesh's joint normalisation, camera frame metres.

    centre = middle of the union axis-aligned box of both meshes' vertices, max_dist = 1.03 x the farthest
    vertex from it; offset = -centre, scale = 1 / max_dist. (PreprocessMesh takes the box's z maximum from
    the hand's y maximum, a slip that only moves the centre; the correct box is used here.)
    """
    verts = np.concatenate([hand_vertices, obj_vertices]).astype(np.float64)
    centre = (verts.min(0) + verts.max(0)) / 2.0
    max_dist = np.linalg.norm(verts - centre, axis=1).max() * BUFFER
    return (-centre).astype(np.float32), np.array([1.0 / max_dist], np.float32)


def to_normalised(xyz: np.ndarray, sdf: np.ndarray, offset, scale) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) m and distances (..., N) m -> normalised float32, with the stored float32
    offset and scale (so ``xyz / scale - offset`` gives the points back to float32 precision)."""
    s = np.float64(np.asarray(scale, np.float32)[0])
    xyz_n = (np.asarray(xyz, np.float64) + np.asarray(offset, np.float32).astype(np.float64)) * s
    return xyz_n.astype(np.float32), (np.asarray(sdf, np.float64) * s).astype(np.float32)


def alignsdf_points(hand_vertices, hand_faces, obj_vertices, obj_faces, offset, scale, rng: np.random.Generator
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Query points (camera frame, metres) of the hand file and the object file, AlignSDF's counts each.

    Returns two (20000, 3) float64 arrays: per mesh 9,400 surface points + N(0, 0.005) offsets, the same
    points + N(0, 0.0005) offsets (normalised variances, i.e. metres x max_dist), then 1,200 uniform in the
    normalised cube.
    """
    max_dist = 1.0 / np.float64(np.asarray(scale, np.float32)[0])
    centre = -np.asarray(offset, np.float32).astype(np.float64)
    out = []
    for verts, faces in ((hand_vertices, hand_faces), (obj_vertices, obj_faces)):
        base = surface_points(np.asarray(verts, np.float64), np.asarray(faces), SURFACE_POINTS, rng)
        near = [base + rng.normal(size=base.shape) * np.sqrt(v) * max_dist for v in VARIANCES]
        uniform = centre + (rng.random((UNIFORM_POINTS, 3)) * 2.0 - 1.0) * max_dist
        out.append(np.concatenate(near + [uniform]))
    return out[0], out[1]


def exact_distances(points, hand_vertices, hand_faces, obj_vertices, obj_faces, obj_watertight: bool):
    """Signed distances (m, negative inside) of points (N, 3) to the hand (winding-number sign: a posed MANO
    mesh passes through itself) and the object, and the closest hand face (N,)."""
    sdf_hand, hand_face = signed_distance(points, hand_vertices, hand_faces, watertight=False)
    sdf_obj, _ = signed_distance(points, obj_vertices, obj_faces, watertight=bool(obj_watertight))
    return sdf_hand, sdf_obj, hand_face


def branch_arrays(xyz_n: np.ndarray, own: np.ndarray, other: np.ndarray, labels: np.ndarray,
                  labels_other: np.ndarray) -> dict[str, np.ndarray]:
    """One file's arrays (see the module docstring) from normalised rows: xyz (N, 3), own and other distance
    (N,), own and other labels (N, 4); split by the sign of the own distance (> 0 is ``pos``)."""
    pos = own > 0
    arrays = {}
    for name, keep in (("pos", pos), ("neg", ~pos)):
        arrays[name] = np.concatenate([xyz_n[keep], own[keep, None]], axis=1).astype(np.float32)
        arrays[f"{name}_other"] = other[keep, None].astype(np.float32)
        arrays[f"lab_{name}"] = labels[keep].astype(np.int32)
        arrays[f"lab_{name}_other"] = labels_other[keep].astype(np.int32)
    return arrays


def frame_files(xyz_hand, xyz_obj, dist_hand_pts, dist_obj_pts, hand_lab_hand_pts, hand_lab_obj_pts, offset, scale
                ) -> dict[str, dict[str, np.ndarray]]:
    """{'sdf_hand': arrays, 'sdf_obj': arrays, 'norm': arrays} of one frame.

    Args:
        xyz_hand: (Nh, 3) query points of the hand file, camera frame, metres.
        xyz_obj: (No, 3) query points of the object file, likewise.
        dist_hand_pts: (2, Nh) signed distances of the hand file's points to (hand, object), metres.
        dist_obj_pts: (2, No) the same for the object file's points.
        hand_lab_hand_pts: (Nh, 4) AlignSDF labels of the closest hand face, hand file's points.
        hand_lab_obj_pts: (No, 4) the same for the object file's points.
        offset: (3,) the frame's normalisation offset (:func:`normalisation`).
        scale: the frame's normalisation scale.
    """
    xh, dh = to_normalised(xyz_hand, dist_hand_pts, offset, scale)
    xo, do = to_normalised(xyz_obj, dist_obj_pts, offset, scale)
    zeros_h, zeros_o = np.zeros((len(xh), 4), np.int32), np.zeros((len(xo), 4), np.int32)
    return {"sdf_hand": branch_arrays(xh, dh[0], dh[1], hand_lab_hand_pts, zeros_h),
            "sdf_obj": branch_arrays(xo, do[1], do[0], zeros_o, hand_lab_obj_pts),
            "norm": {"offset": np.asarray(offset, np.float32), "scale": np.asarray(scale, np.float32)}}


def loader_problem(arrays: dict[str, np.ndarray], filter_dist: float = 2.0) -> str | None:
    """Why gSDF's ``unpack_sdf`` would fail on one file's arrays (None if it would not): it keeps rows with
    both distances below ``filter_dist`` in magnitude and then indexes ``pos`` and ``neg``, so each needs a row."""
    for name in ("pos", "neg"):
        rows, other = arrays[name], arrays[f"{name}_other"][:, 0]
        if not np.count_nonzero((np.abs(rows[:, 3]) < filter_dist) & (np.abs(other) < filter_dist)):
            return f"no '{name}' row within |sdf| < {filter_dist} (normalised): gSDF's unpack_sdf would fail"
    return None


def store_rows(sdf_rows: np.ndarray, counts: np.ndarray, hand_root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A record's stored ``sdf.npy`` (int16) -> (hand file rows, object file rows), each (N, 5) float64:
    camera-frame xyz (metres), sdf_hand, sdf_object. The hand set and the object set go to their own file,
    the uniform set to both."""
    from hoidata.schema import dequantize_sdf

    xyz, sdf_h, sdf_o, _ = dequantize_sdf(sdf_rows)
    rows = np.concatenate([xyz.astype(np.float64) + np.asarray(hand_root, np.float64),
                           sdf_h[:, None].astype(np.float64), sdf_o[:, None].astype(np.float64)], axis=1)
    n_h, n_o, _ = (int(c) for c in counts)
    uniform = rows[n_h + n_o:]
    return np.concatenate([rows[:n_h], uniform]), np.concatenate([rows[n_h:n_h + n_o], uniform])
