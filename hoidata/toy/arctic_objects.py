"""Toy articulated objects in ARCTIC's template layout (``meta/object_vtemplates/<name>/``, millimetres).

Each of ARCTIC's eleven object names gets a box with a hinged lid of its own size: the base (parts.json label 1,
ARCTIC's root part) and the lid (label 0, the part ARCTIC's code turns) are two closed boxes, gridded in cells of
at most 8 mm, the lid's hinge on the canonical z axis so that a positive articulation lifts it
(docs/datasets.md, "ARCTIC"). Beside ``mesh.obj`` and ``parts.json``: ``object_params.json`` (mocap markers,
box corners, 16 keypoints per part), ``top/bottom_keypoints_300.json`` (farthest-point samples of each part's surface),
``top.obj`` / ``bottom.obj`` (shipped by ARCTIC, read by none of its code) and ``meta/object_meta.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hoidata.atomic import write_atomic
from hoidata.objects.arctic import ARCTIC_OBJECTS

MAX_EDGE_MM = 8.0
LID_GAP_MM = 1.0
# base width (x), height (y), depth (z) and lid thickness, millimetres; one row per ARCTIC name, in its order
SIZES_MM = ((120, 70, 90, 14), (150, 60, 110, 12), (60, 130, 45, 16), (200, 18, 150, 10), (170, 90, 120, 14),
            (90, 110, 80, 18), (140, 14, 100, 8), (110, 120, 90, 16), (130, 40, 130, 20), (100, 12, 40, 8),
            (75, 10, 40, 6))


def box_mesh(lo, hi, max_edge: float = MAX_EDGE_MM) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-facing box between corners ``lo`` and ``hi`` (mm): each face a regular grid of cells no
    longer than ``max_edge`` along either side, two triangles a cell, the faces sharing their edge vertices."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    axes = [np.linspace(lo[a], hi[a], int(np.ceil((hi[a] - lo[a]) / max_edge)) + 1) for a in range(3)]
    points, faces = [], []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3  # e_b x e_c = e_a
        u, v = np.meshgrid(axes[b], axes[c], indexing="ij")
        nu, nv = u.shape
        idx = np.arange(nu * nv).reshape(nu, nv)
        q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
        for side, value in ((1, hi[a]), (-1, lo[a])):
            grid = np.zeros((nu * nv, 3))
            grid[:, a], grid[:, b], grid[:, c] = value, u.ravel(), v.ravel()
            tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
            faces.append((tris if side > 0 else tris[:, ::-1]) + sum(len(p) for p in points))
            points.append(grid)
    allp = np.concatenate(points)
    unique, inverse = np.unique(np.round(allp, 6), axis=0, return_inverse=True)
    return unique, inverse.reshape(-1)[np.concatenate(faces)]


def farthest_points(points: np.ndarray, n: int) -> np.ndarray:
    """``n`` rows of ``points`` by farthest-point sampling from row 0 (deterministic)."""
    chosen = [0]
    dist = np.linalg.norm(points - points[0], axis=1)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen]


def corners(lo, hi) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], np.float64)


def toy_object(index: int) -> dict:
    """Object ``index`` of :data:`ARCTIC_OBJECTS`: its parts' boxes and meshes (mm)."""
    w, h, d, t = SIZES_MM[index]
    base = ((-w, -h, -d / 2), (0.0, 0.0, d / 2))
    lid = ((-w, LID_GAP_MM, -d / 2), (0.0, LID_GAP_MM + t, d / 2))
    return {"name": ARCTIC_OBJECTS[index], "top_box": lid, "bottom_box": base,
            "top": box_mesh(*lid), "bottom": box_mesh(*base)}


def _obj_text(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    rows = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return ("\n".join(rows) + "\n").encode()


def _json_bytes(value) -> bytes:
    return (json.dumps(value) + "\n").encode()


def write_toy_template(folder: Path, obj: dict) -> float:
    """Write one template folder; returns its diameter (metres: the largest distance between two vertices)."""
    (tv, tf), (bv, bf) = obj["top"], obj["bottom"]
    vertices, faces = np.concatenate([tv, bv]), np.concatenate([tf, bf + len(tv)])
    labels = [0] * len(tv) + [1] * len(bv)  # 0: the part ARCTIC's code turns ("top"); 1: the root ("bottom")
    folder.mkdir(parents=True, exist_ok=True)
    write_atomic(folder / "mesh.obj", _obj_text(vertices, faces))
    write_atomic(folder / "top.obj", _obj_text(tv, tf))
    write_atomic(folder / "bottom.obj", _obj_text(bv, bf))
    write_atomic(folder / "parts.json", _json_bytes(labels))
    for part in ("top", "bottom"):  # from a finer grid of the part's surface: a small part has < 300 vertices
        dense = box_mesh(*obj[f"{part}_box"], max_edge=2.0)[0]
        keypoints = {"keypoints": farthest_points(dense, 300).tolist()}
        write_atomic(folder / f"{part}_keypoints_300.json", _json_bytes(keypoints))
    params = {}
    for part, verts in (("top", tv), ("bottom", bv)):
        lo, hi = obj[f"{part}_box"]
        face_y = hi[1] if part == "top" else lo[1]
        params[f"mocap_{part}"] = [[x, face_y, z] for x in (lo[0] + 5, hi[0] - 5) for z in (lo[2] + 5, hi[2] - 5)]
        params[f"bbox_{part}"] = corners(lo, hi).tolist()
        params[f"keypoints_{part}"] = farthest_points(verts, 16).tolist()
    write_atomic(folder / "object_params.json", _json_bytes(params))
    hull = np.unique(np.concatenate([corners(*obj["top_box"]), corners(*obj["bottom_box"])]), axis=0)
    return float(np.max(np.linalg.norm(hull[:, None] - hull[None], axis=-1)) / 1000.0)


def write_toy_templates(meta: Path) -> dict[str, float]:
    """Every ARCTIC name's toy template under ``meta/object_vtemplates/`` and ``meta/object_meta.json``;
    returns the diameters (metres)."""
    diameters = {}
    for index, name in enumerate(ARCTIC_OBJECTS):
        diameters[name] = write_toy_template(meta / "object_vtemplates" / name, toy_object(index))
    write_atomic(meta / "object_meta.json", _json_bytes({k: {"diameter": v} for k, v in diameters.items()}))
    return diameters
