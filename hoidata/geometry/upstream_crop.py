"""Upstream HOISDF's test-time crop (``data/dexycb.py`` / ``data/ho3d.py`` ``data_crop`` and the helpers of
``data/dataset_util.py``), reproduced operation for operation. Pure numpy + PIL.

Why a second crop beside :mod:`hoidata.geometry.crop`: the authors' released weights were trained on these
exact pixels, boxes and anchor, so evaluating them needs the same inputs bit for bit (``docs/stores.md``).
The arithmetic here follows upstream's, dtypes included (float32 boxes, integer-truncated centres, float32
affine, PIL nearest-neighbour warp), because a different rounding moves an integer centre or a nearest pixel.

Conventions (upstream's, not the project's):

* boxes are (4,) x1, y1, x2, y2 pixels, built about ``int()``-truncated centres;
* the crop is the square of side ``side`` (source px) about the integer ``centre`` of the union of the hand and
  object boxes (each x1.5) clipped to the image, mapped to ``size`` px by ``u' = (size/side)(u - c) + size/2``;
* PIL samples output pixel x at source coordinate ``A^-1 (x + 1/2)`` (pixel corners at integers) and takes the
  pixel under it, while the returned K is ``A @ K``: it sits ``0.5 (1 - size/side)`` px off the pixels
  (:func:`pixel_affine` gives the map the pixels really follow, in the project's OpenCV convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CROP_FACTOR = 1.5  # hand and object boxes are each expanded 1.5x about their integer centres for the crop
OBJECT_GRID_FACTOR = 1.0  # the object grid-filter box: the projected 21 points' box itself
HO3D_ANCHOR_DEPTH = 0.5244322  # metres: upstream's fixed object-anchor depth on HO-3D (cfg.obj_depth_mean_value)
INPUT_SIZE = 256  # px: upstream's network input (cfg.input_img_shape)


def joints_box(uv: np.ndarray, factor: float) -> np.ndarray:
    """Box (4,) float32 of pixels ``uv`` (N, 2) float32 scaled by ``factor`` about its integer-truncated centre
    (upstream's ``get_bbox_joints``)."""
    lo, hi = uv.min(0), uv.max(0)
    centre = np.asarray([int((hi[0] + lo[0]) / 2), int((hi[1] + lo[1]) / 2)])
    delta = np.asarray([(hi[0] - lo[0]) * factor / 2, (hi[1] - lo[1]) * factor / 2])
    return np.array([*(centre - delta), *(centre + delta)], dtype=np.float32)


def fused_square(box_a: np.ndarray, box_b: np.ndarray, image_size: tuple[int, int]):
    """(integer centre (2,), side) of the union of two boxes (4,) clipped to the image (width, height) px
    (upstream's ``fuse_bbox``: the side is the longer side of the clipped union)."""
    corners = np.concatenate((box_a.reshape(2, 2), box_b.reshape(2, 2)), axis=0)
    min_x, min_y = corners.min(0)
    min_x, min_y = max(0, min_x), max(0, min_y)
    max_x, max_y = corners.max(0)
    max_x, max_y = min(max_x, image_size[0]), min(max_y, image_size[1])
    centre = np.asarray([int((max_x + min_x) / 2), int((max_y + min_y) / 2)])
    return centre, max(max_x - min_x, max_y - min_y) * 1.0


def scale_translate(centre, side, size: int) -> np.ndarray:
    """(3, 3) float64 map of the square of ``side`` px about ``centre`` onto ``size`` px (upstream's
    ``get_affine_trans_no_rot``; its entries are computed in ``side``'s dtype, as upstream's are)."""
    out = np.zeros((3, 3))
    out[0, 0] = float(size) / side
    out[1, 1] = float(size) / side
    out[0, 2] = size * (-float(centre[0]) / side + 0.5)
    out[1, 2] = size * (-float(centre[1]) / side + 0.5)
    out[2, 2] = 1
    return out


def rotated_crop_affines(centre: np.ndarray, side, rot: float, K: np.ndarray, size: int = INPUT_SIZE):
    """(pixel affine, K affine, rotation (3, 3)) float32 of a crop of ``side`` px about ``centre`` turned by ``rot``
    radians (upstream's ``get_affine_transform`` with K: the image turns about the origin, then the crop is cut about
    the turned centre; K's affine is cut about the centre turned about the principal point, a round trip that can
    differ from the first in the last bit: DexYCB's K uses it, HO-3D's the first)."""
    rot_mat = np.zeros((3, 3))
    sn, cs = np.sin(rot), np.cos(rot)
    rot_mat[0, :2] = [cs, -sn]
    rot_mat[1, :2] = [sn, cs]
    rot_mat[2, 2] = 1
    homogeneous = centre.tolist() + [1]
    post = scale_translate(rot_mat.dot(homogeneous)[:2], side, size)
    to_pp, from_pp = np.eye(3), np.eye(3)
    to_pp[:2, 2] = -K[0, 2], -K[1, 2]
    from_pp[:2, 2] = K[0, 2], K[1, 2]
    about_pp = from_pp.dot(rot_mat).dot(to_pp).dot(homogeneous)
    return (post.dot(rot_mat).astype(np.float32), scale_translate(about_pp[:2], side, size).astype(np.float32),
            rot_mat.astype(np.float32))


def crop_affines(centre: np.ndarray, side, size: int, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(affine, affine for K) float32 (3, 3) of an unrotated crop: :func:`rotated_crop_affines` at rot 0."""
    affine, affine_k, _ = rotated_crop_affines(centre, side, 0.0, K, size)
    return affine, affine_k


def transform_points(uv: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) through an affine (3, 3) -> (N, 2) float64 (upstream's ``transform_coords``)."""
    hom = np.concatenate([uv, np.ones([np.array(uv).shape[0], 1])], 1)
    return affine.dot(hom.transpose()).transpose()[:, :2]


def warp_pil(image, affine: np.ndarray, size: int):
    """PIL image -> PIL image (size, size) through ``affine`` (3, 3) with PIL's default nearest-neighbour AFFINE
    transform, black outside (upstream's ``transform_img``)."""
    from PIL import Image

    inv = np.linalg.inv(affine)
    return image.transform((size, size), Image.AFFINE, (inv[0, 0], inv[0, 1], inv[0, 2], inv[1, 0], inv[1, 1], inv[1, 2]))


def warp_nearest(image, affine: np.ndarray, size: int) -> np.ndarray:
    """PIL image (RGB) -> (size, size, 3) uint8 through :func:`warp_pil` (upstream's ``transform_img`` then
    ``crop``)."""
    return np.asarray(warp_pil(image, affine, size).crop((0, 0, size, size)))


def pixel_affine(affine: np.ndarray) -> np.ndarray:
    """(3, 3) float64 map from source to crop pixels, in the project's convention (centres at integers), that
    PIL's warp by ``affine`` follows: ``x = a u + b + (a - 1) / 2``. Use it for what must sit on the pixels
    (masks); the record's K is upstream's ``affine @ K``."""
    out = np.asarray(affine, np.float64).copy()
    out[:2, 2] += 0.5 * (np.diag(out)[:2] - 1)
    return out


def box21_upstream(points: np.ndarray) -> np.ndarray:
    """(21, 3) float64 keypoints of the axis-aligned box of ``points`` (N, 3) (a model's ``points.xyz``): 8
    corners, 12 edge midpoints, centre (upstream's ``get_bbox21_3d_from_dict``; the set and the rounding of
    each point are upstream's, the order is not used)."""
    lo, hi = points.min(0), points.max(0)
    corners = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    edges = [(0, 2), (1, 3), (2, 3), (0, 1), (4, 6), (5, 7), (6, 7), (4, 5), (6, 2), (4, 0), (7, 3), (5, 1)]
    mids = [(corners[i] + corners[j]) / 2 for i, j in edges]
    return np.stack([*corners, *mids, (corners[4] + corners[3]) / 2])


def project_posed(xyz: np.ndarray, K: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Model points (N, 3) posed by ``pose`` ([R | t], (3, 4) or (4, 4)) and projected with K -> (N, 2)
    (upstream's ``projectPoints``; dtypes follow the inputs')."""
    uv = np.matmul(K, np.matmul(pose[:3, :3], xyz.T) + pose[:3, 3].reshape(-1, 1)).T
    return uv[:, :2] / uv[:, -1:]


def centre_camera(box: np.ndarray, depth, K: np.ndarray) -> np.ndarray:
    """(3,) float32 camera-frame point of the box's integer-truncated centre at ``depth`` m (upstream's
    ``get_center_cam`` then ``astype(float32)``)."""
    centre = np.asarray([int((box[2] + box[0]) / 2), int((box[3] + box[1]) / 2), depth])  # float64, as upstream's
    x = (centre[0] - K[0, 2]) / K[0, 0] * centre[2]
    y = (centre[1] - K[1, 2]) / K[1, 1] * centre[2]
    return np.array([x, y, centre[2]]).astype(np.float32)


@dataclass
class UpstreamCrop:
    """One frame's upstream test crop: image (S, S, 3) uint8; K (3, 3) upstream's crop intrinsics; grid boxes
    (4,) crop px; anchor (3,) float32 m; centre (2,) int and side of the crop square, source px; affine (3, 3)
    float32 source -> crop (upstream's)."""

    image: np.ndarray
    K: np.ndarray
    grid_hand_box: np.ndarray
    grid_object_box: np.ndarray
    anchor: np.ndarray
    centre: np.ndarray
    side: float
    affine: np.ndarray


def upstream_crop(image, K: np.ndarray, hand_uv: np.ndarray, object_uv: np.ndarray, hand_grid_factor: float,
                  anchor_depth, k_about_pp: bool, size: int = INPUT_SIZE) -> UpstreamCrop:
    """Upstream's ``data_crop`` for one frame.

    image: the decoded original frame (PIL RGB; flipped already for a left hand); K (3, 3) its intrinsics in
    upstream's dtype (DexYCB float64, HO-3D float32); hand_uv (N, 2) float32: DexYCB's 2D joints, or HO-3D's
    given hand box as its two corners; object_uv (21, 2): the projected box keypoints; hand_grid_factor: 1.1
    (DexYCB) or 1.2 (HO-3D); anchor_depth: the hand root's z (DexYCB, float32) or HO3D_ANCHOR_DEPTH;
    k_about_pp: DexYCB's K comes from the principal-point round trip's affine (see :func:`crop_affines`).
    Raises ValueError when the clipped box is empty (the build skips such a frame with this reason).
    """
    crop_hand, crop_obj = joints_box(hand_uv, CROP_FACTOR), joints_box(object_uv, CROP_FACTOR)
    grid_hand, grid_obj = joints_box(hand_uv, hand_grid_factor), joints_box(object_uv, OBJECT_GRID_FACTOR)
    centre, side = fused_square(crop_hand, crop_obj, image.size)
    if not np.isfinite(side) or side < 1:  # upstream would divide by zero; its full-set filter drops such frames
        raise ValueError(f"upstream's crop box is empty (side {side} px): hand and object outside the image")
    affine, affine_k = crop_affines(centre, side, size, K)
    grid_hand = transform_points(grid_hand.reshape(2, 2), affine).flatten()
    grid_obj = transform_points(grid_obj.reshape(2, 2), affine).flatten()
    K_crop = (affine_k if k_about_pp else affine).dot(K)
    return UpstreamCrop(warp_nearest(image, affine, size), K_crop, grid_hand, grid_obj,
                        centre_camera(grid_obj, anchor_depth, K_crop), centre, float(side), affine)


# upstream's training jitter (data/dexycb.py, data/ho3d.py ``__init__`` defaults and ``data_aug``)
CENTER_JITTER = 0.1  # centre + CENTER_JITTER * side * U(-1, 1) per axis
SCALE_JITTER = 0.2  # side * clip(SCALE_JITTER * N(0, 1) + 1, 1 - SCALE_JITTER, 1 + SCALE_JITTER)
REGION_MARGIN = 2  # px beyond the farthest pixel a jittered, scaled and rotated crop can sample


def base_square(hand_uv: np.ndarray, object_uv: np.ndarray, image_size: tuple[int, int]):
    """(integer centre (2,), side) of upstream's crop square before any jitter: the union of the hand points' box
    x1.5 and the object's 21-point box x1.5, clipped to the image (width, height) (``data_aug``'s first lines)."""
    return fused_square(joints_box(hand_uv, CROP_FACTOR), joints_box(object_uv, CROP_FACTOR), image_size)



def train_region(centre: np.ndarray, side: float) -> tuple[int, int, int]:
    """(x0, y0, n): the square of n px at (x0, y0), source pixels, holding every pixel upstream's training warp can
    sample about ``centre`` / ``side`` (:func:`base_square`): the centre moves by up to CENTER_JITTER * side per
    axis, the side grows to (1 + SCALE_JITTER) * side and any rotation turns it, so it stays within
    (CENTER_JITTER + (1 + SCALE_JITTER) / sqrt(2)) * side of the centre, plus REGION_MARGIN px for the rounding of
    a nearest-neighbour pick."""
    reach = (CENTER_JITTER + (1 + SCALE_JITTER) / np.sqrt(2)) * float(side) + REGION_MARGIN
    x0, y0 = (int(np.floor(float(c) - reach)) for c in centre)
    return x0, y0, int(np.ceil(2 * reach)) + 1


def cut_region(image: np.ndarray, x0: int, y0: int, n: int) -> np.ndarray:
    """(n, n, 3) uint8: the square of ``image`` (H, W, 3) at (x0, y0), black where it leaves the image."""
    out = np.zeros((n, n, 3), np.uint8)
    h, w = image.shape[:2]
    sx0, sy0, sx1, sy1 = max(x0, 0), max(y0, 0), min(x0 + n, w), min(y0 + n, h)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = image[sy0:sy1, sx0:sx1]
    return out
