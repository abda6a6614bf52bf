"""Pictures of results: hand skeleton, mesh and object box over the image, query points coloured by their
predicted distance (the paper's Figure 3), image grids, and the training curve of a run.

Images are RGB uint8 (H, W, 3); colours below are RGB. 3D inputs are camera-frame (OpenCV) points in
metres, projected with the image's intrinsics ``K`` (3, 3) in pixels; points at z <= 1 mm are not drawn.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from hoidata.atomic import atomic_path, write_atomic
from hoidata.errors import DataError
from hoidata.objects import BOX_EDGES, box_corners
from hoidata.reading import read_text

PRED_COLOR = (255, 80, 40)  # predictions: orange-red
GT_COLOR = (40, 220, 80)  # ground truth: green
# DexYCB / manopth joint order: 0 wrist, thumb 1-4, index 5-8, middle 9-12, ring 13-16, little 17-20
HAND_PARENTS = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
HAND_BONES = tuple((p, j) for j, p in enumerate(HAND_PARENTS) if p >= 0)
MIN_DEPTH = 1e-3  # metres
NOT_LOSSES = ("lr", "samples_per_s")  # logged beside the loss terms, not plotted with them


def project(points, K) -> tuple[np.ndarray, np.ndarray]:
    """Camera points (N, 3) metres -> pixels (N, 2) and a (N,) mask of points in front of the camera."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    K = np.asarray(K, dtype=np.float64)
    z = pts[:, 2]
    front = z > MIN_DEPTH
    uvw = pts @ K.T
    uv = uvw[:, :2] / np.where(front, z, 1.0)[:, None]
    return uv, front & np.isfinite(uv).all(1)


def _pt(uv) -> tuple[int, int]:
    """Integer pixel for OpenCV drawing, clipped far outside any image (cv2 rejects huge coordinates)."""
    u, v = np.clip(np.asarray(uv, dtype=np.float64), -1e5, 1e5)
    return round(float(u)), round(float(v))


def _check_image(img) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"img must be a (H, W, 3) uint8 RGB image, got {img.shape} {img.dtype}")
    return np.ascontiguousarray(img).copy()


def _draw_segments(canvas, uv, front, pairs, color, thickness) -> None:
    for a, b in pairs:
        if front[a] and front[b]:
            cv2.line(canvas, _pt(uv[a]), _pt(uv[b]), color, thickness, cv2.LINE_AA)


