"""A contact sheet of a store for a person to look at: :func:`inspect_store` writes one PNG grid.

Each record gets a cell of two ``TILE`` px panels and a caption strip below them:

* left: the crop (``img.jpg``) with the visible hand and object masks tinted over it, the amodal masks
  outlined, and the 2D joints with the hand skeleton (DexYCB order);
* right: the joint heatmap (``hm.png``, white) over the darkened crop, and the near-surface SDF samples
  of the hand and object sets projected with ``K``, coloured by their signed distance to the hand;
* caption: the record key and the object name.

A record of kind ``eval`` (no masks, joints or SDF samples) gets the crop with its given hand box and its object
box outlined, and a black right panel.

Cells fill ``COLUMNS`` per row, so a grid of k records is ``min(k, COLUMNS) * 2 * TILE`` px wide and
``ceil(k / COLUMNS) * (TILE + CAPTION_HEIGHT)`` px high (see :func:`grid_size`).
"""

from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path

import cv2
import numpy as np

from hoidata.atomic import write_atomic
from hoidata.errors import DataError
from hoidata.schema import (
    HEATMAP,
    IMG,
    META,
    SDF,
    SEG,
    SEG_HAND_AMODAL,
    SEG_HAND_VISIBLE,
    SEG_OBJECT_AMODAL,
    SEG_OBJECT_VISIBLE,
    dequantize_sdf,
)
from hoidata.store.codec import KEY
from hoidata.store.shards import iter_records, read_shard_members
from hoidata.store.verify import read_sidecar

TILE = 256  # panel side, px
COLUMNS = 4  # record cells per grid row
CAPTION_HEIGHT = 32  # px below each cell's panels: two lines of text
CAPTION_SCALE = 0.38  # OpenCV font scale
TINT_ALPHA = 0.45  # weight of the mask colour where a visible mask is tinted
HAND_COLOUR = (40, 220, 90)  # RGB
OBJECT_COLOUR = (255, 150, 20)
HEATMAP_ALPHA = 0.8  # weight of white where hm.png is 255
SDF_SATURATION = 0.02  # metres: signed distances beyond +-2 cm get the full colour
SDF_NEAR = 0.005  # metres: only samples this close to their own surface are drawn
INSIDE_COLOUR = np.array([40, 90, 255], np.float32)  # RGB, negative distance to the hand
OUTSIDE_COLOUR = np.array([255, 40, 40], np.float32)  # RGB, positive distance
# DexYCB joint order: wrist 0, then thumb, index, middle, ring and little finger, four joints each
FINGER_COLOURS = ((255, 60, 60), (255, 220, 0), (255, 255, 255), (0, 220, 255), (255, 70, 255))
FINGER_CHAINS = tuple((0, 1 + 4 * f, 2 + 4 * f, 3 + 4 * f, 4 + 4 * f) for f in range(5))


def grid_size(k: int) -> tuple[int, int]:
    """(height, width) in px of the grid for k records."""
    cols, rows = min(k, COLUMNS), math.ceil(k / COLUMNS)
    return rows * (TILE + CAPTION_HEIGHT), cols * 2 * TILE


# --------------------------------------------------------------------------------------------------
# choosing and reading records


def _shard_counts(store_dir: Path) -> list[tuple[Path, int]]:
    """Every ``shard-*.tar`` in shard order with its record count: the sidecar's, else counted in the tar."""
    shards = []
    for path in sorted(store_dir.glob("shard-*.tar")):  # zero-padded numbers: name order is shard order
        count = None
        number = path.stem.removeprefix("shard-")
        if number.isdigit():
            try:
                info = read_sidecar(store_dir, int(number))
                count = info.count if info.name == path.name else None
            except DataError:
                pass
        if count is None:
            count = sum(1 for _ in read_shard_members(path))
        shards.append((path, count))
    return shards


