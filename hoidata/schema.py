"""The record schema (version 1): one WebDataset sample per frame. Writer and reader both use this.

No string literal of a member name appears anywhere else in the project: import the constants.

Members of a record (key ``<dataset>-<split>-<frame id>``, no dots):

==============  =============================================================================
``img.jpg``     RGB crop, square, ``crop_size`` px (default 512), JPEG; pixels outside the image black
``img.png``     in place of ``img.jpg`` in an upstream-crop record (see below): the RGB crop, lossless PNG
``frame.jpg``   in place of ``img.jpg`` in an upstream-region record (see below): the original frame's file as shipped
                (``frame.png`` when that file is a PNG)
``seg.png``     uint8 single channel at ``crop_size // 2``: bit 0 visible hand, bit 1 visible object,
                bit 2 amodal hand, bit 3 amodal object
``hm.png``      uint8 single channel at ``crop_size // 2``: sum of 21 joint Gaussians (sigma 1.25 px),
                clipped to 1 and scaled to 255
``sdf.npy``     int16 (N, 6): x, y, z relative to the hand root (camera axes), signed distance to the
                hand, signed distance to the object, all in units of ``SDF_QUANTUM`` metres; then the
                hand part label (0-15, MANO joint order; -1 where not applicable). Negative = inside.
``meta.json``   labels (see :data:`META_FIELDS`), UTF-8 JSON, metres and crop pixels
==============  =============================================================================

SDF sample order inside ``sdf.npy``: the hand set (near the hand surface), then the object set, then
the uniform set; ``meta.json`` holds the three counts under ``sdf_counts``.

Record kinds (``meta.json`` ``kind``; :data:`RECORD_KINDS` lists each kind's members and meta fields):

``full``   every member and every label: what training needs (any split: a DexYCB test record is full).
``eval``   what a benchmark's withheld split gives (HO-3D v2 ``evaluation``): ``img.jpg`` and ``meta.json`` only.
           The crop comes from the dataset's given hand box and the object; ``hand_root`` is the given root
           joint, ``hand_box`` the given box, ``object_pose`` / ``object_box`` the given object pose. Nothing that
           needs the hidden hand pose is there: no joints, no MANO parameters, no masks (the hand's would need
           its mesh), no heatmap, no SDF samples (the hand's distance needs the mesh too), no mask IoU.
           Trainers refuse these records; evaluators take them.

Upstream-crop records (``record.crop = "upstream"``, any kind): the test-time input of upstream HOISDF
(``data_crop``), exactly: a 256 px crop cut with PIL's nearest-neighbour warp from the original frame and stored
losslessly as ``img.png``; ``K`` is upstream's crop intrinsics. Their ``meta.json`` also holds the
:data:`CROP_FIELDS` (all of them; other records hold none): the 2D boxes that filter upstream's inference grid
and its object anchor, which evaluation uses in place of its own.

Upstream-region records (``record.upstream_region``, full records of the named splits) keep what upstream's training
warp samples: the original frame's file as the dataset ships it, byte for byte, as ``frame.jpg`` or ``frame.png``
(by its format; never re-encoded), read as upstream reads it (Pillow, flipped for a left hand); readers get under
``img`` the square of that frame at ``region_origin`` (``seg.png`` and ``hm.png`` are at half its side), large enough
for upstream's training jitter, scale and rotation. Stores built before the frame member hold that square itself as
a lossless ``img.png``; both read the same. Their ``meta.json`` also holds the :data:`REGION_FIELDS` (upstream's
frame-level inputs to its training warp).
"""

from __future__ import annotations

import re

import numpy as np

SCHEMA_VERSION = 2  # 2: sample_index, record kinds

IMG = "img.jpg"
IMG_LOSSLESS = "img.png"  # the image member of an upstream-crop record (CROP_FIELDS), in place of IMG
FRAME_JPG, FRAME_PNG = "frame.jpg", "frame.png"  # an upstream-region record's original frame file, in place of IMG
FRAME_MEMBERS = (FRAME_JPG, FRAME_PNG)
IMAGE_STAND_INS = (IMG_LOSSLESS, *FRAME_MEMBERS)  # members that stand in for IMG (one at most, never beside it)
SEG = "seg.png"
HEATMAP = "hm.png"
SDF = "sdf.npy"
META = "meta.json"
MEMBERS = (IMG, SEG, HEATMAP, SDF, META)
WRITE_ORDER = (IMG, IMG_LOSSLESS, FRAME_JPG, FRAME_PNG, SEG, HEATMAP, SDF, META)  # member order inside a shard

