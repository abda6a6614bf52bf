"""The contact definitions of earlier papers, restated so that they give their scripts' numbers on the same meshes
(docs/plausibility.md, "Older definitions, beside the exact ones"; tests/golden/contact/ holds the scripts' own
numbers).

- ``gsdf`` (gSDF, Chen et al. 2023, ``tools/eval_contact.py``; AlignSDF and HORT report the same): libigl's
  signed distance (its default sign, the winding number) of every hand vertex, each moved by +1e-10 m, to the
  object. A frame is in contact only when the smallest one is <= 0 (some vertex inside: touching is not contact);
  the penetration depth is then |that distance| in cm, and the intersection volume counts the points of a 5 mm
  grid that are inside both meshes (libigl signed distance < 0), 0.125 cm^3 each. The grid starts 5 mm below the
  overlap of the two vertex boxes and runs ``int((extent + 10 mm) / 5 mm) + 1`` points per axis, its coordinates
  accumulated in float32 (a torch loop there, the same float32 sums here). Out of contact, or with vertex boxes
  that do not overlap (strictly, on every axis), all three are 0. The hand is the closed one, every vertex (gSDF's
  reconstructed hands are closed meshes).
- ``grasptta`` (GraspTTA, Jiang et al. 2021, ``gen_diverse_grasp_ho3d.py``; the volume is obman_train's
  ``intersect_vox``, also in GanHand): trimesh voxelizes the object's *surface* at 5 mm, counts the voxel centres
  inside the hand (trimesh's ray test ``contains``) and multiplies by 0.125 cm^3; contact is some hand vertex
  inside the object (trimesh's ray test) or within 5 mm of its surface (trimesh's closest point). The hand is MANO's
  own open mesh (778 vertices, no wrist cap), as there. trimesh's ray test casts a second ray, in a direction drawn
  from its shared generator (seeded from OS entropy), where two rays disagree, so GraspTTA's own number can change
  from run to run (toy frame 8: 6.25 or 5.0 cm^3, or 4.625 after the draws other code made in one process). Here that
  draw comes from a generator seeded with ``RAY_SEED`` at every call: the number repeats.

Both take one frame's meshes in metres (one frame, e.g. the camera's) and return contact (0/1), penetration depth
(mm; the ``grasptta`` depth is the exact one, which GraspTTA's scripts do not define differently) and volume (cm^3).
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

GRID = 0.005  # metres: gSDF's grid step
PITCH = 0.005  # metres: GraspTTA's voxel pitch
CONTACT_TOL = 0.005  # metres: GraspTTA's penetration_tol
NUDGE = 1e-10  # metres: gSDF moves the hand vertices by this before the signed distance
DEFINITIONS = ("exact", "gsdf", "grasptta")
RAY_SEED = 0  # the generator trimesh's ray test re-casts disputed rays from (module docstring)


@contextmanager
def repeatable_rays(seed: int = RAY_SEED):
    """trimesh's shared generator (``trimesh.util.random_generator()``) replaced by a fresh one seeded with `seed`
    for the block, then put back."""
    import trimesh.util

    saved = trimesh.util._RANDOM_DEFAULT
    trimesh.util._RANDOM_DEFAULT = np.random.default_rng(seed)
    try:
        yield
    finally:
        trimesh.util._RANDOM_DEFAULT = saved


def _igl_signed(points, vertices, faces) -> np.ndarray:
    import igl

    out = igl.signed_distance(np.ascontiguousarray(points, dtype=np.float64),
                              np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int64))
    return np.asarray(out[0])


def gsdf_grid(lo: np.ndarray, hi: np.ndarray, step: float = GRID) -> np.ndarray:
    """(N, 3) float32 grid points over the box [lo, hi] widened by one step, in gSDF's order and float32 sums."""
    start = np.asarray(lo, np.float64) - step
    stop = np.asarray(hi, np.float64) + step
    axes = []
    for d in range(3):
        n = int((stop[d] - start[d]) / step) + 1
        values = np.empty(n, np.float32)
        values[0] = np.float32(start[d])
        for i in range(1, n):  # one float32 addition per point, as the torch loop
            values[i] = values[i - 1] + np.float32(step)
        axes.append(values)
    grid = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.reshape(-1) for g in grid], axis=1)


