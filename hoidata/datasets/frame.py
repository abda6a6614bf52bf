"""The Frame: one annotated image, as every dataset reader yields it.

All geometry is in the project's conventions (docs/conventions.md): OpenCV camera frame (x right,
y down, z forward), metres, pixels, 21 joints in DexYCB/manopth order, MANO pose as 48 axis-angle
values in the flat-hand-mean convention. Readers convert at the border (HO-3D's OpenGL frame, DexYCB's
PCA pose) so nothing downstream has to know where a frame came from.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.reading_media import read_image


@dataclass
class Frame:
    """One annotated image.

    Hand fields are ``None`` where the dataset withholds them (HO-3D's evaluation split keeps only the
    root joint and a hand box).
    """

    dataset: str  # 'dexycb' | 'ho3d' | 'hot3d_clips' | 'toy'
    split: str  # 'train' | 'val' | 'test' | 'evaluation'
    frame_id: str  # unique within the dataset, no dots (safe as a WebDataset key)
    image_path: Path
    image_size: tuple[int, int]  # (width, height) pixels
    K: np.ndarray  # (3, 3) intrinsics of the stored image
    side: str  # 'right' | 'left' (as captured; see ``mirror``)
    root_3d: np.ndarray  # (3,) wrist joint, camera frame, metres
    object_name: str  # YCB folder name, e.g. '006_mustard_bottle'
    object_id: int  # DexYCB class id 1..21
    object_pose: np.ndarray  # (4, 4) model -> camera
    mano_pose: np.ndarray | None = None  # (48,) flat-hand-mean axis-angle, camera frame
    mano_betas: np.ndarray | None = None  # (10,)
    mano_transl: np.ndarray | None = None  # (3,) metres, camera frame
    joints_3d: np.ndarray | None = None  # (21, 3) camera frame, metres, DexYCB order
    joints_2d: np.ndarray | None = None  # (21, 2) pixels
    tip_convention: str = "manopth"  # fingertip vertices the joints use: 'manopth' | 'ho3d'
    hand_box: np.ndarray | None = None  # (4,) x1, y1, x2, y2 pixels, where the dataset gives one
    mirror: bool = False  # True: a left hand that a "full" setting asks to mirror to a right hand
    fix_left_shapedirs: bool = True  # left hands: the MANO_LEFT shape convention the labels were made with
    segmentation_path: Path | None = None  # the dataset's own segmentation, if any
    sample_index: int = -1  # DexYCB: index in the toolkit's enumeration of the split (result-file id); else -1
    source: dict = field(default_factory=dict)  # provenance: raw file paths and indices
    image: np.ndarray | None = None  # (H, W, 3) RGB already in memory (synthetic renders); else read image_path
    labels: np.ndarray | None = None  # (H, W) in-memory label map of the render that made `image`: 1 hand, 2 object
    image_source: object = None  # a picklable callable making the RGB image on demand (HOT3D: the crop's remap)

    @property
    def has_hand_pose(self) -> bool:
        return self.mano_pose is not None

    def load_image(self) -> np.ndarray:
        """The RGB image (H, W, 3) uint8. Raises DataError naming the file if it cannot be read."""
        if self.image is not None:
            return self.image
        if self.image_source is not None:
            return self.image_source()
        return read_rgb(self.image_path, self.image_size)


def read_rgb(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image file as RGB uint8 (H, W, 3), optionally checking its (width, height).

    A JPEG or PNG that is cut short is a DataError (OpenCV alone would fill the missing part with grey).
    """
    import cv2

    img = read_image(path, cv2.IMREAD_COLOR, "image file")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise DataError(path, None, f"image is {img.shape[1]}x{img.shape[0]}, expected {size[0]}x{size[1]}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


@dataclass
class Skip:
    """A frame a reader left out, and why (recorded in the store's index, never silent)."""

    frame_id: str
    reason: str
    path: str = ""
    sample_index: int = -1  # DexYCB: the frame's id in the toolkit's enumeration of its split; else -1
