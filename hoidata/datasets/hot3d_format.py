"""HOT3D-Clips' files, field by field: a clip tar's members, its JSON values, the RLE masks.

The layout (docs/datasets.md, "HOT3D-Clips"): ``<split>_<device>/clip-<id>.tar``, one WebDataset sample per frame
keyed ``%06d`` with members ``<key>.image_<stream>.jpg``, ``<key>.cameras.json``, ``<key>.hands.json``,
``<key>.hand_crops.json``, ``<key>.objects.json``, ``<key>.info.json``, and the clip's ``__hand_shapes.json__``.
Every parser here raises a :class:`~hoidata.errors.DataError` naming the member and the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.geometry.crop_camera import crop_intrinsics
from hoidata.geometry.fisheye624 import Fisheye624
from hoidata.geometry.se3 import se3_from_wxyz
from hoidata.reading import list_tar, parse_json, read_span
from hoidata.shapes import ANY, Integer, MapOf, Record, String, check
from hoidata.shapes import numbers as declared_numbers

HAND_SHAPES = "__hand_shapes.json__"
FISHEYE624 = "CameraModelType.FISHEYE624"
FRAME_MEMBERS = ("cameras.json", "hands.json", "hand_crops.json", "objects.json", "info.json")
SIDES = ("left", "right")
RLE_LOOP_RUNS = 20_000  # rle_decode sets up to this many runs one slice each, more through one cumulative sum


CAMERA = Record({"calibration": Record({"projection_model_type": String(), "projection_params": ANY, "label": String(),
                                         "image_width": Integer(1, 1 << 16), "image_height": Integer(1, 1 << 16)}),
                 "T_world_from_camera": ANY})  # one cameras.json entry; the parameters and pose checked below
FRAME_SHAPES = {"hand_crops.json": MapOf(MapOf(ANY))}  # each side: {stream: crop}; other members: an object


@dataclass
class ClipMembers:
    """Where each member of a clip tar lies: ``frames[key][suffix] = (offset, size)`` of its bytes in the file, the
    hand-shape member's, ``duplicates``: member names (after the basename rule) that two members share, with
    both names (reading one is an error naming them), and ``truncated``: a problem that ended the listing early
    (the members before it stand)."""

    path: Path
    frames: dict = field(default_factory=dict)
    hand_shapes: tuple | None = None
    truncated: str = ""
    duplicates: dict = field(default_factory=dict)

    def read(self, where: tuple, member: str | None = None) -> bytes:
        return read_span(self.path, where[0], where[1], member)

    def refuse_duplicate(self, name: str) -> None:
        if name in self.duplicates:
            names = " and ".join(repr(n) for n in self.duplicates[name])
            raise DataError(self.path, name, f"two members of the clip are {name!r} ({names}): which one is the "
                                             "frame's is not known")

    def json(self, key: str, suffix: str):
        """A frame's JSON member, parsed and checked to be an object (``hand_crops.json``: of objects); a
        DataError naming ``<key>.<suffix>`` when absent, duplicated, not JSON or of another shape."""
        name = f"{key}.{suffix}"
        self.refuse_duplicate(name)
        where = self.frames.get(key, {}).get(suffix)
        if where is None:
            raise DataError(self.path, name, "member missing")
        value = parse_json(self.read(where, name), self.path, name)
        return check(value, FRAME_SHAPES.get(suffix, MapOf(ANY)), self.path, name)


def list_members(path: Path) -> ClipMembers:
    """The members of a clip tar with the byte range of each (nothing is read but the headers), by basename (a
    member in a folder counts as the clip's). A tar cut short keeps the members whose bytes are all there
    (``truncated`` says where it ended); an unreadable file raises."""
    path = Path(path)
    listing = list_tar(path, lambda name: Path(name).name, "tar file")
    out = ClipMembers(path, truncated=listing.truncated, duplicates=listing.duplicates)
    for name, member in listing.members.items():
        if name == HAND_SHAPES:
            out.hand_shapes = (member.offset, member.size)
            continue
        key, dot, suffix = name.partition(".")
        if dot:
            out.frames.setdefault(key, {})[suffix] = (member.offset, member.size)
    return out


def read_betas(clip: ClipMembers) -> np.ndarray:
    """The clip's MANO betas (10,) from ``__hand_shapes.json__`` (``mano``; the official reader also requires the
    ``umetrack`` entry, so its absence is an error too)."""
    if clip.hand_shapes is None and clip.truncated:  # HOT3D stores it last: a cut tar loses it first
        raise DataError(clip.path, HAND_SHAPES, f"member lost: {clip.truncated}; without the clip's MANO betas none "
                                                "of its frames is built")
    clip.refuse_duplicate(HAND_SHAPES)
    if clip.hand_shapes is None:
        raise DataError(clip.path, HAND_SHAPES, "member missing: the clip's hand shape (MANO betas) is not there")
    shapes = parse_json(clip.read(clip.hand_shapes, HAND_SHAPES), clip.path, HAND_SHAPES)
    for key in ("mano", "umetrack"):
        if not isinstance(shapes, dict) or key not in shapes:
            raise DataError(clip.path, f"{HAND_SHAPES}: {key}", "missing")
    return numbers(shapes["mano"], 10, clip.path, f"{HAND_SHAPES}: mano")


def numbers(value, size: int, path, name: str) -> np.ndarray:
    """``value`` as ``size`` finite float64 numbers (any nesting), else a DataError naming ``name`` and what is
    wrong (a string or boolean, the count, the NaN)."""
    return declared_numbers(value, path, name, count=size).reshape(-1)


def transform(value, path, name: str) -> np.ndarray:
    """A ``{"quaternion_wxyz": [4], "translation_xyz": [3]}`` value -> (4, 4) (w first)."""
    if not isinstance(value, dict):
        raise DataError(path, name, "expected quaternion_wxyz and translation_xyz")
    q = numbers(value.get("quaternion_wxyz"), 4, path, f"{name}.quaternion_wxyz")
    if not 0.9 < np.linalg.norm(q) < 1.1:
        raise DataError(path, f"{name}.quaternion_wxyz", f"not a unit quaternion (norm {np.linalg.norm(q):.3f})")
    return se3_from_wxyz(q, numbers(value.get("translation_xyz"), 3, path, f"{name}.translation_xyz"))


@dataclass(frozen=True)
class StreamCamera:
    """One stream's camera in one frame: intrinsics, camera -> world, and whether the stream is RGB."""

    camera: Fisheye624
    world_from_camera: np.ndarray
    label: str

    @property
    def is_rgb(self) -> bool:
        return "rgb" in self.label  # as the official reader decides it


