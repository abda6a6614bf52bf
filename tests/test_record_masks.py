"""record.masks = "dataset": the datasets' own masks as the visible mask targets, as upstream's loader reads them."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from hoidata import schema
from hoidata.datasets.frame import Frame
from hoidata.errors import DataError
from hoidata.geometry import crop as crop_ops
from hoidata.records.records import with_dataset_masks
from hoidata.records.settings import load_build_config

SIZE = 64  # mask grid of the test's crop
HAND, OBJ = (40, 30, 80, 60), (90, 50, 130, 100)  # x1, y1, x2, y2 rectangles in the 160 x 120 seg JPEG


def ho3d_frame(root: Path, write_seg: bool = True, mirror: bool = False) -> Frame:
    """An HO-3D frame of ``root/train/SEQ/rgb/0000.png`` whose seg JPEG (quarter resolution, RGB) has a red hand
    rectangle and a blue object rectangle, as HO-3D's are."""
    seq = root / "train" / "SEQ"
    (seq / "seg").mkdir(parents=True, exist_ok=True)
    seg_path = seq / "seg" / "0000.jpg"
    if write_seg:
        seg = np.zeros((120, 160, 3), np.uint8)
        seg[HAND[1]:HAND[3], HAND[0]:HAND[2], 0] = 255
        seg[OBJ[1]:OBJ[3], OBJ[0]:OBJ[2], 2] = 255
        cv2.imwrite(str(seg_path), cv2.cvtColor(seg, cv2.COLOR_RGB2BGR))
    eye = np.eye(4)
    return Frame("ho3d", "train", "SEQ_0000", seq / "rgb" / "0000.png", (640, 480), np.eye(3), "right", np.zeros(3),
                 "006_mustard_bottle", 5, eye, segmentation_path=seg_path if write_seg else None, mirror=mirror)


def full_frame_map() -> np.ndarray:
    """The source -> mask map of a crop holding the whole 640 px width at SIZE px (x1 = 0, y1 = -80, side 640)."""
    return crop_ops.crop_affine(np.array([0.0, -80.0, 640.0]), SIZE)


def expected_plane(rect, mirror: bool) -> np.ndarray:
    """The rectangle (seg pixels, x4 to the frame) on the SIZE grid: pixel centres inside it."""
    x1, y1, x2, y2 = (4 * v for v in rect)
    if mirror:
        x1, x2 = 640 - x2, 640 - x1
    centres = (np.arange(SIZE) + 0.5) * (640 / SIZE)  # crop pixel centre -> frame coordinate (edges convention)
    inside_x = (centres >= x1) & (centres < x2)
    inside_y = (centres - 80 >= y1) & (centres - 80 < y2)
    return inside_y[:, None] & inside_x[None, :]


@pytest.mark.parametrize("mirror", [False, True])
def test_visible_planes_are_the_datasets_masks(tmp_path, mirror):
    frame = ho3d_frame(tmp_path, mirror=mirror)
    rendered = np.full((SIZE, SIZE), schema.SEG_HAND_VISIBLE | schema.SEG_HAND_AMODAL, np.uint8)  # stand-in masks
    seg = with_dataset_masks(rendered, frame, full_frame_map())
    for bit, rect in ((schema.SEG_HAND_VISIBLE, HAND), (schema.SEG_OBJECT_VISIBLE, OBJ)):
        got, want = (seg & bit) > 0, expected_plane(rect, mirror)
        assert np.count_nonzero(got ^ want) <= 2 * SIZE // 8, bit  # nearest on an 8:1 grid: at most an edge row
        assert np.count_nonzero(got & want) >= 0.8 * np.count_nonzero(want)
    assert ((seg & schema.SEG_HAND_AMODAL) > 0).all()  # the amodal planes stay the rendered ones


def test_a_missing_mask_file_is_one_error_naming_it(tmp_path):
    frame = ho3d_frame(tmp_path, write_seg=False)
    with pytest.raises(DataError) as err:
        with_dataset_masks(np.zeros((SIZE, SIZE), np.uint8), frame, full_frame_map())
    assert str(tmp_path / "train" / "SEQ" / "seg" / "0000.jpg") in str(err.value) and "record.masks" in str(err.value)
    bad = ho3d_frame(tmp_path)
    bad.segmentation_path.write_bytes(bad.segmentation_path.read_bytes()[:200])  # cut short: corrupt
    with pytest.raises(DataError, match="0000.jpg"):
        with_dataset_masks(np.zeros((SIZE, SIZE), np.uint8), bad, full_frame_map())