# seg.png bit planes
SEG_HAND_VISIBLE, SEG_OBJECT_VISIBLE, SEG_HAND_AMODAL, SEG_OBJECT_AMODAL = 1, 2, 4, 8

# sdf.npy layout
SDF_QUANTUM = 2e-5  # metres per unit: 0.02 mm, so the rounding error is at most 0.01 mm
SDF_LIMIT = 32767 * SDF_QUANTUM  # about 0.655 m; larger magnitudes are clipped
SDF_DTYPE = np.int16
SDF_COLUMNS = ("x", "y", "z", "sdf_hand", "sdf_object", "part")
NO_PART = -1

HEATMAP_SIGMA = 1.25  # pixels at the mask resolution

# meta.json fields: name -> (shape or None for scalars/strings, description)
META_FIELDS = {
    "schema_version": (None, "SCHEMA_VERSION of the writer"),
    "kind": (None, "'full' | 'eval': which members and fields the record has (RECORD_KINDS)"),
    "key": (None, "the record key"),
    "dataset": (None, "'dexycb' | 'ho3d' | 'toy' | 'synthetic'"),
    "split": (None, "source split"),
    "frame_id": (None, "the reader's frame id"),
    "side": (None, "'right' (left hands are mirrored; see 'mirrored')"),
    "mirrored": (None, "true if the frame was a left hand mirrored to a right hand"),
    "tip_convention": (None, "'manopth' | 'ho3d': fingertip vertices of joints_3d"),
    "K": ((3, 3), "intrinsics of img.jpg (crop pixels)"),
    "crop_box": ((4,), "x1, y1, x2, y2 of the crop in the source image, pixels"),
    "hand_root": ((3,), "wrist joint, camera frame, metres: the origin of sdf.npy's xyz"),
    "joints_3d": ((21, 3), "camera frame, metres, DexYCB order"),
    "joints_2d": ((21, 2), "crop pixels"),
    "mano_pose": ((48,), "flat-hand-mean axis-angle, camera frame"),
    "mano_betas": ((10,), "MANO shape"),
    "mano_transl": ((3,), "MANO translation, camera frame, metres"),
    "object_name": (None, "YCB folder name"),
    "object_id": (None, "DexYCB class id 1..21"),
    "object_pose": ((4, 4), "model -> camera"),
    "hand_box": ((4,), "x1, y1, x2, y2 of the projected hand mesh (eval records: the dataset's given hand box), "
                       "crop pixels"),
    "object_box": ((4,), "x1, y1, x2, y2 of the projected object mesh, crop pixels"),
    "sdf_counts": ((3,), "hand, object and uniform sample counts in sdf.npy"),
    "seg_iou": ((2,), "IoU of our visible hand / object masks with the dataset's own segmentation "
                      "(a quality statistic); -1 where the dataset has none"),
    "sample_index": (None, "DexYCB: the sample's index in the dex-ycb-toolkit's enumeration of its split (the id "
                           "of HPE result files and of gSDF's frame lists); -1 for other datasets"),
    "source": (None, "provenance dict from the reader"),
}

# meta.json fields of an upstream-crop record only (all or none): name -> (shape or None, description)
UPSTREAM_CROP = "upstream"
CROP_FIELDS = {
    "crop": (None, "'upstream': img.png, K and the fields below are upstream HOISDF's test-time crop"),
    "grid_hand_box": ((4,), "x1, y1, x2, y2, crop pixels: upstream's box that filters the hand's inference grid "
                            "(2D joints' box x1.1, HO-3D: the given hand box x1.2)"),
    "grid_object_box": ((4,), "x1, y1, x2, y2, crop pixels: upstream's box that filters the object's inference grid "
                              "(projected 21-point box of points.xyz, x1.0)"),
    "object_anchor": ((3,), "camera frame, metres: upstream's object anchor (obj_center_cam: the integer centre of "
                            "grid_object_box back-projected at the hand root's depth; HO-3D: at 0.5244322 m)"),
}

