"""A procedural hand written in the exact MANO v1.2 file format (MANO_RIGHT.pkl / MANO_LEFT.pkl).

The real MANO files are licensed and cannot be shipped, so tests and toy datasets use this hand. It
has the real files' keys, shapes, dtypes and pickled layout (Python-2 era protocol 2, ``shapedirs`` as
a chumpy ``Select`` over a chumpy ``Ch`` of 20 directions, a scipy ``csc_matrix`` ``J_regressor``),
MANO's kinematic tree and finger order, and its fingertips at MANO's tip vertex indices, so every
MANO code path runs on it unchanged.

Rig (all derived from the geometry in :mod:`hoidata.toy.hand_mesh`):

- joints: the wrist, then three joints per finger along each finger axis; ``J_regressor`` rows
  average nearby vertices with weights solved so that they reproduce those joints;
- skinning weights: phalanx by phalanx with 4 mm blends at the joints, palm on the wrist with soft
  influence from the knuckles and the thumb's CMC joint;
- shape directions: size, finger length, palm width, finger and palm thickness, per-finger lengths,
  then 10 smooth low-amplitude fields; pose correctives: knuckle bulges along the normals;
- PCA pose space: principal components of 1554 synthetic grasps (curl, spread, thumb opposition), which span
  11 directions; the other 34 rows complete the basis without a decomposition (:func:`pca_basis`).

Fingers flex about ``side = back x axis`` (``+z`` for the index finger), so positive angles curl them
toward the palm. The left file mirrors the right one through x -> -x and, like the real MANO_LEFT.pkl,
stores the right hand's ``shapedirs`` unchanged (the known bug that :func:`read_mano_file` fixes).
"""

from __future__ import annotations

import os
import pickle
import sys
import types
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import scipy.sparse

from hoidata.geometry.mirror import mirror_axis_angle
from hoidata.hand.model import MANO_PARENTS, NUM_JOINTS, TIP_VERTICES
from hoidata.toy.hand_mesh import (
    BACK_AXIS,
    LENGTH_AXIS,
    WIDTH_AXIS,
    HandMesh,
    build_hand_mesh,
)

# MANO joint ids of each finger's three joints.
FINGER_JOINTS = {"index": (1, 2, 3), "middle": (4, 5, 6), "pinky": (7, 8, 9), "ring": (10, 11, 12), "thumb": (13, 14, 15)}
TIP_ORDER = ("thumb", "index", "middle", "ring", "pinky")
SEED = 20240617


def mano_tip_slots() -> dict[int, tuple[str, str]]:
    """Vertex index -> (finger, 'tip'|'pad'|'nail'): where the procedural vertices must land."""
    slots = {}
    for finger, tip, ho3d, left in zip(TIP_ORDER, TIP_VERTICES[("manopth", "right")], TIP_VERTICES[("ho3d", "right")],
                                       TIP_VERTICES[("manopth", "left")]):
        slots[tip] = (finger, "tip")
        if ho3d != tip:
            slots[ho3d] = (finger, "pad")
        if left != tip:
            slots[left] = (finger, "nail")
    return slots


def _order_vertices(mesh: HandMesh) -> np.ndarray:
    """Permutation new_index[old] placing each fingertip (and its pad/nail neighbour) at MANO's index."""
    n = len(mesh.vertices)
    target = np.full(n, -1)
    for index, (finger, kind) in mano_tip_slots().items():
        geo = mesh.fingers[finger]
        if kind == "tip":
            old = geo.tip_id
        else:
            back = np.cross(geo.axis, geo.side)
            heights = (mesh.vertices[geo.last_ring] - geo.joints[3]) @ back
            old = geo.last_ring[np.argmin(heights) if kind == "pad" else np.argmax(heights)]
        target[old] = index
    free = iter(sorted(set(range(n)) - set(target[target >= 0].tolist())))
    for old in range(n):
        if target[old] < 0:
            target[old] = next(free)
    return target