def test_settings_refuse_unknown_choices_and_hot3d_dataset_masks():
    with pytest.raises(DataError, match="record.masks"):
        load_build_config("hot3d_clips", ['record.masks="dataset"'])
    with pytest.raises(DataError, match="record.masks"):
        load_build_config("dexycb", ['record.masks="gt"'])
    with pytest.raises(DataError, match="record.sdf_points"):
        load_build_config("dexycb", ['record.sdf_points="mesh_to_sdf"'])
    cfg = load_build_config("ho3d", ['record.masks="dataset"', 'record.sdf_points="deepsdf"'])
    assert (cfg.record.masks, cfg.record.sdf_points) == ("dataset", "deepsdf")
    default = load_build_config("toy")  # the project's defaults; the dataset presets take upstream's masks
    assert (default.record.masks, default.record.sdf_points) == ("rendered", "project")
    assert load_build_config("dexycb").record.masks == "dataset"


@pytest.mark.slow
def test_ho3d_build_stores_dataset_masks_and_skips_a_frame_without_one(ho3d_small, tmp_path, capsys):
    from hoidata.cli import main
    from hoidata.store import read_index
    from hoidata.store.shards import iter_records

    root = tmp_path / "ho3d"
    shutil.copytree(ho3d_small, root)
    segs = sorted((root / "train").glob("*/seg/*.jpg"))
    blank = segs[0]
    image = cv2.imread(str(blank))
    image[..., 2] = 0  # BGR on disk: no red, so no hand in the dataset's mask of this frame
    cv2.imwrite(str(blank), image)
    missing = segs[1]
    missing.unlink()
    out = tmp_path / "store"
    args = ["record.crop_size=128", "record.sdf_samples_hand=256", "record.sdf_samples_object=128", 'record.masks="dataset"',
            'record.sdf_points="deepsdf"']
    assert main(["build-sdf", "--dataset", "ho3d", "--root", str(root), "--out", str(out), *args]) == 0
    text = capsys.readouterr().out
    assert "supervision: masks the dataset's own masks" in text and "SDF samples deepsdf" in text
    assert str(missing) in text  # the skipped frame's line names the missing file
    index = read_index(out)
    assert len(index.keys) == len(segs) - 1
    records = {r[schema.META]["frame_id"]: r for r in iter_records(out)}
    blank_id = next(k for k in records if k.endswith(blank.stem) and blank.parent.parent.name in k)
    for frame_id, rec in records.items():
        hand = (rec[schema.SEG] & schema.SEG_HAND_VISIBLE) > 0
        assert (not hand.any()) if frame_id == blank_id else hand.sum() > 20, frame_id
        counts = rec[schema.META]["sdf_counts"]
        assert counts[2] == 0 and counts[0] > 200 and counts[1] > 100  # the two blocks, no shared uniform set


@pytest.mark.slow
def test_dexycb_build_stores_the_label_files_seg_in_the_crop(tiny_dexycb, tmp_path):
    """Right and mirrored left hands: the stored visible planes are label["seg"] == 255 / == the grasped object's id,
    flipped for a mirrored record and warped (nearest) through the record's crop, read here from the raw file."""
    from hoidata.build_sdf import build_store
    from hoidata.store import iter_records

    size = 128
    overrides = ['dataset.splits=["train"]', f"record.crop_size={size}", "record.sdf_samples_hand=256", "record.sdf_samples_object=128",
                 'record.masks="dataset"']
    build_store(load_build_config("toy", overrides), tiny_dexycb, tiny_dexycb / "mano", tiny_dexycb / "models",
                tmp_path / "store", workers=1, progress=False)
    records = list(iter_records(tmp_path / "store"))
    assert {r[schema.META]["mirrored"] for r in records} == {False, True}
    for rec in records:
        meta = rec[schema.META]
        seg = np.load(tiny_dexycb / meta["source"]["labels"])["seg"]  # the path is relative to the root
        planes = np.stack([seg == 255, seg == meta["object_id"]]).astype(np.uint8)
        planes = planes[:, :, ::-1] if meta["mirrored"] else planes
        x1, y1, x2, _ = meta["crop_box"]
        to_mask = crop_ops.resize_affine(size, size // 2) @ crop_ops.crop_affine(np.array([x1, y1, x2 - x1]), size)
        for plane, bit in zip(planes, (schema.SEG_HAND_VISIBLE, schema.SEG_OBJECT_VISIBLE)):
            want = crop_ops.warp_image(np.ascontiguousarray(plane), to_mask, size // 2, nearest=True) > 0
            assert np.array_equal((rec[schema.SEG] & bit) > 0, want), (meta["key"], bit)
        assert ((rec[schema.SEG] & schema.SEG_HAND_VISIBLE) > 0).sum() > 10
