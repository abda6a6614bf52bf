"""``record.crop = "upstream"``: a frame's crop, K, grid boxes and anchor as upstream HOISDF's test loader makes them.

The geometry is :mod:`hoidata.geometry.upstream_crop`; this module feeds it each dataset's values in the dtypes
upstream's loaders read them in (``data/dexycb.py`` / ``data/ho3d.py`` ``__getitem__``):

* DexYCB: the frame decoded with PIL; K float64 from the intrinsics; 2D joints float32; the grasped object's
  pose float32 (3, 4); hand grid box x1.1; anchor at the hand root's depth (float32). A left hand is flipped
  as upstream flips it: the image's columns reversed, ``u' = W - u - 1`` in float32, ``cx' = W - cx - 1``, and
  the object's axis-angle ``[1:]`` and translation ``x`` negated, through OpenCV's Rodrigues both ways.
* HO-3D (evaluation split): K float32 (``camMat``); the given hand box float32 (its two corners stand in for
  the joints) with grid box x1.2; the object pose from ``objRot`` / ``objTrans`` re-read from the frame's meta
  file (OpenCV's Rodrigues, OpenGL rows 1 and 2 negated); anchor at upstream's fixed depth.

The object's 21 box points come from the model folder's ``points.xyz`` (upstream's loaders), not from the
mesh the project's crop uses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata import schema
from hoidata.datasets.frame import Frame
from hoidata.errors import DataError
from hoidata.geometry import upstream_crop as up
from hoidata.reading import read_bytes
from hoidata.reading_media import MAX_IMAGE_BYTES, decode_pil

CROPS = ("project", "upstream")
IMAGE_SIZE = (640, 480)  # both datasets' frames; upstream clips its crop to them
HAND_GRID_FACTOR = {"dexycb": 1.1, "ho3d": 1.2}
REGION_STEP = 64  # px: a record.upstream_region square's side is a multiple of this


@dataclass(frozen=True)
class CropPolicy:
    """Which crop each frame's record gets, chosen once from the ``[record]`` settings
    (:meth:`hoidata.records.RecordSettings.crop_policy`; nothing downstream reads ``record.crop`` again): upstream's
    test crop, the frame region upstream's training warp samples, or the project's crop of ``crop_size`` px."""

    crop_size: int  # px: the project's crop
    upstream: bool = False  # record.crop = "upstream": its splits' records are upstream's test crop
    upstream_splits: tuple[str, ...] = ()  # record.crop_splits, under record.crop = "upstream"
    region_splits: tuple[str, ...] = ()  # record.upstream_region

    def upstream_crop(self, frame: Frame) -> bool:
        """Whether ``frame`` gets upstream's test crop."""
        return self.upstream and frame.split in self.upstream_splits

    def upstream_region(self, frame: Frame) -> bool:
        """Whether ``frame``'s record keeps the frame region upstream's training warp samples (labelled frames)."""
        return frame.split in self.region_splits and frame.has_hand_pose

    @property
    def needs_points(self) -> bool:
        """Whether records may need an object's ``points.xyz`` box (upstream's crop or region)."""
        return self.upstream or bool(self.region_splits)

    @property
    def reads_object_folders(self) -> bool:
        """Whether a build reads more of an object's folder than its mesh (upstream's crop reads points.xyz): the
        store's fingerprint then hashes the whole folders."""
        return self.upstream

    def record_size(self, frame: Frame, box3d: np.ndarray | None = None) -> int:
        """Side (px) of the frame's stored crop: upstream's 256 px input, the frame region's side (``box3d``: the
        object's upstream 21-point box), or ``crop_size``."""
        if self.upstream_crop(frame):
            return up.INPUT_SIZE
        if self.upstream_region(frame):
            return region_square(frame, box3d)[2]
        return self.crop_size


def decode_as_upstream(frame: Frame, data: bytes | None = None):
    """The frame's image as upstream decodes it: ``PIL.Image.open(path).convert("RGB")``, size checked (``data``: the
    file's bytes, read already)."""
    from hoidata.datasets.frame import read_rgb

    if frame.image is not None:
        raise DataError(frame.image_path, "record.crop", "upstream's crop needs the original image file")
    read_rgb(frame.image_path, frame.image_size)  # the project's checks: present, complete, decodable, the size
    data = read_bytes(frame.image_path, "image file", MAX_IMAGE_BYTES) if data is None else data
    return decode_pil(data, frame.image_path, None, "image")


