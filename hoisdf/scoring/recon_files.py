"""Mesh folders of ``hoisdf score recon``: which frames a split has, where each part's file is, and whether a file
is a usable mesh.

Layouts (docs/scoring.md, "Reconstruction"):

- predictions: one folder of ``<id>_hand.ply`` / ``<id>_obj.ply`` (gSDF's and AlignSDF's ``sdf_mesh/``), or
  ``.obj``; both suffixes for one part of one frame is an error;
- ground truth: the same naming, or gSDF's test export (``mesh_hand/<id>.obj`` and ``mesh_obj/<id>.obj`` under
  the given folder, its ``mesh_data/`` or its ``data/mesh_data/``: what ``hoidata export --format gsdf`` writes).

The ground truth defines the split: every frame with a ground-truth mesh of a scored part is scored, and a
ground-truth file that is not a usable mesh is an error naming it (a prediction's is a counted failure).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.reading import read_text
from hoidata.reading_media import read_mesh

PARTS = ("hand", "obj")
SUFFIXES = (".ply", ".obj")


def _gsdf_root(folder: Path) -> Path | None:
    for root in (folder, folder / "mesh_data", folder / "data" / "mesh_data"):
        if (root / "mesh_hand").is_dir() or (root / "mesh_obj").is_dir():
            return root
    return None


def named_files(folder: Path, part: str) -> dict[str, Path]:
    """``{id: path}`` of the ``<id>_<part>.ply|.obj`` files in ``folder``; DataError on an id with both."""
    out: dict[str, Path] = {}
    for suffix in SUFFIXES:
        for path in sorted(folder.glob(f"*_{part}{suffix}")):
            ident = path.name[: -len(f"_{part}{suffix}")]
            if ident in out:
                raise DataError(path, None, f"frame {ident!r} has both {out[ident].name} and {path.name}: keep one")
            out[ident] = path
    return out


def gt_files(folder, parts=PARTS) -> tuple[dict[str, dict[str, Path]], str]:
    """Ground truth ``{part: {id: path}}`` and the layout found ('gsdf export' or 'named files')."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, None, "ground-truth folder not found")
    root = _gsdf_root(folder)
    if root is not None:
        files = {}
        for part in parts:
            sub = root / f"mesh_{part}"
            files[part] = {p.stem: p for p in sorted(sub.glob("*.obj"))} if sub.is_dir() else {}
        layout = "gsdf export"
    else:
        files, layout = {part: named_files(folder, part) for part in parts}, "named files"
    if not any(files.values()):
        raise DataError(folder, None, "no ground-truth mesh here (expected mesh_hand/<id>.obj and mesh_obj/<id>.obj "
                                      "as gSDF's test export, or <id>_hand.ply / <id>_obj.ply)")
    ids = sorted(set().union(*files.values()))
    for part in parts:
        missing = [i for i in ids if i not in files[part]]
        if missing:
            raise DataError(folder, f"{part} mesh of {missing[0]}", f"missing ({len(missing)} of {len(ids)} frames "
                            f"lack a ground-truth {part} mesh; score the other part alone with --parts)")
    return files, layout


def read_ids(path) -> list[str]:
    """A frame list: one id per line; an empty or repeated id is an error naming the line."""
    path = Path(path)
    ids, seen = [], {}
    for k, line in enumerate(read_text(path, "frame list").splitlines()):
        ident = line.strip()
        if not ident:
            continue
        if ident in seen:
            raise DataError(path, f"line {k + 1}", f"id {ident!r} is listed twice (first on line {seen[ident] + 1})")
        seen[ident] = k
        ids.append(ident)
    if not ids:
        raise DataError(path, None, "no frame id in the list")
    return ids


REACH_M = 100.0  # metres: no coordinate of a hand or object in a camera frame lies farther (float64 then keeps
# the exact protocol's bounds to 1e-10 cm^2; hoisdf.scoring.recon_exact.rounding_limits)


def check_mesh(path: Path | None) -> tuple[tuple[np.ndarray, np.ndarray] | None, str]:
    """``((vertices (V, 3) float64 m, faces (F, 3) int64), '')`` of a usable triangle mesh, or ``(None, why)``:
    missing, unreadable, not a triangle mesh, no faces, a face index out of range, a non-finite vertex, a vertex
    beyond REACH_M or no area. Read with trimesh (``process=False``), as gSDF reads it."""
    if path is None or not Path(path).is_file():
        return None, "missing"
    import trimesh

    try:
        mesh = read_mesh(path, process=False)
    except DataError as err:  # trimesh's many exception types on a damaged file, as one: each is a failure
        return None, f"unreadable: {err.problem}"[:200]
    if not isinstance(mesh, trimesh.Trimesh):
        return None, f"not one triangle mesh (trimesh reads a {type(mesh).__name__})"
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    if faces.ndim != 2 or len(faces) == 0:
        return None, "no faces"
    if faces.min() < 0 or faces.max() >= len(vertices):
        return None, "a face index is out of range"
    if not np.isfinite(vertices).all():
        return None, "a vertex is NaN or infinite"
    reach = float(np.abs(vertices).max())
    if reach > REACH_M:
        return None, f"a vertex lies {reach:.3g} m from the camera, beyond the {REACH_M:g} m of a physical scene"
    tri = vertices[faces]
    if not np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum() > 0:
        return None, "the surface has no area"
    return (vertices, faces), ""


def gt_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A ground-truth mesh, or a DataError naming the file and what is wrong with it."""
    mesh, why = check_mesh(path)
    if mesh is None:
        raise DataError(path, None, f"ground-truth mesh {why}")
    return mesh
