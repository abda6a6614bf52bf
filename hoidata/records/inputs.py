"""Human-readable checks of the inputs users point the pipelines at: MANO files and object folders.

Each function returns plain rows (dicts) so the CLI only formats them and tests can assert on them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import trimesh

from hoidata.geometry.mirror import mirror_axis_angle, mirror_points


def mano_rows(mano_dir: str | os.PathLike) -> list[dict]:
    """Load each MANO file in `mano_dir` and check it: closed mesh, volume, parts, and left/right agreement."""
    from hoidata.hand import load_mano

    models, rows = {}, []
    for side in ("right", "left"):
        path = Path(mano_dir) / f"MANO_{side.upper()}.pkl"
        if not path.is_file():
            rows.append({"file": str(path), "status": "missing"})
            continue
        model = load_mano(path, side=side, dtype=torch.float64)
        models[side] = model
        closed = trimesh.Trimesh(model.close(model.v_template[None])[0].numpy(), model.closed_faces, process=False)
        rows.append({
            "file": str(path), "status": "ok", "vertices": model.v_template.shape[0], "faces": len(model.faces),
            "closed_watertight": bool(closed.is_watertight), "volume_cm3": round(float(closed.volume) * 1e6, 1),
            "parts": int(len(np.unique(model.vertex_parts))),
            "hand_length_cm": round(float(np.ptp(model.v_template.numpy(), axis=0).max()) * 100, 1),
        })
    if len(models) == 2:
        gen = torch.Generator().manual_seed(0)
        pose = torch.randn(4, 48, generator=gen, dtype=torch.float64) * 0.3
        betas = torch.randn(4, 10, generator=gen, dtype=torch.float64)
        right = models["right"](pose, betas).vertices
        left = models["left"](mirror_axis_angle(pose), betas).vertices
        gap_mm = float((mirror_points(left) - right).norm(dim=-1).max()) * 1000
        rows.append({"file": "left vs mirrored right", "status": "ok" if gap_mm < 0.1 else "MISMATCH",
                     "max_vertex_gap_mm": round(gap_mm, 4)})
    return rows


def object_rows(models_dir: str | os.PathLike, n_vertices: int = 1000, cache_dir=None) -> list[dict]:
    """Check every object in a YCB-layout folder: loads, repairs to watertight, simplifies exactly."""
    from hoidata import objects

    rows = []
    for name in objects.list_objects(models_dir):
        mesh = objects.load_object_mesh(objects.object_mesh_path(models_dir, name))
        repaired, report = objects.repair_mesh(mesh)
        simple = objects.load_simplified(models_dir, name, n_vertices=n_vertices, cache_dir=cache_dir)
        err = objects.surface_error(simple, repaired, n_samples=5000)
        size = np.ptp(repaired.vertices, axis=0) * 100
        rows.append({
            "object": name, "vertices": len(mesh.vertices), "faces": len(mesh.faces),
            "size_cm": "x".join(f"{s:.1f}" for s in size), "watertight_after_repair": report.watertight,
            "volume_cm3": round(float(report.volume) * 1e6, 1), f"simplified_{n_vertices}": len(simple.vertices),
            "simplify_max_mm": round(err["max"] * 1000, 2), "simplify_mean_mm": round(err["mean"] * 1000, 3),
        })
    return rows


def format_rows(rows: list[dict]) -> str:
    """Rows of dicts -> an aligned plain-text table (columns in first-seen order)."""
    if not rows:
        return "(nothing)"
    cols = list(dict.fromkeys(k for r in rows for k in r))
    cells = [[str(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    line = lambda vals: "  ".join(v.ljust(w) for v, w in zip(vals, widths)).rstrip()  # noqa: E731
    return "\n".join([line(cols), line(["-" * w for w in widths])] + [line(r) for r in cells])