def pick_rows(total: int, n: int, seed: int) -> np.ndarray:
    """min(n, total) sorted, distinct row numbers spread evenly over 0..total-1: one from each of that
    many equal strata, its place inside the stratum drawn with ``seed`` (so the same seed, same rows)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    k = min(n, total)
    edges = np.linspace(0, total, k + 1)
    offsets = np.random.default_rng(seed).random(k) * np.diff(edges)
    return np.minimum(np.floor(edges[:-1] + offsets).astype(np.int64), total - 1)


def _read_picked(shards: list[tuple[Path, int]], rows: np.ndarray) -> list[dict]:
    """Decode just the records at the given global rows, reading each shard only as far as needed."""
    records, start = [], 0
    for path, count in shards:
        wanted = {int(r) - start for r in rows if start <= r < start + count}
        start += count
        if not wanted:
            continue
        last = max(wanted)
        for row, record in enumerate(iter_records([path])):
            if row in wanted:
                records.append(record)
            if row >= last:
                break
    return records


# --------------------------------------------------------------------------------------------------
# drawing


def _to_tile(xy: np.ndarray, size: int) -> np.ndarray:
    """Pixel coordinates in a ``size`` px image -> int32 coordinates in a TILE px panel (kept near it)."""
    scaled = (np.asarray(xy, np.float64) + 0.5) * (TILE / size) - 0.5
    return np.clip(np.round(scaled), -4 * TILE, 5 * TILE).astype(np.int32)


def _mask(seg: np.ndarray, bit: int) -> np.ndarray:
    """One seg.png bit plane as a TILE px uint8 0/1 mask (nearest neighbour: no blurred edges)."""
    plane = ((seg & bit) > 0).astype(np.uint8)
    return cv2.resize(plane, (TILE, TILE), interpolation=cv2.INTER_NEAREST)


def _draw_skeleton(panel: np.ndarray, joints_2d: np.ndarray, size: int) -> None:
    """Bones from the wrist along each finger, one colour per finger, and a dot per joint; in place."""
    pts = _to_tile(joints_2d, size)
    for chain, colour in zip(FINGER_CHAINS, FINGER_COLOURS):
        for a, b in pairwise(chain):
            cv2.line(panel, tuple(map(int, pts[a])), tuple(map(int, pts[b])), colour, 1, cv2.LINE_AA)
        for j in chain[1:]:
            cv2.circle(panel, tuple(map(int, pts[j])), 2, colour, -1, cv2.LINE_AA)
    cv2.circle(panel, tuple(map(int, pts[0])), 3, (255, 255, 255), -1, cv2.LINE_AA)


def overlay_panel(record: dict) -> np.ndarray:
    """The crop with tinted visible masks, amodal outlines and the joint skeleton: (TILE, TILE, 3) RGB."""
    img = record[IMG]
    panel = cv2.resize(img, (TILE, TILE), interpolation=cv2.INTER_AREA).astype(np.float32)
    seg = record[SEG]
    for bit, colour in ((SEG_OBJECT_VISIBLE, OBJECT_COLOUR), (SEG_HAND_VISIBLE, HAND_COLOUR)):
        inside = _mask(seg, bit).astype(bool)
        panel[inside] = (1 - TINT_ALPHA) * panel[inside] + TINT_ALPHA * np.float32(colour)
    panel = np.ascontiguousarray(np.round(panel).astype(np.uint8))
    for bit, colour in ((SEG_OBJECT_AMODAL, OBJECT_COLOUR), (SEG_HAND_AMODAL, HAND_COLOUR)):
        contours, _ = cv2.findContours(_mask(seg, bit), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(panel, contours, -1, colour, 1)
    _draw_skeleton(panel, record[META]["joints_2d"], img.shape[0])
    return panel


def sdf_colours(distance: np.ndarray) -> np.ndarray:
    """Signed distances (metres) -> RGB uint8 (N, 3): blue inside, red outside, saturating at SDF_SATURATION."""
    t = (np.clip(distance / SDF_SATURATION, -1.0, 1.0)[:, None] + 1.0) / 2.0
    return np.round((1 - t) * INSIDE_COLOUR + t * OUTSIDE_COLOUR).astype(np.uint8)


def _near_surface_samples(record: dict) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (M, 3) and their distance to the hand (M,): the object set's samples near the
    object, then the hand set's near the hand (drawn last, on top); the uniform set is left out."""
    meta = record[META]
    xyz, sdf_hand, sdf_object, _ = dequantize_sdf(record[SDF])
    n_hand, n_object = int(meta["sdf_counts"][0]), int(meta["sdf_counts"][1])
    hand = np.arange(len(xyz)) < n_hand
    obj = (np.arange(len(xyz)) >= n_hand) & (np.arange(len(xyz)) < n_hand + n_object)
    order = np.concatenate([np.flatnonzero(obj & (np.abs(sdf_object) < SDF_NEAR)),
                            np.flatnonzero(hand & (np.abs(sdf_hand) < SDF_NEAR))])
    points = xyz[order].astype(np.float64) + np.asarray(meta["hand_root"], np.float64)
    return points, sdf_hand[order]


