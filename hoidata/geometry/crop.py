"""Square crops around hand and object, the projection of camera points to pixels, and the intrinsics of the cropped
pixels. Pure numpy.

Pixel convention (OpenCV): pixel (col, row) is centred at integer (u, v). A crop of a square box
(x1, y1, side) in source pixels resized to ``size`` pixels is the affine map
``u' = a (u - x1) - 1/2`` with ``a = size / side``: the box's left edge x1 (a continuous coordinate)
maps to the crop's left edge -1/2. The crop's intrinsics are ``A @ K``. ``cv2.warpAffine`` with the same 2x3 matrix
produces exactly those pixels, so labels projected with the new K land on the warped image.
"""

from __future__ import annotations

import numpy as np

# Context around the hand-object box so training-time jitter stays inside the stored crop: centre
# jitter +-10 % and zoom-out up to 1.2x (HOISDF's augmentation), and any in-plane rotation (a square
# rotated by 45 degrees needs sqrt(2) of its side): 1.2 * sqrt(2) * 1.2 ~= 2.0.
DEFAULT_CONTEXT = 2.0
BOX_EXPAND = 1.5  # hand box and object box are each expanded 1.5x about their centres (HOISDF)


def box_from_points(uv: np.ndarray) -> np.ndarray:
    """Tight box (4,) x1, y1, x2, y2 around pixel points (N, 2)."""
    return np.concatenate([uv.min(0), uv.max(0)])


def expand_box(box: np.ndarray, factor: float) -> np.ndarray:
    """Box (4,) x1, y1, x2, y2 scaled by `factor` about its centre."""
    c, half = (box[:2] + box[2:]) / 2, (box[2:] - box[:2]) / 2 * factor
    return np.concatenate([c - half, c + half])


def union_box(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.concatenate([np.minimum(a[:2], b[:2]), np.maximum(a[2:], b[2:])])


def square_crop_box(hand_uv: np.ndarray, object_uv: np.ndarray, context: float = DEFAULT_CONTEXT,
                    min_side: float = 32.0) -> np.ndarray:
    """Square box (x1, y1, side) around hand points (N, 2) and object points (M, 2), pixels.

    Each point set's tight box is expanded by BOX_EXPAND, the union is squared about its centre and
    scaled by `context`. Nothing is clipped to the image: pixels outside it become black.
    """
    box = union_box(expand_box(box_from_points(hand_uv), BOX_EXPAND), expand_box(box_from_points(object_uv), BOX_EXPAND))
    centre = (box[:2] + box[2:]) / 2
    side = max(float(np.max(box[2:] - box[:2])) * context, min_side)
    return np.array([centre[0] - side / 2, centre[1] - side / 2, side])


def crop_affine(box: np.ndarray, size: int) -> np.ndarray:
    """(3, 3) map from source pixels to crop pixels for a square box (x1, y1, side) resized to `size`."""
    x1, y1, side = box
    a = size / side
    return np.array([[a, 0.0, -a * x1 - 0.5], [0.0, a, -a * y1 - 0.5], [0.0, 0.0, 1.0]])


def resize_affine(from_size: int, to_size: int) -> np.ndarray:
    """(3, 3) map between the pixels of the same square image at two resolutions (centres to centres)."""
    a = to_size / from_size
    return np.array([[a, 0.0, (a - 1) / 2], [0.0, a, (a - 1) / 2], [0.0, 0.0, 1.0]])


def warp_image(image: np.ndarray, affine: np.ndarray, size: int, nearest: bool = False) -> np.ndarray:
    """Apply a source->crop affine (3, 3) to an image; outside the source is black (0)."""
    import cv2

    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA if affine[0, 0] < 1 else cv2.INTER_LINEAR
    return cv2.warpAffine(image, affine[:2], (size, size), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def apply_affine(affine: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) through a (3, 3) affine."""
    return uv @ affine[:2, :2].T + affine[:2, 2]


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (..., 3) -> pixels (..., 2) with intrinsics K (3, 3)."""
    uvw = points @ np.asarray(K).T
    return uvw[..., :2] / uvw[..., 2:3]