# meta.json fields of a record.upstream_region record only (all or none): its image (the frame.jpg / frame.png file's
# square at region_origin, or an older store's img.png) is a square of the original frame at native resolution
# (upstream HOISDF's training warp samples it), K, joints_2d and boxes in its pixels
UPSTREAM_REGION = "upstream_train"
REGION_FIELDS = {
    "region": (None, "'upstream_train': the image is the square of the original frame (flipped for a left hand) at "
                     "region_origin, black outside the frame, that upstream HOISDF's training augmentation samples"),
    "region_origin": ((2,), "x0, y0 of the image's top-left pixel in the (flipped) frame, pixels"),
    "frame_size": ((2,), "width, height of the original frame, pixels"),
    "frame_K": ((3, 3), "upstream's intrinsics of the (flipped) frame (DexYCB float64, HO-3D float32 values)"),
    "frame_joints_2d": ((21, 2), "upstream's 2D joints in the (flipped) frame, float32 values"),
    "frame_box21_2d": ((21, 2), "the object's 21 box points (points.xyz) projected into the (flipped) frame"),
}

OBJECT_IDS = range(1, 22)  # meta object_id: the DexYCB class ids

# JSON types of the scalar meta fields; shaped fields are numeric arrays
META_TYPES = {"schema_version": int, "kind": str, "key": str, "dataset": str, "split": str, "frame_id": str, "side": str,
              "mirrored": bool, "tip_convention": str, "object_name": str, "object_id": int, "sample_index": int,
              "source": dict}

FULL, EVAL = "full", "eval"
# labels an eval record does not have (they need the hidden hand pose, or the masks and samples made from it)
EVAL_ABSENT = ("joints_3d", "joints_2d", "mano_pose", "mano_betas", "mano_transl", "sdf_counts", "seg_iou")
# kind -> (members, meta fields), in schema order
RECORD_KINDS = {
    FULL: (MEMBERS, tuple(META_FIELDS)),
    EVAL: ((IMG, META), tuple(f for f in META_FIELDS if f not in EVAL_ABSENT)),
}


def kind_of_members(names) -> str | None:
    """The record kind whose members are exactly ``names`` (None if no kind has that set); one of IMAGE_STAND_INS
    (``img.png``: an upstream-crop or upstream-region record; ``frame.jpg`` / ``frame.png``: an upstream-region record)
    stands in for ``img.jpg``, never beside it or another."""
    names = set(names)
    stand_ins = names & set(IMAGE_STAND_INS)
    if stand_ins:
        if IMG in names or len(stand_ins) > 1:
            return None
        names = (names - stand_ins) | {IMG}
    return next((kind for kind, (members, _) in RECORD_KINDS.items() if names == set(members)), None)


def image_member(names) -> str:
    """The image member among a record's member ``names``: the one of IMAGE_STAND_INS there, else ``img.jpg``."""
    return next((name for name in IMAGE_STAND_INS if name in names), IMG)


_KEY_RE = re.compile(r"[A-Za-z0-9_\-]+")  # used with fullmatch: no dots, slashes or trailing newline


def check_key(key) -> None:
    """Raise ValueError unless ``key`` is a record key: a non-empty string of letters, digits, '_' and '-'."""
    if not isinstance(key, str) or not _KEY_RE.fullmatch(key):
        raise ValueError(f"{key!r}: keys may only hold letters, digits, '_' and '-'")


def record_key(dataset: str, split: str, frame_id: str) -> str:
    """``<dataset>-<split>-<frame id>``; raises ValueError if a part would put a dot or slash in it."""
    key = f"{dataset}-{split}-{frame_id}"
    check_key(key)
    return key


def quantize_sdf(xyz: np.ndarray, sdf_hand: np.ndarray, sdf_object: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Float samples -> the stored int16 (N, 6) array. xyz relative to the hand root, metres."""
    cols = np.concatenate([xyz, sdf_hand[:, None], sdf_object[:, None]], axis=1)
    q = np.round(np.clip(cols, -SDF_LIMIT, SDF_LIMIT) / SDF_QUANTUM)
    return np.concatenate([q, part[:, None]], axis=1).astype(SDF_DTYPE)


def dequantize_sdf(stored: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stored (N, 6) int16 -> (xyz (N, 3), sdf_hand (N,), sdf_object (N,)) in metres, float32, and part (N,) int8."""
    if stored.dtype != SDF_DTYPE or stored.ndim != 2 or stored.shape[1] != len(SDF_COLUMNS):
        raise ValueError(f"sdf.npy must be {np.dtype(SDF_DTYPE).name} (N, {len(SDF_COLUMNS)}), got {stored.dtype} {stored.shape}")
    vals = stored[:, :5].astype(np.float32) * np.float32(SDF_QUANTUM)
    return vals[:, :3], vals[:, 3], vals[:, 4], stored[:, 5].astype(np.int8)