def stream_camera(value, path, name: str) -> StreamCamera:
    """One entry of ``cameras.json`` (``name`` = ``<key>.cameras.json: <stream>``)."""
    entry = check(value, CAMERA, path, name)
    calib, pose = entry["calibration"], entry["T_world_from_camera"]
    model, params, label = calib["projection_model_type"], calib["projection_params"], calib["label"]
    width, height = calib["image_width"], calib["image_height"]
    if model != FISHEYE624:
        raise DataError(path, f"{name}.projection_model_type", f"expected {FISHEYE624}, got {model!r}")
    params = declared_numbers(params, path, f"{name}.projection_params", (None,))
    try:
        camera = Fisheye624.from_params(params, width, height)
    except (TypeError, ValueError) as e:
        raise DataError(path, f"{name}.projection_params", str(e)) from None
    return StreamCamera(camera, transform(pose, path, f"{name}.T_world_from_camera"), label)


def crop_camera(value, size: int, path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """One ``hand_crops.json`` entry -> (K (3, 3) of a ``size`` px crop, crop camera -> world (4, 4)).
    ``crop_camera_fov`` is in radians (as the official reader uses it)."""
    if not isinstance(value, dict) or "crop_camera_fov" not in value:
        raise DataError(path, f"{name}.crop_camera_fov", "missing")
    fov = numbers(value["crop_camera_fov"], 1, path, f"{name}.crop_camera_fov")[0]
    if not 0.0 < fov < np.pi:
        raise DataError(path, f"{name}.crop_camera_fov", f"{fov} is not an angle in (0, pi) radians")
    return crop_intrinsics(size, fov), transform(value.get("T_world_from_crop_camera"), path,
                                                 f"{name}.T_world_from_crop_camera")


# ---------------------------------------------------------------- masks

def rle_encode(mask: np.ndarray) -> dict:
    """A binary mask (H, W) -> HOT3D's ``{"height", "width", "rle"}``: runs of ones in row-major order as
    ``[start, length, ...]`` with 1-based starts."""
    flat = np.concatenate([[0], np.asarray(mask, bool).reshape(-1).astype(np.int8), [0]])
    edges = np.flatnonzero(flat[1:] != flat[:-1])  # 0-based index of each run's first pixel, then one past its end
    starts, ends = edges[::2], edges[1::2]
    runs = np.stack([starts + 1, ends - starts], axis=1).reshape(-1)
    return {"height": int(mask.shape[0]), "width": int(mask.shape[1]), "rle": [int(v) for v in runs]}


def rle_decode(value, path=None, name: str = "mask") -> np.ndarray:
    """HOT3D's RLE mask -> bool (H, W). Starts are 1-based: ``[1, 2]`` covers the first two pixels. Runs that
    leave the image, an odd count or a start below 1 are a DataError naming ``name``."""
    try:
        h, w = int(value["height"]), int(value["width"])
        runs = np.asarray(value["rle"], np.int64).reshape(-1)
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(path, name, f"expected height, width and rle ({e})") from None
    if runs.size % 2:
        raise DataError(path, f"{name}.rle", f"odd number of values ({runs.size}): expected start, length pairs")
    starts, lengths = runs[::2] - 1, runs[1::2]
    if runs.size and (starts.min() < 0 or lengths.min() < 0 or (starts + lengths).max() > h * w):
        raise DataError(path, f"{name}.rle", f"runs outside the {w}x{h} mask (starts are 1-based)")
    if starts.size <= RLE_LOOP_RUNS:  # a slice per run: no pass over the whole image
        flat = np.zeros(h * w, bool)
        for start, length in zip(starts.tolist(), lengths.tolist()):
            flat[start:start + length] = True
        return flat.reshape(h, w)
    flat = np.zeros(h * w + 1, np.int32)
    np.add.at(flat, starts, 1)
    np.add.at(flat, starts + lengths, -1)
    return (np.cumsum(flat[:-1]) > 0).reshape(h, w)