def _project(points: np.ndarray, K: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points -> (int32 TILE px coordinates, mask of the points) of those in front of the camera."""
    uvw = points @ np.asarray(K, np.float64).T
    front = uvw[:, 2] > 1e-9  # at or behind the camera: nothing to project
    return _to_tile(uvw[front, :2] / uvw[front, 2:], size), front


def sdf_panel(record: dict) -> np.ndarray:
    """The near-surface SDF samples projected onto the darkened crop, the joint heatmap blended over them
    in white: (TILE, TILE, 3) RGB."""
    img = record[IMG]
    grey = cv2.cvtColor(cv2.resize(img, (TILE, TILE), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2GRAY)
    panel = np.repeat((grey // 4)[..., None], 3, axis=2)
    points, distance = _near_surface_samples(record)
    px, front = _project(points, record[META]["K"], img.shape[0])
    colours = sdf_colours(distance[front])
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):  # 2 x 2 px dots
        x, y = px[:, 0] + dx, px[:, 1] + dy
        seen = (x >= 0) & (x < TILE) & (y >= 0) & (y < TILE)
        panel[y[seen], x[seen]] = colours[seen]
    hm = cv2.resize(record[HEATMAP], (TILE, TILE), interpolation=cv2.INTER_LINEAR)
    weight = (HEATMAP_ALPHA / 255.0) * hm.astype(np.float32)[..., None]
    return np.round((1 - weight) * panel + weight * 255.0).astype(np.uint8)


def _fit(text: str, width: int, scale: float) -> str:
    """``text`` cut (ending in '~') to fit ``width`` px in the caption font."""
    while len(text) > 1 and cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > width:
        text = text[:-2] + "~"
    return text


def _caption(record: dict, width: int) -> np.ndarray:
    """A (CAPTION_HEIGHT, width, 3) strip: the key on the first line, the object name on the second."""
    strip = np.zeros((CAPTION_HEIGHT, width, 3), np.uint8)
    lines = (str(record[KEY]), str(record[META]["object_name"]))
    for i, text in enumerate(lines):
        baseline = (i + 1) * CAPTION_HEIGHT // 2 - 4
        cv2.putText(strip, _fit(text, width - 8, CAPTION_SCALE), (4, baseline), cv2.FONT_HERSHEY_SIMPLEX,
                    CAPTION_SCALE, (230, 230, 230), 1, cv2.LINE_AA)
    return strip


def boxes_panel(record: dict) -> np.ndarray:
    """A record without masks, joints or SDF samples (kind ``eval``): the crop with its hand box (green) and
    object box (orange) outlined, (TILE, TILE, 3) RGB."""
    img, meta = record[IMG], record[META]
    panel = np.ascontiguousarray(cv2.resize(img, (TILE, TILE), interpolation=cv2.INTER_AREA))
    for name, colour in (("object_box", OBJECT_COLOUR), ("hand_box", HAND_COLOUR)):
        (x1, y1), (x2, y2) = _to_tile(np.asarray(meta[name]).reshape(2, 2), img.shape[0])
        cv2.rectangle(panel, (int(x1), int(y1)), (int(x2), int(y2)), colour, 1, cv2.LINE_AA)
    return panel


def record_cell(record: dict) -> np.ndarray:
    """One record's cell: overlay and SDF panels side by side over the caption, RGB uint8 (a record without
    labels: the boxes panel and a black one)."""
    if SEG in record:
        panels = np.concatenate([overlay_panel(record), sdf_panel(record)], axis=1)
    else:
        panels = np.concatenate([boxes_panel(record), np.zeros((TILE, TILE, 3), np.uint8)], axis=1)
    return np.concatenate([panels, _caption(record, 2 * TILE)], axis=0)


def _assemble(cells: list[np.ndarray]) -> np.ndarray:
    """Cells row by row, COLUMNS per row, on black."""
    grid = np.zeros((*grid_size(len(cells)), 3), np.uint8)
    cell_h, cell_w = TILE + CAPTION_HEIGHT, 2 * TILE
    for i, cell in enumerate(cells):
        row, col = divmod(i, COLUMNS)
        grid[row * cell_h:(row + 1) * cell_h, col * cell_w:(col + 1) * cell_w] = cell
    return grid


def _write_png_atomic(path: Path, rgb: np.ndarray) -> None:
    """Encode with OpenCV, write ``<name>.tmp`` and rename it over ``path``."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {rgb.shape} grid as PNG")
    write_atomic(path, buf.tobytes())


def inspect_store(store_dir, n: int = 16, out="grid.png", seed: int = 0) -> Path:
    """Write a PNG grid of min(n, store size) records spread evenly over the store; return its path.

    Which records: see :func:`pick_rows` (deterministic for a seed). A missing folder or one without
    records is a DataError naming it; a damaged record is the reader's DataError.
    """
    store_dir = Path(store_dir)
    if not store_dir.is_dir():
        raise DataError(store_dir, None, "not a store folder (missing)")
    shards = _shard_counts(store_dir)
    total = sum(count for _, count in shards)
    if total == 0:
        raise DataError(store_dir, None, "no records (an empty store folder)")
    records = _read_picked(shards, pick_rows(total, n, seed))
    if not records:
        raise DataError(store_dir, None, "no readable records")
    out = Path(out)
    _write_png_atomic(out, _assemble([record_cell(r) for r in records]))
    return out
