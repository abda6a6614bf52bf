"""ARCTIC's articulated object templates (``meta/object_vtemplates/<name>/``) read and posed as ARCTIC's own
object layer poses them (docs/datasets.md, "ARCTIC"): numpy, float64, metres.

A template is one mesh (``mesh.obj``, millimetres) with a per-vertex part label (``parts.json``). Which part turns
follows ARCTIC's code, not its data page: the vertices labelled 0 (part id 1, "top") turn about the canonical
axis (0, 0, -1) through the origin by the articulation; then the global pose (axis-angle, translation) moves both
parts. The vertices labelled 1 (part id 2, "bottom") are the object's root for the metrics.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.reading import read_json, read_text
from hoidata.shapes import not_finite, numbers

# the names ARCTIC's object layer loads, every one, at start-up (a missing folder stops it)
ARCTIC_OBJECTS = ("capsulemachine", "box", "ketchup", "laptop", "microwave", "mixer", "notebook",
                  "espressomachine", "waffleiron", "scissors", "phone")
ARTICULATION_AXIS = np.array([0.0, 0.0, -1.0])  # canonical hinge axis through the origin
TOP, BOTTOM = 1, 2  # ARCTIC's part ids: parts.json's label + 1
TEMPLATE_FILES = ("mesh.obj", "parts.json", "object_params.json", "top_keypoints_300.json",
                  "bottom_keypoints_300.json")  # the files ARCTIC's loader opens
PARAM_SHAPES = {"mocap_top": (None, 3), "mocap_bottom": (None, 3), "bbox_top": (8, 3), "bbox_bottom": (8, 3),
                "keypoints_top": (16, 3), "keypoints_bottom": (16, 3)}


@dataclass
class ArcticObject:
    """One template in metres: ``vertices`` (V, 3), ``faces`` (F, 3), ``part_ids`` (V,) 1 top (turns) / 2 bottom,
    ``sub_vertices`` (600, 3) the 300 top then 300 bottom keypoints and their ``sub_part_ids`` (the label of the
    nearest mesh vertex, as ARCTIC assigns them), ``bbox3d`` (16, 3) and ``kp3d`` (32, 3) top then bottom, and the
    ``diameter`` (metres) from ``object_meta.json``."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    part_ids: np.ndarray
    sub_vertices: np.ndarray
    sub_part_ids: np.ndarray
    bbox3d: np.ndarray
    kp3d: np.ndarray
    diameter: float


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``v`` rows (in file order) and triangle ``f`` rows (0-based) of a Wavefront OBJ."""
    verts, faces = [], []
    lines = read_text(path, "OBJ file").splitlines()
    for n, line in enumerate(lines, 1):
        parts = line.split()
        if not parts:
            continue
        try:
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                idx = [int(p.split("/")[0]) for p in parts[1:]]
                faces += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]  # fan of a polygon
        except (ValueError, IndexError):
            raise DataError(path, f"line {n}", f"malformed {parts[0]!r} row") from None
    if not verts or not faces:
        raise DataError(path, None, "no vertices or no faces")
    v, f = np.asarray(verts, np.float64), np.asarray(faces, np.int64)
    problem = not_finite(v)
    if problem:
        raise DataError(path, "v", f"{v.size} coordinates, {problem}")
    f = np.where(f < 0, f + len(v), f - 1)
    if f.min() < 0 or f.max() >= len(v):
        raise DataError(path, "f", f"a face names a vertex outside 1..{len(v)}")
    return v, f


def _json(path: Path):
    if not Path(path).exists():
        raise DataError(path, None, "missing (ARCTIC's object loader opens it)")
    return read_json(path, "ARCTIC object file")


def _points(value, path: Path, key: str, rows: int | None) -> np.ndarray:
    return numbers(value, path, key, (rows, 3))  # millimetres; never strings or booleans, finite


def read_object_meta(meta_dir: str | Path) -> dict[str, float]:
    """``meta/object_meta.json``: each object's diameter (metres)."""
    path = Path(meta_dir) / "object_meta.json"
    table = _json(path)
    out = {}
    for name, entry in (table.items() if isinstance(table, dict) else ()):
        d = entry.get("diameter") if isinstance(entry, dict) else None
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not d > 0:
            raise DataError(path, f"{name}.diameter", "missing or not a positive number (metres)")
        out[name] = float(d)
    if not out:
        raise DataError(path, None, "must map object names to {'diameter': metres}")
    return out