def flip_image(image):
    """A PIL RGB image mirrored left to right as upstream does it (numpy column reversal)."""
    from PIL import Image

    return Image.fromarray(np.uint8(np.array(image, np.uint8, copy=True)[:, ::-1, :]))


def _dexycb_inputs(frame: Frame, box3d: np.ndarray, width: int) -> dict:
    """DexYCB: (K, hand points, object points, anchor depth) in upstream's dtypes; a left hand flipped."""
    import cv2

    K = np.asarray(frame.K, np.float64).copy()
    joints_uv = np.asarray(frame.joints_2d, np.float32).copy()
    pose = np.asarray(frame.object_pose[:3], np.float32)
    p2d = up.project_posed(box3d, K, pose)
    if frame.mirror:
        joints_uv[:, 0] = np.array(width, dtype=np.float32) - joints_uv[:, 0] - 1
        K[0, 2] = width - K[0, 2] - 1
        rot, trans = cv2.Rodrigues(pose[:, :3])[0].squeeze(), pose[:, 3].copy()
        trans[0] *= -1
        rot[1:] *= -1
        p2d = up.project_posed(box3d, K, np.concatenate([cv2.Rodrigues(rot)[0], trans[:, None]], axis=1))
    depth = np.float32(frame.joints_3d[0, 2])
    return {"K": K, "hand_uv": joints_uv, "object_uv": p2d, "anchor_depth": depth, "k_about_pp": True}


def _ho3d_inputs(frame: Frame, box3d: np.ndarray) -> dict:
    """HO-3D's evaluation split: (K, hand box corners, object points, fixed anchor depth) in upstream's dtypes."""
    import cv2

    from hoidata.datasets.ho3d import read_meta

    meta = read_meta(Path(frame.source["meta"]), frame.split)
    K = np.asarray(frame.K, np.float32)
    pose = np.zeros((4, 4))
    pose[:3, 3], pose[3, 3] = meta["objTrans"], 1
    pose[:3, :3] = cv2.Rodrigues(np.asarray(meta["objRot"]).reshape((3,)))[0]
    pose[1:3] = -pose[1:3]  # OpenGL -> OpenCV
    hand = np.asarray(frame.hand_box, np.float32).reshape(2, 2)
    return {"K": K, "hand_uv": hand, "object_uv": up.project_posed(box3d, K, pose),
            "anchor_depth": up.HO3D_ANCHOR_DEPTH, "k_about_pp": False}


def _ho3d_train_inputs(frame: Frame, box3d: np.ndarray) -> dict:
    """HO-3D's training split as upstream's train loader holds it: K float32, the 2D joints projected from the
    float32 3D joints, the 21 box points float32 (upstream reads them from its unreleased ``ho3d_train_data.json``;
    here projected as its evaluation path projects them, then float32)."""
    K = np.asarray(frame.K, np.float32)
    uv = np.matmul(K, np.asarray(frame.joints_3d, np.float32).T).T
    object_uv = up.project_posed(box3d, K, np.asarray(frame.object_pose, np.float64)).astype(np.float32)
    return {"K": K, "hand_uv": uv[:, :2] / uv[:, -1:], "object_uv": object_uv}


def train_inputs(frame: Frame, box3d: np.ndarray) -> dict:
    """What upstream's training ``data_aug`` reads of a labelled frame, in its dtypes: K, hand_uv (the 2D joints),
    object_uv (the projected 21-point box), flipped for a left hand (DexYCB)."""
    if frame.dataset == "dexycb":
        return _dexycb_inputs(frame, box3d, frame.image_size[0])
    if frame.dataset == "ho3d":
        return _ho3d_train_inputs(frame, box3d)
    raise DataError(frame.image_path, "record.upstream_region", f"upstream's training crop exists for DexYCB and "
                                                                f"HO-3D frames, not {frame.dataset}")