def mesh_edges(faces) -> np.ndarray:
    """(E, 2) unique undirected edges of a triangle mesh's (F, 3) faces."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0)


def draw_wireframe(img, K, verts, faces, color, alpha: float = 0.45) -> np.ndarray:
    """Blend the projected edges of a mesh (verts (V, 3) metres, faces (F, 3)) over ``img``."""
    canvas = _check_image(img)
    overlay = canvas.copy()
    uv, front = project(verts, K)
    _draw_segments(overlay, uv, front, mesh_edges(faces), color, 1)
    return cv2.addWeighted(overlay, alpha, canvas, 1 - alpha, 0)


def draw_skeleton(img, K, joints, color, thickness: int = 2) -> np.ndarray:
    """Draw the 21-joint hand skeleton (joints (21, 3) metres, DexYCB order) on a copy of ``img``."""
    canvas = _check_image(img)
    uv, front = project(joints, K)
    _draw_segments(canvas, uv, front, HAND_BONES, color, thickness)
    radius = max(2, thickness + 1)
    for j in range(len(uv)):
        if front[j]:
            cv2.circle(canvas, _pt(uv[j]), radius, color, -1, cv2.LINE_AA)
    return canvas


def draw_box(img, K, corners, color, thickness: int = 2) -> np.ndarray:
    """Draw the 12 edges of a 3D box given its 8 corners (8, 3) in :func:`hoidata.objects.box_corners` order."""
    canvas = _check_image(img)
    uv, front = project(corners, K)
    _draw_segments(canvas, uv, front, BOX_EDGES, color, thickness)
    return canvas


def draw_result(img, K, pred_joints=None, gt_joints=None, pred_verts=None, gt_verts=None, faces=None,
                pred_obj_box_corners=None, gt_obj_box_corners=None) -> np.ndarray:
    """Prediction (orange-red) and ground truth (green) over an image; every 3D input is optional.

    Args:
        img: (H, W, 3) uint8 RGB. K: (3, 3) intrinsics of ``img``.
        pred_joints, gt_joints: (21, 3) camera frame, metres, DexYCB order: skeletons.
        pred_verts, gt_verts: (778, 3) hand vertices, with ``faces`` (F, 3): wireframes.
        pred_obj_box_corners, gt_obj_box_corners: (8, 3) posed object box corners.

    Returns:
        (H, W, 3) uint8 RGB; ground truth is drawn first, the prediction on top.
    """
    out = _check_image(img)
    for verts, color in ((gt_verts, GT_COLOR), (pred_verts, PRED_COLOR)):
        if verts is not None and faces is not None:
            out = draw_wireframe(out, K, verts, faces, color)
    for corners, color in ((gt_obj_box_corners, GT_COLOR), (pred_obj_box_corners, PRED_COLOR)):
        if corners is not None:
            out = draw_box(out, K, corners, color)
    for joints, color in ((gt_joints, GT_COLOR), (pred_joints, PRED_COLOR)):
        if joints is not None:
            out = draw_skeleton(out, K, joints, color)
    return out


def _colormap(values: np.ndarray, vmax: float, name: str = "coolwarm") -> np.ndarray:
    """(N,) signed values -> (N, 3) uint8 RGB, -vmax blue .. 0 white .. +vmax red."""
    from matplotlib import colormaps

    t = np.clip(0.5 + 0.5 * np.asarray(values, dtype=np.float64) / vmax, 0.0, 1.0)
    return (colormaps[name](t)[:, :3] * 255).round().astype(np.uint8)


def _colour_bar(height: int, vmax: float, width: int = 64) -> np.ndarray:
    """A vertical colour bar (height, width, 3) titled "SDF mm", +vmax at the top, -vmax at the bottom."""
    bar = np.full((height, width, 3), 255, np.uint8)
    scale = max(0.3, min(0.45, height / 500))
    top, bottom = 22, height - 8
    inner = max(2, bottom - top)
    bar[top:top + inner, 4:18] = _colormap(np.linspace(vmax, -vmax, inner), vmax)[:, None, :]
    text = {"fontFace": cv2.FONT_HERSHEY_SIMPLEX, "fontScale": scale, "color": (0, 0, 0), "thickness": 1,
            "lineType": cv2.LINE_AA}
    cv2.putText(bar, "SDF mm", (2, 12), **text)
    for frac, value in ((0.0, vmax), (0.5, 0.0), (1.0, -vmax)):
        y = int(top + frac * (inner - 1))
        cv2.putText(bar, f"{value * 1000:+.3g}" if value else "0", (20, min(height - 2, y + 4)), **text)
    return bar


def draw_query_points(img, K, points_cam, sdf, vmax: float | None = None, radius: int = 2) -> np.ndarray:
    """Sampled query points coloured by their predicted signed distance, with a colour bar (Figure 3).

    Args:
        img: (H, W, 3) uint8 RGB. K: (3, 3) intrinsics of ``img``.
        points_cam: (N, 3) camera frame, metres. sdf: (N,) predicted signed distance, metres.
        vmax: colour range +-vmax metres; default the 98th percentile of |sdf| (at least 1 mm).

    Returns:
        (H, W + 64, 3) uint8 RGB: the image (dimmed) with the points, the colour bar on the right.
    """
    canvas = _check_image(img)
    sdf = np.asarray(sdf, dtype=np.float64).reshape(-1)
    uv, front = project(points_cam, K)
    if len(sdf) != len(uv):
        raise ValueError(f"points_cam and sdf differ in length: {len(uv)} vs {len(sdf)}")
    if vmax is None:
        finite = np.abs(sdf[np.isfinite(sdf)])
        vmax = max(1e-3, float(np.percentile(finite, 98)) if len(finite) else 1e-3)
    canvas = (canvas * 0.6).astype(np.uint8)
    colours = _colormap(np.nan_to_num(sdf), vmax)
    for i in np.argsort(-np.abs(np.nan_to_num(sdf))):  # closest to the surface drawn last, on top
        if front[i]:
            cv2.circle(canvas, _pt(uv[i]), radius, tuple(int(c) for c in colours[i]), -1, cv2.LINE_AA)
    return np.concatenate([canvas, _colour_bar(canvas.shape[0], vmax)], axis=1)


def result_panel(img, K, pred_joints, gt_joints, pred_verts, gt_verts, faces, pred_pose, gt_pose, obj_verts,
                 points_cam, sdf, min_size: int = 256) -> list[np.ndarray]:
    """The two pictures of one sample: :func:`draw_result` and :func:`draw_query_points`.

    ``pred_pose``/``gt_pose`` (4, 4) pose the object model ``obj_verts`` (V, 3) whose box is drawn; other
    arguments as in those functions. Images smaller than ``min_size`` px are enlarged (nearest pixel, with
    K adjusted) so the drawing stays legible.
    """
    img, K = _check_image(img), np.asarray(K, dtype=np.float64)
    s = max(1, min_size // max(1, img.shape[0]))
    if s > 1:
        img = np.repeat(np.repeat(img, s, 0), s, 1)
        K = np.diag([s, s, 1.0]) @ K
        K[:2, 2] += (s - 1) / 2  # pixel centres: u' = s u + (s - 1) / 2
    corners = box_corners(obj_verts)
    boxes = [corners @ np.asarray(p)[:3, :3].T + np.asarray(p)[:3, 3] for p in (pred_pose, gt_pose)]
    return [draw_result(img, K, pred_joints, gt_joints, pred_verts, gt_verts, faces, *boxes),
            draw_query_points(img, K, points_cam, sdf)]


def grid_image(images: Sequence[np.ndarray], cols: int | None = None, pad: int = 4) -> np.ndarray:
    """Tile RGB uint8 images (any sizes) into one image, row-major, white padding; cols default all in a row."""
    if not images:
        raise ValueError("grid_image needs at least one image")
    images = [_check_image(i) for i in images]
    cols = max(1, min(cols or len(images), len(images)))
    rows = -(-len(images) // cols)
    h = max(i.shape[0] for i in images)
    w = max(i.shape[1] for i in images)
    out = np.full((rows * h + (rows + 1) * pad, cols * w + (cols + 1) * pad, 3), 255, np.uint8)
    for k, im in enumerate(images):
        r, c = divmod(k, cols)
        y, x = pad + r * (h + pad), pad + c * (w + pad)
        out[y:y + im.shape[0], x:x + im.shape[1]] = im
    return out


def save_grid(images: Sequence[np.ndarray], path, cols: int | None = None) -> Path:
    """Write :func:`grid_image` of RGB uint8 ``images`` as a PNG (atomically); returns the path."""
    path = Path(path)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(grid_image(images, cols), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"{path}: PNG encoding failed")
    write_atomic(path, buf.tobytes())
    return path


def read_curve(metrics_csv) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """``RUN/metrics.csv`` -> {split: {name: (steps (n,), values (n,))}}; malformed rows are a DataError."""
    path = Path(metrics_csv)
    series: dict[str, dict[str, list]] = {}
    try:
        reader = csv.DictReader(io.StringIO(read_text(path, "training curve"), newline=""))
        columns, rows = reader.fieldnames, list(reader)
    except csv.Error as exc:  # a field past csv's limit
        raise DataError(path, None, f"not a training curve ({exc})") from None
    missing = {"split", "step", "name", "value"} - set(columns or ())
    if missing:
        raise DataError(path, "header", f"missing column(s) {sorted(missing)}")
    for line, row in enumerate(rows, start=2):
        try:
            step, value = int(float(row["step"])), float(row["value"])
        except (TypeError, ValueError):
            raise DataError(path, f"line {line}", f"step/value not numeric: {row}") from None
        series.setdefault(row["split"], {}).setdefault(row["name"], []).append((step, value))
    return {split: {name: tuple(np.array(v, dtype=np.float64).T.reshape(2, -1)) for name, v in names.items()}
            for split, names in series.items()}


def _plot_series(ax, series: dict, names: list[str], style: str, log: bool, prefix: str = "") -> None:
    for name in names:
        steps, values = series[name]
        keep = np.isfinite(values) & ((values > 0) if log else True)
        if keep.any():
            ax.plot(steps[keep], values[keep], style, label=prefix + name, lw=2.2 if name == "total" else 1.0)


def plot_training_curve(metrics_csv, png_path) -> Path:
    """Plot a run's ``metrics.csv``: train (and val) loss terms vs step on a log axis, val metrics apart.

    Left panel: ``total`` (thick) and every other train loss term, solid; validation losses dashed.
    Right panel (when validation rows exist): validation metrics whose name ends in ``_mm``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = read_curve(metrics_csv)
    if not curves:
        raise DataError(Path(metrics_csv), None, "the training curve has no rows")
    train, val = curves.get("train", {}), curves.get("val", {})
    val_metrics = sorted(n for n in val if n.endswith("_mm"))
    val_losses = sorted(n for n in val if n not in val_metrics and n not in NOT_LOSSES)
    fig, axes = plt.subplots(1, 2 if val_metrics else 1, figsize=(13 if val_metrics else 8, 5), squeeze=False)
    ax = axes[0, 0]
    order = sorted((n for n in train if n not in NOT_LOSSES), key=lambda n: (n != "total", n))
    _plot_series(ax, train, order, "-", log=True)
    _plot_series(ax, val, [n for n in val_losses if n == "total"], "k--o", log=True, prefix="val ")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title("training losses" + (" (dashed: validation total)" if "total" in val_losses else ""))
    ax.grid(True, which="both", alpha=0.3)
    if ax.lines:
        ax.legend(fontsize=7, ncol=2)
    if val_metrics:
        ax2 = axes[0, 1]
        _plot_series(ax2, val, val_metrics, "-o", log=False)
        ax2.set_xlabel("step")
        ax2.set_ylabel("mm")
        ax2.set_title("validation metrics")
        ax2.grid(True, alpha=0.3)
        ax2.legend(fontsize=8)
    fig.tight_layout()
    png_path = Path(png_path)
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return png_path
