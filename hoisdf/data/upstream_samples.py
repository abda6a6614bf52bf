"""``augment.upstream``: a record.upstream_region record -> one training sample augmented as upstream HOISDF augments
it (:mod:`hoisdf.data.upstream_augment`), in the loader's per-sample layout, in the loader's worker.

The sample is the network input already: img (256, 256, 3) uint8 after blur and colour, seg_bits (128, 128), K, 2D
joints and grid boxes in its pixels, every 3D label turned by the draw's rotation, the object anchor upstream's
(``object_anchor``), and ``upstream_aug`` True, so that :func:`hoisdf.data.augment.augment_batch` passes it through.

Masks: the record's planes (half the region's side) are read nearest at the frame pixel upstream's warp reads for
each 128-px output pixel (its 256-px warp, then Pillow's nearest resize to 128 picks pixel 2 x + 1).
"""

from __future__ import annotations

import numpy as np

from hoidata.errors import DataError
from hoisdf.data.upstream_augment import HEATMAP_RES, ROTATIONS, UpstreamDraw, augment_view, footprint_inside

POINT_KEYS = ("hand_points", "obj_points", "hand_near_points", "obj_near_points")


def frame_inputs(meta: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, joints_uv, box21_uv) of a region record in upstream's dtypes (DexYCB: K and the box float64; HO-3D: float32;
    the joints float32), so its arithmetic rounds as upstream's does."""
    wide = np.float64 if meta["dataset"] == "dexycb" else np.float32
    return (np.asarray(meta["frame_K"], wide), np.asarray(meta["frame_joints_2d"], np.float32),
            np.asarray(meta["frame_box21_2d"], wide))


def upstream_rule(meta: dict, key: str) -> str:
    """The dataset's rule name ("dexycb" | "ho3d"): grid factor, anchor depth and rotation rule; DataError otherwise."""
    if meta["dataset"] not in ROTATIONS:
        raise DataError(None, key, f"upstream's training augmentation exists for {sorted(ROTATIONS)}, not "
                                   f"{meta['dataset']!r}")
    return meta["dataset"]


def warp_mask_bits(bits: np.ndarray, affine: np.ndarray, origin, frame_size) -> np.ndarray:
    """(HEATMAP_RES, HEATMAP_RES) uint8: the record's mask bits (h, h) at half the region's side, read nearest at
    the frame pixel that upstream's warp by ``affine`` reads for each output mask pixel; 0 outside the frame."""
    grid = (2 * np.arange(HEATMAP_RES) + 1.5).astype(np.float64)
    xs, ys = np.meshgrid(grid, grid)
    inv = np.linalg.inv(affine.astype(np.float64))
    fx = np.floor(inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2])
    fy = np.floor(inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2])
    inside = (fx >= 0) & (fy >= 0) & (fx < frame_size[0]) & (fy < frame_size[1])
    mx, my = np.floor((fx - origin[0]) / 2).astype(np.int64), np.floor((fy - origin[1]) / 2).astype(np.int64)
    inside &= (mx >= 0) & (my >= 0) & (mx < bits.shape[1]) & (my < bits.shape[0])
    out = np.zeros((HEATMAP_RES, HEATMAP_RES), np.uint8)
    out[inside] = bits[my[inside], mx[inside]]
    return out


def rotate_pose(object_pose: np.ndarray, mano_pose: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(object pose (4, 4), MANO pose (48,)) turned by ``rot`` (3, 3) about the camera origin, float32."""
    import cv2

    turn = np.eye(4)
    turn[:3, :3] = rot
    glob = cv2.Rodrigues(rot.astype(np.float64) @ cv2.Rodrigues(np.asarray(mano_pose[:3], np.float64))[0])[0][:, 0]
    return (turn @ object_pose).astype(np.float32), np.concatenate([glob, mano_pose[3:]]).astype(np.float32)


def upstream_sample(rec_img: np.ndarray, meta: dict, sample: dict, draw: UpstreamDraw, key: str,
                    frame: np.ndarray | None = None) -> dict:
    """The loader's per-sample dict ``sample`` (made from the record as for the project's augmentation) with the
    region record's image ``rec_img`` replaced by upstream's augmented 256 px input and every label moved with it.
    ``frame``: the whole (flipped) frame (H, W, 3) the record stores (hoidata.store.FRAME_IMAGE), warped in place of
    ``rec_img`` (the same pixels where the region holds them; no rebuilt frame)."""
    if "region" not in meta:
        raise DataError(None, key, "augment.upstream needs records built with record.upstream_region (the frame region "
                                   "upstream's training warp samples); this record has a project crop")
    dataset = upstream_rule(meta, key)
    origin, frame_size = meta["region_origin"].astype(np.int64), meta["frame_size"].astype(np.int64)
    K, joints_uv, box21_uv = frame_inputs(meta)
    joints = np.asarray(meta["joints_3d"], np.float32)
    source, at = (rec_img, origin) if frame is None else (frame, np.zeros(2, np.int64))
    view = augment_view(source, at, frame_size, K, joints_uv, box21_uv, joints, dataset, draw)
    if frame is None and not footprint_inside(view.affine, origin, rec_img.shape[0], frame_size):
        raise DataError(None, key, "the draw samples frame pixels outside the stored region (a region built for "
                                   "other jitter ranges?)")
    rot = view.rot
    out = {k: v for k, v in sample.items() if k not in ("img", "seg_bits")}
    for name in POINT_KEYS:
        if name in out:
            out[name] = out[name].dot(rot.T).astype(np.float32)
    out["object_pose"], out["mano_pose"] = rotate_pose(np.asarray(meta["object_pose"]), sample["mano_pose"], rot)
    out.update({
        "img": np.array(view.image), "seg_bits": warp_mask_bits(sample["seg_bits"], view.affine, origin, frame_size),
        "K": view.K.astype(np.float32), "joints_3d": view.joints_3d,
        "hand_root": np.asarray(sample["hand_root"], np.float32).dot(rot.T),
        "joints_2d": view.joints_uv.astype(np.float32), "hand_box": view.hand_box.astype(np.float32),
        "object_box": view.object_box.astype(np.float32), "upstream_crop": np.bool_(False),
        "grid_hand_box": view.hand_box.astype(np.float32), "grid_object_box": view.object_box.astype(np.float32),
        "object_anchor": view.anchor.astype(np.float32), "upstream_aug": np.bool_(True),
        "crop_scale": np.float32(view.size / view.side)})
    return out


def project_sample(meta: dict, key: str) -> None:
    """A region record met by the project's augmentation: DataError (its image is a frame square of varying side)."""
    if "region" in meta:
        raise DataError(None, key, "a record.upstream_region record is a frame region for augment.upstream = true; "
                                   "the project's augmentation needs project-crop records")


def finish_sample(rec_img: np.ndarray, meta: dict, sample: dict, key: str, seed,
                  frame: np.ndarray | None = None) -> dict:
    """The loader's last per-sample step: ``seed`` falsy: the sample as it is (a region record refused); else a
    list of ints seeding this sample's draw (:func:`~hoisdf.data.upstream_augment.draw_upstream`, the record's
    dataset's rotation rule) and :func:`upstream_sample` (``frame``: the record's whole frame, when it stores one)."""
    from hoisdf.data.upstream_augment import ROTATIONS, draw_upstream

    if not seed:
        project_sample(meta, key)
        return sample
    rule = ROTATIONS[upstream_rule(meta, key)]
    return upstream_sample(rec_img, meta, sample, draw_upstream(np.random.default_rng(seed), rule), key, frame)