def gsdf_frame(hand_v, hand_f, obj_v, obj_f) -> dict[str, float]:
    """gSDF's contact, penetration depth and grid volume of one frame (see the module docstring)."""
    hand_v, obj_v = np.asarray(hand_v, np.float64), np.asarray(obj_v, np.float64)
    nearest = float(_igl_signed(hand_v + NUDGE, obj_v, obj_f).min())
    zero = {"contact": 0.0, "penetration_depth_mm": 0.0, "intersection_volume_cm3": 0.0}
    if nearest > 0:
        return zero
    lo, hi = np.maximum(hand_v.min(0), obj_v.min(0)), np.minimum(hand_v.max(0), obj_v.max(0))
    if not np.all(hi > lo):  # gSDF's bounding_box_intersection: boxes that do not overlap give 0, 0, 0
        return zero
    out = {**zero, "contact": 1.0, "penetration_depth_mm": abs(nearest) * 1e3}
    points = gsdf_grid(lo, hi)
    in_hand = points[_igl_signed(points, hand_v, hand_f) < 0]
    count = int((_igl_signed(in_hand, obj_v, obj_f) < 0).sum()) if len(in_hand) else 0
    out["intersection_volume_cm3"] = count * GRID ** 3 * 1e6
    return out


def _open_hand(hand_v, hand_f, n_points: int):
    import trimesh

    hand_v, hand_f = np.asarray(hand_v, np.float64)[:n_points], np.asarray(hand_f)
    return trimesh.Trimesh(vertices=hand_v, faces=hand_f[(hand_f < n_points).all(1)])  # their default processing


def surface_voxel_volume(hand_v, hand_f, obj_v, obj_f, pitch: float = PITCH, n_points: int = 778) -> float:
    """obman_train's ``intersect_vox``: the object's surface voxels (``pitch`` metres) whose centres lie in the open
    hand mesh (trimesh's ray test), times pitch^3; m^3."""
    import trimesh

    obj = trimesh.Trimesh(vertices=np.asarray(obj_v, np.float64), faces=np.asarray(obj_f))
    with repeatable_rays():
        inside = _open_hand(hand_v, hand_f, n_points).contains(obj.voxelized(pitch=pitch).points)
    return float(inside.sum()) * pitch ** 3


def grasptta_frame(hand_v, hand_f, obj_v, obj_f, n_points: int = 778) -> dict[str, float]:
    """GraspTTA's surface-voxel volume and 5 mm contact of one frame (see the module docstring); ``hand_v``'s
    first ``n_points`` vertices and the faces among them are MANO's open mesh."""
    import trimesh

    from hoisdf.scoring.plausibility import penetration_depth

    hand_v = np.asarray(hand_v, np.float64)[:n_points]
    obj = trimesh.Trimesh(vertices=np.asarray(obj_v, np.float64), faces=np.asarray(obj_f))
    _, distance, _ = trimesh.proximity.closest_point(obj, hand_v)
    with repeatable_rays():
        touching = obj.ray.contains_points(hand_v) | (distance <= CONTACT_TOL)
    return {"contact": float(touching.any()),
            "penetration_depth_mm": penetration_depth(hand_v, obj_v, obj_f) * 1e3,
            "intersection_volume_cm3": surface_voxel_volume(hand_v, hand_f, obj_v, obj_f, PITCH, n_points) * 1e6}


def legacy_frame(definition: str, hand_v, hand_f, obj_v, obj_f, n_points: int = 778) -> dict[str, float]:
    """One frame under ``gsdf`` or ``grasptta``."""
    if definition == "gsdf":
        return gsdf_frame(hand_v, hand_f, obj_v, obj_f)
    if definition == "grasptta":
        return grasptta_frame(hand_v, hand_f, obj_v, obj_f, n_points)
    raise ValueError(f"unknown contact definition {definition!r}; choose from {', '.join(DEFINITIONS)}")


def _job(job: tuple) -> dict[str, float]:
    definition, sample, n_points = job
    return legacy_frame(definition, *sample, n_points=n_points)


def legacy_many(definition: str, samples, workers: int = 1, n_points: int = 778) -> list[dict[str, float]]:
    """:func:`legacy_frame` of every sample ``(hand_v, hand_f, obj_v, obj_f)``, in order, on ``workers`` spawned
    processes (0 or 1: this one)."""
    if definition not in DEFINITIONS[1:]:
        raise ValueError(f"unknown contact definition {definition!r}; choose from {', '.join(DEFINITIONS)}")
    jobs = [(definition, tuple(s), n_points) for s in samples]
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn")) as pool:
            return list(pool.map(_job, jobs, chunksize=1))
    return [_job(j) for j in jobs]


def legacy_summary(frames: list[dict[str, float]]) -> dict[str, float]:
    """Means over frames, as the scripts report them: ``contact_ratio``, ``penetration_depth_mm`` (gSDF: 0 for a
    frame out of contact, counted), ``intersection_volume_cm3``; NaN for no frames."""
    def mean(key):
        return float(np.mean([f[key] for f in frames])) if frames else float("nan")
    return {"contact_ratio": mean("contact"), "penetration_depth_mm": mean("penetration_depth_mm"),
            "intersection_volume_cm3": mean("intersection_volume_cm3"), "num_samples": len(frames)}