def load_arctic_object(meta_dir: str | Path, name: str, diameters: dict[str, float] | None = None) -> ArcticObject:
    """The template ``meta_dir/object_vtemplates/<name>/`` in metres, checked as ARCTIC's loader needs it."""
    folder = Path(meta_dir) / "object_vtemplates" / name
    v_mm, faces = read_obj(folder / "mesh.obj")
    labels = _json(folder / "parts.json")
    if not isinstance(labels, list) or len(labels) != len(v_mm) or \
            any(type(x) is not int or x not in (0, 1) for x in labels):  # a boolean is no label
        raise DataError(folder / "parts.json", None, f"must list one label 0 or 1 per mesh.obj vertex ({len(v_mm)})")
    part_ids = np.asarray(labels, np.int64) + 1
    if not (part_ids == BOTTOM).any():
        raise DataError(folder / "parts.json", None, "no vertex labelled 1 (the root part the metrics use)")
    subs = []
    for part in ("top", "bottom"):
        path = folder / f"{part}_keypoints_300.json"
        entry = _json(path)
        subs.append(_points(entry.get("keypoints") if isinstance(entry, dict) else None, path, "keypoints", 300))
    sub = np.concatenate(subs)
    nearest = np.argmin(((sub[:, None, :] - v_mm[None]) ** 2).sum(-1), axis=1)
    params = _json(folder / "object_params.json")
    if not isinstance(params, dict):
        raise DataError(folder / "object_params.json", None, "must be an object")
    got = {k: _points(params.get(k), folder / "object_params.json", k, rows) for k, (rows, _) in PARAM_SHAPES.items()}
    diameters = read_object_meta(meta_dir) if diameters is None else diameters
    short = "".join(c for c in name if not c.isdigit())
    if short not in diameters:
        raise DataError(Path(meta_dir) / "object_meta.json", short, "no diameter for this object")
    return ArcticObject(name, v_mm / 1000.0, faces, part_ids, sub / 1000.0, part_ids[nearest],
                        np.concatenate([got["bbox_top"], got["bbox_bottom"]]) / 1000.0,
                        np.concatenate([got["keypoints_top"], got["keypoints_bottom"]]) / 1000.0, diameters[short])


def pose_points(points: np.ndarray, part_ids: np.ndarray, radian, rotvec, transl=None) -> np.ndarray:
    """Template points (P, 3) with part ids (P,) posed for N frames -> (N, P, 3): the top part turned by
    ``radian`` (N,) about :data:`ARTICULATION_AXIS`, then every point rotated by ``rotvec`` (N, 3) and moved by
    ``transl`` (N, 3), all metres (None: no translation, as ARCTIC's evaluation poses objects)."""
    from scipy.spatial.transform import Rotation

    radian = np.asarray(radian, np.float64).reshape(-1)
    arti = Rotation.from_rotvec(radian[:, None] * ARTICULATION_AXIS).as_matrix()
    glob = Rotation.from_rotvec(np.asarray(rotvec, np.float64).reshape(-1, 3)).as_matrix()
    pts = np.broadcast_to(np.asarray(points, np.float64), (len(radian),) + np.shape(points))
    top = (np.asarray(part_ids) == TOP)[None, :, None]
    local = np.where(top, pts @ arti.transpose(0, 2, 1), pts)
    out = local @ glob.transpose(0, 2, 1)
    return out if transl is None else out + np.asarray(transl, np.float64).reshape(-1, 1, 3)


def pose_object(obj: ArcticObject, radian, rotvec, transl=None) -> np.ndarray:
    """The template's mesh vertices posed for N frames: (N, V, 3) metres (:func:`pose_points`)."""
    return pose_points(obj.vertices, obj.part_ids, radian, rotvec, transl)