def _smooth_step(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def skinning_weights(mesh: HandMesh, joints: np.ndarray, blend: float = 0.004) -> np.ndarray:
    """(V, 16) weights: finger vertices by phalanx, palm vertices on the wrist with soft knuckle influence."""
    w = np.zeros((len(mesh.vertices), NUM_JOINTS))
    palm = mesh.palm_ids
    influence = np.zeros((len(palm), NUM_JOINTS))
    for name, geo in mesh.fingers.items():
        j0 = FINGER_JOINTS[name][0]
        amp, sigma = (0.9, 0.022) if name == "thumb" else (0.6, 0.011)
        d = np.linalg.norm(mesh.vertices[palm] - joints[j0], axis=1)
        influence[:, j0] = amp * np.exp(-((d / sigma) ** 2))
    influence[:, 0] = np.clip(1.0 - influence.sum(1), 0.05, None)
    w[palm] = influence / influence.sum(1, keepdims=True)
    for name, geo in mesh.fingers.items():
        ids, s = geo.vertex_ids, geo.stations
        bounds = np.cumsum(np.linalg.norm(np.diff(geo.joints, axis=0), axis=1))[:2]
        up1 = _smooth_step((s - bounds[0] + blend) / (2 * blend))
        up2 = _smooth_step((s - bounds[1] + blend) / (2 * blend))
        a, b, c = FINGER_JOINTS[name]
        w[ids, a], w[ids, b], w[ids, c] = 1 - up1, up1 - up2, up2
    return w


def joint_regressor(vertices: np.ndarray, joints: np.ndarray, k: int = 96) -> scipy.sparse.csc_matrix:
    """(16, V) sparse regressor: non-negative weights on the k nearest vertices whose mean is the joint.

    Starts from Gaussian weights and applies the smallest correction that makes the weighted mean hit
    the joint exactly, then clips negatives (rare, tiny) and renormalises.
    """
    rows, cols, vals = [], [], []
    for j, p in enumerate(joints):
        d = np.linalg.norm(vertices - p, axis=1)
        near = np.argsort(d, kind="stable")[:k]
        w = np.exp(-((d[near] / (d[near].max() * 0.6)) ** 2))
        w /= w.sum()
        a = np.vstack([vertices[near].T, np.ones(k)])  # (4, k)
        w = w + a.T @ np.linalg.solve(a @ a.T, np.append(p, 1.0) - a @ w)
        w = np.clip(w, 0.0, None)
        w /= w.sum()
        rows += [j] * k
        cols += near.tolist()
        vals += w.tolist()
    return scipy.sparse.csc_matrix((vals, (rows, cols)), shape=(len(joints), len(vertices)))


def shape_directions(mesh: HandMesh, n_smooth: int = 10) -> np.ndarray:
    """(V, 3, 10 + n_smooth) shape directions in metres per unit beta (see the module docstring)."""
    v = mesh.vertices
    centre = mesh.wrist_center
    dirs = np.zeros((len(v), 3, 10 + n_smooth))
    dirs[:, :, 0] = 0.05 * (v - centre)  # overall size, +5 % per unit
    palm = mesh.palm_ids
    rel = v[palm] - centre
    dirs[palm, :, 2] = 0.06 * (rel @ WIDTH_AXIS)[:, None] * WIDTH_AXIS  # palm width
    dirs[palm, :, 4] = 0.10 * (rel @ BACK_AXIS)[:, None] * BACK_AXIS  # palm thickness
    per_finger = {"thumb": 5, "index": 6, "middle": 7, "ring": 8, "pinky": 9}
    for name, geo in mesh.fingers.items():
        ids, s = geo.vertex_ids, geo.stations
        along = 0.08 * s[:, None] * geo.axis  # stretch away from the knuckle
        dirs[ids, :, 1] = along
        dirs[ids, :, per_finger[name]] = along
        dirs[ids, :, 2] = 0.06 * ((geo.joints[0] - centre) @ WIDTH_AXIS) * WIDTH_AXIS
        rel_f = v[ids] - geo.joints[0]
        radial = rel_f - (rel_f @ geo.axis)[:, None] * geo.axis
        dirs[ids, :, 3] = 0.10 * radial  # finger thickness
    rng = np.random.default_rng(SEED)
    for k in range(10, 10 + n_smooth):
        for _ in range(3):  # a few broad bumps in random directions, about 1 mm
            c = v[rng.integers(len(v))]
            amp = rng.normal(size=3) * 0.0006
            dirs[:, :, k] += np.exp(-np.sum((v - c) ** 2, 1) / 0.03 ** 2)[:, None] * amp
    return dirs


def pose_directions(normals: np.ndarray, weights: np.ndarray, bulge: float = 0.0015) -> np.ndarray:
    """(V, 3, 135) pose correctives: knuckle bulge along the normal as a joint bends.

    Only the diagonal of R - I is used: it equals cos(angle) - 1 on the two axes orthogonal to the
    rotation axis, so the offset grows with the bend angle whatever the axis, and it is unchanged by
    mirroring (which keeps the diagonal of R), as a real MANO left/right pair behaves.
    """
    dirs = np.zeros((len(normals), 3, (NUM_JOINTS - 1) * 9))
    for j in range(1, NUM_JOINTS):
        mix = 4.0 * weights[:, j] * (1.0 - weights[:, j])  # 1 where the weight crosses 0.5
        for i in range(3):
            dirs[:, :, 9 * (j - 1) + 4 * i] = -bulge * mix[:, None] * normals
    return dirs


def synthetic_grasps(mesh: HandMesh, n: int = 1554) -> np.ndarray:
    """(n, 45) finger poses (MANO joints 1..15, axis-angle, flat convention) of plausible grasps."""
    rng = np.random.default_rng(SEED + 1)
    poses = np.zeros((n, 15, 3))
    curl = rng.uniform(0.0, 1.2, size=n)
    for name, (j1, j2, j3) in FINGER_JOINTS.items():
        geo = mesh.fingers[name]
        c = np.clip(curl + rng.normal(0, 0.25, n), -0.1, 1.5)
        spread = rng.normal(0, 0.12 if name != "thumb" else 0.25, n)
        gains = (0.6, 0.7, 0.5) if name == "thumb" else (0.9, 1.1, 0.7)
        for joint, gain in zip((j1, j2, j3), gains):
            poses[:, joint - 1] = (gain * c)[:, None] * geo.side
        poses[:, j1 - 1] += spread[:, None] * BACK_AXIS
        if name == "thumb":  # opposition: the thumb turns about its own axis
            poses[:, j1 - 1] += rng.normal(0.3, 0.2, n)[:, None] * geo.axis
    return poses.reshape(n, 45)


def complete_basis(rows: np.ndarray, floor: float = 0.1) -> np.ndarray:
    """Orthonormal rows (r, n) -> (n, n): the given rows, then the unit vectors e_0, e_1, ... in order with the
    span so far projected out (twice, for round-off), each kept when what is left of it is longer than ``floor``.

    No decomposition: every added row is a fixed function of ``rows`` (a unit vector's residual, positive along
    that unit vector), so it moves by round-off when ``rows`` do, whatever LAPACK kernel the CPU runs.
    """
    basis = [np.asarray(r, dtype=np.float64) for r in rows]
    n = len(basis[0])
    for i in range(n):
        if len(basis) == n:
            break
        v = np.eye(n)[i]
        for _ in range(2):
            v = v - sum((b * v).sum() * b for b in basis)
        if np.sqrt((v * v).sum()) > floor:
            basis.append(v / np.sqrt((v * v).sum()))
    if len(basis) != n:
        raise ValueError(f"completing {len(rows)} rows to a basis of {n} found only {len(basis)}")
    return np.stack(basis)


def pca_basis(samples: np.ndarray, rtol: float = 1e-8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA of (n, 45) poses -> (components (45, 45) rows by decreasing variance, mean (45,), coeffs (n, 45)).

    The grasps span only ``rank`` directions (11: five curls, five spreads, the thumb's opposition; the next
    singular value is 1e-14 of the first). Those come from the SVD, well separated (gaps >= 1.5 % of the
    values), each with its largest entry made positive. The remaining rows span the null space, where an SVD's
    basis is arbitrary and changes with the BLAS kernel (Haswell's and SkylakeX's differed by up to 1.6 per
    entry): :func:`complete_basis` builds them without a decomposition.
    """
    mean = samples.mean(0)
    centred = samples - mean
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    rank = int((sv > rtol * sv[0]).sum())
    top = vt[:rank]
    signs = np.sign(top[np.arange(rank), np.abs(top).argmax(1)])  # deterministic sign per component
    comps = complete_basis(top * signs[:, None])
    return comps, mean, centred @ comps.T


def build_toy_mano() -> dict:
    """All arrays of the procedural right hand, keyed as in MANO_RIGHT.pkl (before chumpy wrapping)."""
    import trimesh

    from hoidata.hand import topology

    mesh = build_hand_mesh()
    joints = np.zeros((NUM_JOINTS, 3))
    joints[0] = mesh.wrist_center + LENGTH_AXIS * 0.006
    for name, ids in FINGER_JOINTS.items():
        joints[list(ids)] = mesh.fingers[name].joints[:3]
    weights = skinning_weights(mesh, joints)
    closed, loop = topology.close_faces(mesh.faces, len(mesh.vertices))
    normals = trimesh.Trimesh(topology.close_vertices(mesh.vertices, loop), closed, process=False).vertex_normals
    shapedirs = shape_directions(mesh)
    posedirs = pose_directions(normals[: len(mesh.vertices)], weights)
    comps, mean, coeffs = pca_basis(synthetic_grasps(mesh))
    # Centre the template like MANO's (vertex mean at the origin), then fix the vertex order.
    offset = mesh.vertices.mean(0)
    order = _order_vertices(mesh)
    inverse = np.argsort(order)
    verts = (mesh.vertices - offset)[inverse]
    regressor = joint_regressor(verts, joints - offset)
    return {
        "v_template": verts, "shapedirs": shapedirs[inverse], "posedirs": posedirs[inverse],
        "J_regressor": regressor, "J": np.asarray(regressor @ verts), "weights": weights[inverse],
        "kintree_table": np.array([[p % 2 ** 32 for p in MANO_PARENTS], list(range(NUM_JOINTS))], dtype=np.int64),
        "f": order[mesh.faces].astype(np.uint32), "hands_components": comps, "hands_mean": mean,
        "hands_coeffs": coeffs, "bs_style": "lbs", "bs_type": "lrotmin",
    }


def mirror_to_left(right: dict) -> dict:
    """The left-hand arrays from the right ones: x -> -x, with MANO_LEFT.pkl's unfixed shapedirs.

    Faces are rewound so the left surface also faces outward; pose data (PCA basis and mean) is
    mirrored per joint; posedirs pick up the sign of the reflected output axis and of the reflected
    rotation-matrix entries (R -> M R M flips the sign of the entries in row 0 xor column 0).
    """
    s = np.array([-1.0, 1.0, 1.0])
    entry_sign = np.tile(np.outer(s, s).ravel(), NUM_JOINTS - 1)  # (135,)
    left = dict(right)
    left["v_template"] = right["v_template"] * s
    left["J"] = right["J"] * s
    left["posedirs"] = right["posedirs"] * s[None, :, None] * entry_sign[None, None, :]
    left["f"] = right["f"][:, ::-1].copy()
    left["hands_components"] = mirror_axis_angle(right["hands_components"])
    left["hands_mean"] = mirror_axis_angle(right["hands_mean"])
    left["shapedirs"] = right["shapedirs"].copy()  # the real file's bug, kept on purpose
    return left


def _chumpy_class(module: str, name: str):
    cls = type(name, (), {"__module__": module})
    cls.__qualname__ = name
    return cls


@contextmanager
def chumpy_stand_ins():
    """Temporarily provide ``chumpy.ch.Ch`` and ``chumpy.reordering.Select`` classes for pickling.

    They pickle exactly as chumpy objects do (class reference plus the instance ``__dict__``), so the
    written file has the real MANO file's layout. Real modules in sys.modules are restored afterwards.
    """
    names = ("chumpy", "chumpy.ch", "chumpy.reordering")
    saved = {n: sys.modules.get(n) for n in names}
    mods = {n: types.ModuleType(n) for n in names}
    mods["chumpy.ch"].Ch = _chumpy_class("chumpy.ch", "Ch")
    mods["chumpy.reordering"].Select = _chumpy_class("chumpy.reordering", "Select")
    sys.modules.update(mods)
    try:
        yield mods["chumpy.ch"].Ch, mods["chumpy.reordering"].Select
    finally:
        for n, m in saved.items():
            if m is None:
                sys.modules.pop(n, None)
            else:
                sys.modules[n] = m


def _chumpy_state(**terms) -> dict:
    """Instance dict of a chumpy object as chumpy's __getstate__ leaves it (caches removed)."""
    base = {"_dirty_vars": set(), "_itr": None, "_depends_on_deps": {}, "_make_dense": False, "_make_sparse": False}
    return {**base, **terms}


def wrap_shapedirs(shapedirs: np.ndarray, ch_cls, select_cls, n: int = 10):
    """shapedirs (V, 3, S) -> chumpy Select of the first n directions over a Ch of all S, as in MANO v1.2."""
    full = ch_cls.__new__(ch_cls)
    full.__dict__.update(_chumpy_state(x=shapedirs))
    sel = select_cls.__new__(select_cls)
    idxs = np.arange(shapedirs.size).reshape(shapedirs.shape)[:, :, :n].ravel()
    sel.__dict__.update(_chumpy_state(a=full, idxs=idxs, preferred_shape=shapedirs.shape[:2] + (n,)))
    return sel


def write_mano_pickle(path: Path, arrays: dict, protocol: int = 2) -> None:
    """Write MANO arrays as a MANO-format pickle (shapedirs chumpy-wrapped), atomically."""
    with chumpy_stand_ins() as (ch_cls, select_cls):
        content = dict(arrays)
        content["shapedirs"] = wrap_shapedirs(arrays["shapedirs"], ch_cls, select_cls)
        data = pickle.dumps(content, protocol=protocol)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_toy_mano(out_dir: str | os.PathLike) -> dict[str, Path]:
    """Write MANO_RIGHT.pkl and MANO_LEFT.pkl of the procedural hand into `out_dir`.

    Deterministic: the same bytes on every run on one machine. Across CPUs the float64 values agree to round-off
    (~1e-15: the BLAS/LAPACK kernel and numpy's SIMD paths differ in the last bits), so tests compare them with a
    tolerance, never by their bytes (docs/development.md, "Floating-point goldens").
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    right = build_toy_mano()
    paths = {"right": out / "MANO_RIGHT.pkl", "left": out / "MANO_LEFT.pkl"}
    write_mano_pickle(paths["right"], right)
    write_mano_pickle(paths["left"], mirror_to_left(right))
    return paths