def region_square(frame: Frame, box3d: np.ndarray | None) -> tuple[int, int, int]:
    """(x0, y0, n) of the frame square a record.upstream_region record keeps (:func:`~hoidata.geometry.upstream_crop.
    train_region`), its side rounded up to a multiple of REGION_STEP px (few mask renderer sizes)."""
    if box3d is None:
        raise DataError(frame.image_path, "record.upstream_region", f"no points.xyz box for {frame.object_name}")
    inputs = train_inputs(frame, box3d)
    centre, side = up.base_square(inputs["hand_uv"], inputs["object_uv"], tuple(frame.image_size))
    if not np.isfinite(side) or side < 1:
        raise ValueError(f"upstream's crop box is empty (side {side} px): hand and object outside the image")
    x0, y0, n = up.train_region(centre, side)
    grown = -(-n // REGION_STEP) * REGION_STEP
    return x0 - (grown - n) // 2, y0 - (grown - n) // 2, grown


def frame_file(frame: Frame) -> bytes:
    """The frame's image file as shipped (what a record.upstream_region record keeps): a JPEG or PNG file."""
    data = read_bytes(frame.image_path, "image file", MAX_IMAGE_BYTES)
    if data[:2] != b"\xff\xd8" and data[:8] != b"\x89PNG\r\n\x1a\n":
        raise DataError(frame.image_path, "record.upstream_region", "the record keeps the frame's file as shipped: a "
                                                                    "JPEG or PNG file, not this")
    return data


def region_view(frame: Frame, box3d: np.ndarray) -> dict:
    """A record.upstream_region record's image and fields: ``frame_bytes`` the original frame file's bytes (what the
    record stores, as shipped), ``img`` (n, n, 3) uint8 the square of that frame (decoded as upstream decodes it,
    flipped for a left hand, black outside the frame; what readers get), ``to_pixels`` (3, 3) the frame -> region
    pixel map (a translation), ``meta``: schema.REGION_FIELDS."""
    x0, y0, n = region_square(frame, box3d)
    data = frame_file(frame)
    image = decode_as_upstream(frame, data)
    image = flip_image(image) if frame.mirror else image
    inputs = train_inputs(frame, box3d)
    to_pixels = np.eye(3)
    to_pixels[:2, 2] = -x0, -y0
    meta = {"region": schema.UPSTREAM_REGION, "region_origin": np.array([x0, y0], np.float64),
            "frame_size": np.array(image.size, np.float64), "frame_K": np.asarray(inputs["K"], np.float64),
            "frame_joints_2d": np.asarray(inputs["hand_uv"], np.float64),
            "frame_box21_2d": np.asarray(inputs["object_uv"], np.float64)}
    return {"img": up.cut_region(np.asarray(image), x0, y0, n), "to_pixels": to_pixels, "meta": meta,
            "frame_bytes": data}


def upstream_view(frame: Frame, box3d: np.ndarray) -> up.UpstreamCrop:
    """Upstream's test crop of ``frame`` (as read, before the project mirrors it; ``frame.mirror`` asks for the
    flip). ``box3d`` (21, 3): :func:`~hoidata.geometry.upstream_crop.box21_upstream` of the object's points.xyz.
    K, boxes and anchor come out in the dtypes upstream's loader hands the network (K float32 ...)."""
    if frame.dataset == "dexycb" and frame.joints_2d is not None:
        image = decode_as_upstream(frame)
        inputs, factor = _dexycb_inputs(frame, box3d, image.size[0]), HAND_GRID_FACTOR["dexycb"]
        image = flip_image(image) if frame.mirror else image
    elif frame.dataset == "ho3d" and frame.joints_2d is None and frame.hand_box is not None:
        image, inputs, factor = decode_as_upstream(frame), _ho3d_inputs(frame, box3d), HAND_GRID_FACTOR["ho3d"]
    else:
        raise DataError(frame.image_path, "record.crop", "upstream's test crop exists for DexYCB frames and HO-3D's "
                                                         f"evaluation split, not a {frame.dataset} {frame.split} frame")
    if image.size != IMAGE_SIZE:
        raise DataError(frame.image_path, None, f"upstream's crop expects {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]} frames")
    view = up.upstream_crop(image, hand_grid_factor=factor, **inputs)
    view.K = view.K.astype(np.float32)  # meta_info's cam_intr, on both datasets
    if frame.dataset == "ho3d":  # its loader hands the boxes on as float32 (DexYCB's as float64)
        view.grid_hand_box, view.grid_object_box = (np.float32(b) for b in (view.grid_hand_box, view.grid_object_box))
    return view


def crop_meta(view: up.UpstreamCrop) -> dict:
    """The record's schema.CROP_FIELDS of an upstream view."""
    return {"crop": schema.UPSTREAM_CROP, "grid_hand_box": np.asarray(view.grid_hand_box, np.float64),
            "grid_object_box": np.asarray(view.grid_object_box, np.float64),
            "object_anchor": np.asarray(view.anchor, np.float64)}


def crop_box(view: up.UpstreamCrop) -> np.ndarray:
    """(x1, y1, side) of the crop square, source pixels (the record's ``crop_box``: x1, y1, x1 + side, y1 + side)."""
    half = view.side / 2
    return np.array([view.centre[0] - half, view.centre[1] - half, view.side], np.float64)
