"""inspect_store: the PNG contact sheet of a store (grid size, mask tint, SDF points, record choice, errors)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from hoidata.errors import DataError
from hoidata.schema import (
    META_FIELDS,
    SCHEMA_VERSION,
    SDF_QUANTUM,
    SEG_HAND_AMODAL,
    SEG_HAND_VISIBLE,
    SEG_OBJECT_AMODAL,
    SEG_OBJECT_VISIBLE,
)
from hoidata.store import encode_record, write_shard
from hoidata.store.inspect import (
    CAPTION_HEIGHT,
    HAND_COLOUR,
    TILE,
    TINT_ALPHA,
    grid_size,
    inspect_store,
    pick_rows,
)

CROP = 64
GREY = 100
HAND_CENTRE = 18  # crop px, inside the visible hand square (crop px 8..27)
N_SDF = (30, 20, 10)  # hand, object, uniform samples


def make_record(i: int):
    """A schema-valid record: grey crop, a hand square (top left), an object square (bottom right), joints
    in the bottom-left corner away from both, SDF samples near the surfaces in front of the camera."""
    rng = np.random.default_rng(i)
    key = f"toy-train-f{i:04d}"
    img = np.full((CROP, CROP, 3), GREY, np.uint8)
    seg = np.zeros((CROP // 2, CROP // 2), np.uint8)
    seg[2:16, 2:16] = SEG_HAND_AMODAL
    seg[4:14, 4:14] |= SEG_HAND_VISIBLE
    seg[18:30, 18:30] = SEG_OBJECT_VISIBLE | SEG_OBJECT_AMODAL
    hm = np.zeros_like(seg)
    hm[24:27, 4:7] = 255
    n = sum(N_SDF)
    sdf = np.zeros((n, 6), np.int16)
    sdf[:, :3] = rng.uniform(-0.05, 0.05, (n, 3)) / SDF_QUANTUM
    sdf[:, 3:5] = rng.uniform(-0.003, 0.003, (n, 2)) / SDF_QUANTUM
    sdf[:, 5] = rng.integers(-1, 16, n)
    meta = {"schema_version": SCHEMA_VERSION, "kind": "full", "key": key, "dataset": "toy", "split": "train",
            "frame_id": f"f{i:04d}", "side": "right", "mirrored": False, "tip_convention": "manopth",
            "object_name": "002_master_chef_can", "object_id": 1, "sample_index": i,
            "source": {"index": i}}
    for name, (shape, _) in META_FIELDS.items():
        if shape is not None:
            meta[name] = rng.normal(size=shape)
    meta["K"] = np.array([[100.0, 0, CROP / 2], [0, 100.0, CROP / 2], [0, 0, 1]])
    meta["hand_root"] = np.array([0.0, 0.0, 0.5])
    meta["joints_2d"] = np.column_stack([rng.uniform(4, 24, 21), rng.uniform(44, 60, 21)])
    meta["sdf_counts"] = np.array(N_SDF)
    return key, img, seg, hm, sdf, meta


@pytest.fixture
def store(tmp_path):
    """Five records in two shards (3 + 2), no index."""
    out = tmp_path / "store"
    records = [(make_record(i)[0], encode_record(*make_record(i))) for i in range(5)]
    write_shard(out, 0, records[:3])
    write_shard(out, 1, records[3:])
    return out


def test_grid_size_tint_and_sdf_points(store, tmp_path):
    out = inspect_store(store, n=16, out=tmp_path / "sheet" / "grid.png")  # n larger than the store: all 5
    grid = cv2.imread(str(out), cv2.IMREAD_COLOR)[..., ::-1].astype(int)  # RGB
    assert grid.shape[:2] == grid_size(5) == (2 * (TILE + CAPTION_HEIGHT), 4 * 2 * TILE)
    assert not list(out.parent.glob("*.tmp"))
    scale = TILE / CROP
    centre = round((HAND_CENTRE + 0.5) * scale - 0.5)
    want = (1 - TINT_ALPHA) * GREY + TINT_ALPHA * np.array(HAND_COLOUR)
    for cell in range(5):  # every cell's overlay panel: the visible hand is tinted, the background is not
        row, col = divmod(cell, 4)
        y0, x0 = row * (TILE + CAPTION_HEIGHT), col * 2 * TILE
        np.testing.assert_allclose(grid[y0 + centre, x0 + centre], want, atol=3)
        np.testing.assert_allclose(grid[y0 + 4, x0 + TILE - 5], [GREY] * 3, atol=3)
        sdf_panel = grid[y0:y0 + TILE, x0 + TILE:x0 + 2 * TILE]
        coloured = np.abs(sdf_panel[..., 0] - sdf_panel[..., 1]) > 40  # blue/red SDF points, not grey
        assert coloured.sum() >= 10
    assert not grid[TILE + CAPTION_HEIGHT:, 2 * TILE:].any()  # the unused cells stay black


def test_fewer_records_and_determinism(store, tmp_path):
    first = inspect_store(store, n=2, out=tmp_path / "a.png", seed=3)
    second = inspect_store(store, n=2, out=tmp_path / "b.png", seed=3)
    assert first.read_bytes() == second.read_bytes()
    assert cv2.imread(str(first)).shape[:2] == grid_size(2) == (TILE + CAPTION_HEIGHT, 2 * 2 * TILE)


def test_pick_rows_spread_evenly():
    rows = pick_rows(100, 4, seed=0)
    assert [r // 25 for r in rows] == [0, 1, 2, 3]  # one per quarter
    np.testing.assert_array_equal(rows, pick_rows(100, 4, seed=0))
    assert not np.array_equal(rows, pick_rows(100, 4, seed=1))
    np.testing.assert_array_equal(pick_rows(5, 16, seed=7), np.arange(5))
    with pytest.raises(ValueError):
        pick_rows(5, 0, seed=0)


def test_missing_or_empty_store(tmp_path):
    with pytest.raises(DataError, match="nowhere"):
        inspect_store(tmp_path / "nowhere", out=tmp_path / "grid.png")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="empty"):
        inspect_store(tmp_path / "empty", out=tmp_path / "grid.png")
    assert not (tmp_path / "grid.png").exists()
