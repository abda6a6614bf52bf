"""YCB object models as DexYCB and HO-3D use them: class table, on-disk layout, loading, caching.

On-disk layout (the ``models`` folder of DexYCB / YCB-Video)::

    models/<name>/textured_simple.obj      one textured triangle mesh, metres, origin near the centre
    models/<name>/textured_simple.obj.mtl  its material (``map_Kd texture_map.png``)
    models/<name>/texture_map.png          its texture
    models/<name>/points.xyz               plain text, one "x y z" per line, metres

Mesh repair and simplification live in :mod:`hoidata.objects.meshops` and are re-exported here.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import numpy as np
import trimesh

from hoidata.errors import DataError, naming_os_errors
from hoidata.reading import read_bytes, read_npz, read_table
from hoidata.reading_media import decode_mesh, read_mesh
from hoidata.shapes import not_finite
from hoidata.objects.meshops import (
    MeshReport,
    check_mesh,
    repair_mesh,
    simplify_mesh,
    surface_error,
)

__all__ = [
    "YCB_CLASSES", "UnknownObjectError", "class_id", "class_name", "MESH_FILE", "POINTS_FILE",
    "object_mesh_path", "object_points_path", "list_objects", "load_object_mesh", "load_points",
    "MeshReport", "check_mesh", "repair_mesh", "simplify_mesh", "surface_error",
    "SIMPLIFY_VERSION", "default_cache_dir", "simplify_cache_key", "load_simplified",
    "box_corners", "box21", "BOX_EDGES",
]

# DexYCB object class ids (1-based, as in its labels) and YCB model folder names.
YCB_CLASSES: dict[int, str] = {
    1: "002_master_chef_can", 2: "003_cracker_box", 3: "004_sugar_box", 4: "005_tomato_soup_can",
    5: "006_mustard_bottle", 6: "007_tuna_fish_can", 7: "008_pudding_box", 8: "009_gelatin_box",
    9: "010_potted_meat_can", 10: "011_banana", 11: "019_pitcher_base", 12: "021_bleach_cleanser",
    13: "024_bowl", 14: "025_mug", 15: "035_power_drill", 16: "036_wood_block", 17: "037_scissors",
    18: "040_large_marker", 19: "051_large_clamp", 20: "052_extra_large_clamp", 21: "061_foam_brick",
}
_IDS_BY_NAME = {name: cid for cid, name in YCB_CLASSES.items()}

MESH_FILE = "textured_simple.obj"
POINTS_FILE = "points.xyz"
# Bump whenever simplify_mesh changes its output, so cached results are recomputed.
SIMPLIFY_VERSION = "1"


class UnknownObjectError(DataError, KeyError):
    """An object name or class id that is not one of the 21 DexYCB classes."""

    # KeyError would repr() the message; keep DataError's plain "path: 'field': problem" text.
    __str__ = BaseException.__str__


def class_id(name: str) -> int:
    """DexYCB class id (1..21) of a YCB model name such as ``"025_mug"``."""
    try:
        return _IDS_BY_NAME[name]
    except (KeyError, TypeError):
        raise UnknownObjectError(None, "object name", f"unknown YCB object {name!r}; "
                                 f"expected one of {', '.join(YCB_CLASSES.values())}") from None


def class_name(cid: int) -> str:
    """YCB model name of a DexYCB class id (1..21)."""
    try:
        return YCB_CLASSES[int(cid)]
    except (KeyError, TypeError, ValueError):
        raise UnknownObjectError(None, "class id", f"unknown YCB class id {cid!r}; expected 1..21") from None


def object_mesh_path(models_dir: str | os.PathLike, name: str) -> Path:
    """``models_dir/<name>/textured_simple.obj`` (the path; existence is not checked); for a BOP-style name
    ``obj_<id>`` (HOT3D-Clips' ``object_models_eval``), ``models_dir/obj_<id>.glb``."""
    if name.startswith("obj_"):
        return Path(models_dir) / f"{name}.glb"
    return Path(models_dir) / name / MESH_FILE


def object_points_path(models_dir: str | os.PathLike, name: str) -> Path:
    """``models_dir/<name>/points.xyz`` (the path; existence is not checked)."""
    return Path(models_dir) / name / POINTS_FILE


def list_objects(models_dir: str | os.PathLike) -> list[str]:
    """Sorted names of the sub-folders of ``models_dir`` that contain ``textured_simple.obj``."""
    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise DataError(models_dir, None, "models folder not found")
    return sorted(p.name for p in models_dir.iterdir() if (p / MESH_FILE).is_file())


def load_object_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Load one object mesh as a :class:`trimesh.Trimesh` with its texture visuals.

    Loaded with ``process=False`` and ``maintain_order=True`` so the file's vertex order and UV
    seams survive (vertex ids then match the OBJ). Units are whatever the file holds (YCB: metres).
    Raises DataError for a missing or unreadable file, no faces, or several separate geometries
    (OBJ ``o``/``g`` groups or materials are split, not merged, so a multi-part file is caught).
    """
    path = Path(path)
    options = dict(process=False, maintain_order=True, split_objects=True, split_groups=True)
    if path.suffix.lower() == ".obj":  # text: handed to trimesh as UTF-8, whatever the file's encoding
        loaded = decode_mesh(_as_utf8(read_bytes(path, "mesh file")), path, "obj", resolver=_Utf8Resolver(path),
                             **options)
    else:
        loaded = read_mesh(path, **options)
    if isinstance(loaded, trimesh.Scene):
        geometries = loaded.dump(concatenate=False)  # applies scene transforms
        if len(geometries) > 1:
            raise DataError(path, "geometry", f"expected one mesh, found {len(geometries)} "
                            f"({', '.join(sorted(loaded.geometry))})")
        loaded = geometries[0] if geometries else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise DataError(path, "faces", "no triangle faces")
    problem = not_finite(np.asarray(loaded.vertices))
    if problem:
        raise DataError(path, "vertices", f"{loaded.vertices.size} coordinates, {problem}")
    return loaded


def _as_utf8(data: bytes) -> bytes:
    """OBJ/MTL text as UTF-8: files that are not UTF-8 (a latin-1 byte in a comment or material name) are read
    as latin-1, which maps every byte. trimesh would need charset_normalizer or chardet to guess, and the
    geometry never depends on those characters."""
    try:
        data.decode("utf-8")
        return data
    except UnicodeDecodeError:
        return data.decode("latin-1").encode("utf-8")


class _Utf8Resolver(trimesh.resolvers.FilePathResolver):
    """Finds an OBJ's material and texture files next to it; material text is handed on as UTF-8."""

    def get(self, name):
        data = super().get(name)
        return _as_utf8(data) if str(name).lower().endswith(".mtl") else data


def load_points(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) float64 points of a ``points.xyz`` file (metres)."""
    path = Path(path)
    points = read_table(path, "'x y z' points file")
    problem = not_finite(points)
    if problem:
        raise DataError(path, "points", f"{points.size} coordinates, {problem}")
    if points.shape[1] != 3 or len(points) == 0:
        raise DataError(path, "points", f"expected (N, 3) coordinates, got shape {points.shape}")
    return points


def default_cache_dir() -> Path:
    """``$HOIDATA_CACHE/objects`` if that variable is set, else ``~/.cache/hoidata/objects``."""
    root = os.environ.get("HOIDATA_CACHE")
    return Path(root) / "objects" if root else Path.home() / ".cache" / "hoidata" / "objects"


def simplify_cache_key(obj_path: str | os.PathLike, n_vertices: int) -> str:
    """sha256 hex of the OBJ bytes, the vertex count and SIMPLIFY_VERSION (content, not mtime)."""
    digest = hashlib.sha256(read_bytes(obj_path, "mesh file"))
    digest.update(f"|n_vertices={int(n_vertices)}|simplify={SIMPLIFY_VERSION}".encode())
    return digest.hexdigest()


def load_simplified(models_dir: str | os.PathLike, name: str, n_vertices: int = 1000,
                    cache_dir: str | os.PathLike | None = None) -> trimesh.Trimesh:
    """The :func:`simplify_mesh` result for ``models_dir/<name>``, cached on disk.

    The cache file is ``<cache_dir>/<name>-<n_vertices>-<key[:32]>.npz`` holding ``vertices``
    (float64, m) and ``faces`` (int64); editing the OBJ changes the key. Written atomically
    (temp file + os.replace), so concurrent workers never read a half-written file. The cache
    must not live inside the dataset folder, which is treated as read-only.
    """
    obj_path = object_mesh_path(models_dir, name)
    key = simplify_cache_key(obj_path, n_vertices)
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    if cache_dir.resolve().is_relative_to(Path(models_dir).resolve()):
        raise DataError(cache_dir, None, f"cache folder is inside the dataset folder {models_dir}")
    cache_file = cache_dir / f"{name}-{int(n_vertices)}-{key[:32]}.npz"
    cached = _read_cached(cache_file)
    if cached is not None:
        return cached
    mesh = simplify_mesh(load_object_mesh(obj_path), n_vertices)
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = tempfile.NamedTemporaryFile(dir=cache_dir, suffix=".npz.tmp", delete=False)
    try:
        with naming_os_errors(cache_file), tmp:  # a full disk: the error names the cache file, no .tmp stays
            np.savez(tmp, vertices=np.asarray(mesh.vertices, np.float64), faces=np.asarray(mesh.faces, np.int64))
        os.replace(tmp.name, cache_file)
    except BaseException:
        Path(tmp.name).unlink(missing_ok=True)
        raise
    return mesh


def _read_cached(cache_file: Path) -> trimesh.Trimesh | None:
    """The cached mesh, or None if absent or unreadable (then it is simply recomputed)."""
    if not cache_file.is_file():
        return None
    try:
        data = read_npz(cache_file, ("vertices", "faces"), "mesh cache file")
    except DataError:
        return None
    vertices, faces = data["vertices"], data["faces"]
    return trimesh.Trimesh(vertices, faces, process=False)


def box_corners(vertices: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned bounding box of ``vertices`` (N, 3).

    Corner ``i`` has bits ``(x, y, z) = (i >> 2 & 1, i >> 1 & 1, i & 1)``, each bit choosing the
    min (0) or max (1) along that axis: 0 = (xmin, ymin, zmin), 1 = (xmin, ymin, zmax),
    2 = (xmin, ymax, zmin), ..., 7 = (xmax, ymax, zmax).
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    lo_hi = np.stack([vertices.min(axis=0), vertices.max(axis=0)])  # (2, 3)
    bits = (np.arange(8)[:, None] >> np.array([2, 1, 0])) & 1  # (8, 3)
    return lo_hi[bits, np.arange(3)]


# The 12 box edges: corner pairs that differ in one bit, in lexicographic order of the pair.
BOX_EDGES: tuple[tuple[int, int], ...] = tuple(
    (i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1)


def box21(vertices: np.ndarray) -> np.ndarray:
    """(21, 3) box keypoints: the 8 :func:`box_corners`, the midpoints of the 12 ``BOX_EDGES``
    ((0,1), (0,2), (0,4), (1,3), (1,5), (2,3), (2,6), (3,7), (4,5), (4,6), (5,7), (6,7)), then the
    box centre."""
    corners = box_corners(vertices)
    edges = np.asarray(BOX_EDGES)
    mids = 0.5 * (corners[edges[:, 0]] + corners[edges[:, 1]])
    return np.vstack([corners, mids, corners.mean(axis=0, keepdims=True)])
