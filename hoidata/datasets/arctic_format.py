"""ARCTIC's files and the rules its processing applies to them (docs/datasets.md, "ARCTIC"): the raw sequences,
``meta/misc.json``, the protocol splits, the egocentric lens, the crop boxes and the validity flags.

Each function reproduces what ARCTIC's own code does with the same files, in float64: points in a view are
world -> camera with the subject's 8 allocentric matrices or the sequence's per-frame egocentric one; the
egocentric lens is OpenCV's rational model (k1 k2 p1 p2 k3 k4 k5 k6) applied to the normalised coordinates;
a view's crop box and a hand's / the object's validity follow ARCTIC's processing step. Views are numbered as
ARCTIC numbers them: 0 the egocentric camera, 1..8 the allocentric ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.reading import read_json
from hoidata.safe_pickle import load_npy
from hoidata.shapes import numbers

MIN_FRAMES = 51  # ARCTIC's loader asserts more than 50 frames per hand
EGO_BOX = (1.0, 1.0, 2800.0, 2000.0)  # ARCTIC's egocentric validity box (xmin, ymin, xmax, ymax), pixels
EGO_CROP = (1400.0, 1000.0, 14.0)  # the egocentric crop (cx, cy, scale): the whole 2800 x 2000 image
OBJECT_MARGIN = 0.6  # the allocentric crop adds this fraction of the object's 2D extent
MIN_SCALE = 3.0  # allocentric crops are at least 3 x 200 = 600 pixels wide
IMAGE_MARGIN = 10  # ARCTIC's splits leave out the first and last 10 image indices of a sequence
HAND_KEYS = {"rot": (3,), "pose": (45,), "trans": (3,), "fitting_err": ()}


@dataclass
class ArcticSequence:
    """One raw sequence, world frame, metres: per hand ``mano[side]`` with ``rot`` (F, 3), ``pose`` (F, 45,
    ``flat_hand_mean=False``), ``trans`` (F, 3), ``shape`` (10,), ``fitting_err`` (F,); the object's ``radian``
    (F,), ``rotvec`` (F, 3), ``transl`` (F, 3) (the file's millimetres / 1000); ``world2ego`` (F, 4, 4),
    ``ego_k`` (3, 3), ``dist8`` (8,)."""

    subject: str
    name: str
    object_name: str
    mano: dict
    radian: np.ndarray
    rotvec: np.ndarray
    transl: np.ndarray
    world2ego: np.ndarray
    ego_k: np.ndarray
    dist8: np.ndarray

    @property
    def frames(self) -> int:
        return len(self.radian)


def _load(path: Path, want_dict: bool):
    if not path.is_file():
        raise DataError(path, None, "missing (ARCTIC's loader opens it)")
    value = load_npy(path)  # a dict's pickle through the allow-list: np.load(allow_pickle=True) would run its code
    if want_dict:
        value = value.item() if isinstance(value, np.ndarray) and value.dtype.hasobject and value.shape == () else None
        if not isinstance(value, dict):
            raise DataError(path, None, "must hold a dict")
    elif value.dtype.hasobject:
        raise DataError(path, None, "must hold an array of numbers, not pickled objects")
    return value


def _array(value, path: Path, key: str, shape: tuple | None) -> np.ndarray:
    if value is None:
        raise DataError(path, key, "missing")
    return numbers(value, path, key, shape)  # numbers (never strings or booleans) of the shape, finite


def read_sequence(root: str | Path, subject: str, name: str) -> ArcticSequence:
    """``raw_seqs/<subject>/<name>.*.npy`` read and checked as ARCTIC's loader reads them."""
    folder = Path(root) / "raw_seqs" / subject
    path = folder / f"{name}.mano.npy"
    data = _load(path, True)
    frames = None
    mano = {}
    for side in ("right", "left"):
        entry = data.get(side)
        if not isinstance(entry, dict):
            raise DataError(path, side, "missing or not a dict")
        n = len(np.atleast_1d(entry.get("fitting_err", [])))
        if n < MIN_FRAMES:
            raise DataError(path, f"{side}.fitting_err", f"{n} frames: ARCTIC's loader needs more than 50")
        frames = n if frames is None else frames
        if n != frames:
            raise DataError(path, f"{side}.fitting_err", f"{n} frames, the right hand has {frames}")
        hand = {k: _array(entry.get(k), path, f"{side}.{k}", (frames, *s)) for k, s in HAND_KEYS.items()}
        shape = _array(entry.get("shape"), path, f"{side}.shape", None)
        hand["shape"] = _array(shape[0] if shape.ndim == 2 else shape, path, f"{side}.shape", (10,))
        mano[side] = hand
    obj_path = folder / f"{name}.object.npy"
    obj = _array(_load(obj_path, False), obj_path, "object params", (frames, 7))
    ego_path = folder / f"{name}.egocam.dist.npy"
    ego = _load(ego_path, True)
    rot = _array(ego.get("R_k_cam_np"), ego_path, "R_k_cam_np", (frames, 3, 3))
    trans = _array(ego.get("T_k_cam_np"), ego_path, "T_k_cam_np", (frames, 3, 1))
    world2ego = np.tile(np.eye(4), (frames, 1, 1))
    world2ego[:, :3, :3], world2ego[:, :3, 3] = rot, trans[..., 0]
    if not (folder / f"{name}.smplx.npy").is_file():
        raise DataError(folder / f"{name}.smplx.npy", None, "missing (ARCTIC's loader opens it; the body is not used)")
    return ArcticSequence(subject, name, name.split("_")[0], mano, obj[:, 0], obj[:, 1:4], obj[:, 4:] / 1000.0,
                          world2ego, _array(ego.get("intrinsics"), ego_path, "intrinsics", (3, 3)),
                          _array(ego.get("dist8"), ego_path, "dist8", (8,)))


def read_misc(root: str | Path) -> dict:
    """``meta/misc.json`` per subject: ``world2cam`` (8, 4, 4), ``intris_mat`` (8, 3, 3), ``image_size`` (9, 2)
    width and height of views 0..8, ``ioi_offset`` (image index of annotation frame 0), ``gender``."""
    path = Path(root) / "meta" / "misc.json"
    table = read_json(path, "ARCTIC meta/misc.json")
    out = {}
    for subject, entry in (table.items() if isinstance(table, dict) else ()):
        if not isinstance(entry, dict):
            raise DataError(path, subject, "must be an object")
        offset = entry.get("ioi_offset")
        if isinstance(offset, bool) or not isinstance(offset, int):
            raise DataError(path, f"{subject}.ioi_offset", "missing or not an integer")
        out[subject] = {"world2cam": _array(entry.get("world2cam"), path, f"{subject}.world2cam", (8, 4, 4)),
                        "intris_mat": _array(entry.get("intris_mat"), path, f"{subject}.intris_mat", (8, 3, 3)),
                        "image_size": _array(entry.get("image_size"), path, f"{subject}.image_size", (9, 2)),
                        "ioi_offset": offset, "gender": entry.get("gender")}
    if not out:
        raise DataError(path, None, "no subjects")
    return out


def read_protocol(root: str | Path, setup: str) -> dict[str, list[str]]:
    """``splits_json/protocol_<setup>.json``: ``sXX/<sequence>`` names per split; train is every listed
    sequence outside val and test, as ARCTIC takes it."""
    path = Path(root) / "splits_json" / f"protocol_{setup}.json"
    table = read_json(path, "ARCTIC protocol file")
    lists = {}
    for split in ("train", "val", "test"):
        names = table.get(split) if isinstance(table, dict) else None
        if not isinstance(names, list) or not all(isinstance(n, str) and n.count("/") == 1 for n in names):
            raise DataError(path, split, "must be a list of 'sXX/<sequence>' names")
        lists[split] = names
    held = set(lists["val"]) | set(lists["test"])
    if len(held) != len(lists["val"]) + len(lists["test"]):
        raise DataError(path, "val", "a sequence is in both val and test, or twice")
    return {"train": [n for n in lists["train"] + lists["val"] + lists["test"] if n not in held],
            "val": lists["val"], "test": lists["test"]}


def protocol_views(setup: str) -> tuple[int, ...]:
    """The views a protocol evaluates: p1 the eight allocentric ones, p2 the egocentric one."""
    return {"p1": (1, 2, 3, 4, 5, 6, 7, 8), "p2": (0,)}[setup]


def image_indices(frames: int) -> range:
    """Image numbers of a sequence's split entries (ARCTIC's splits: 10 .. frames - 11); annotation frame =
    image number - the subject's ``ioi_offset``."""
    return range(IMAGE_MARGIN, frames - IMAGE_MARGIN)


def transform(world2cam: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 4, 4) world -> camera applied to (..., P, 3) points."""
    return points @ np.swapaxes(world2cam[..., :3, :3], -1, -2) + world2cam[..., None, :3, 3]


def distort(points_cam: np.ndarray, dist8: np.ndarray) -> np.ndarray:
    """Camera points moved so that a pinhole projection lands where the rational lens puts them: OpenCV's model
    on (x/z, y/z), the result scaled back by z (ARCTIC's egocentric "distorted" view)."""
    d = np.asarray(dist8, np.float64)
    z = points_cam[..., 2]
    x, y = points_cam[..., 0] / z, points_cam[..., 1] / z
    r2 = x * x + y * y
    radial = (1 + d[0] * r2 + d[1] * r2**2 + d[4] * r2**3) / (1 + d[5] * r2 + d[6] * r2**2 + d[7] * r2**3)
    xd = x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x)
    yd = y * radial + 2 * d[3] * x * y + d[2] * (r2 + 2 * y * y)
    return np.stack([xd * z, yd * z, z], -1)


def project(K: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Pinhole pixels (..., P, 2) of camera points (..., P, 3) through (..., 3, 3) intrinsics."""
    uvw = points_cam @ np.swapaxes(K, -1, -2)
    return uvw[..., :2] / uvw[..., 2:3]


def crop_boxes(object_2d: np.ndarray) -> np.ndarray:
    """ARCTIC's crop (cx, cy, scale) per frame and view (F, 9, 3) from the object's vertices in each view
    (F, 9, V, 2; view 0 undistorted): the square box around them, 1.1 x, plus 0.6 x their extent, / 200; at
    least :data:`MIN_SCALE`; view 0 the whole egocentric image."""
    lo, hi = object_2d.min(axis=2), object_2d.max(axis=2)
    w, h = hi[..., 0] - lo[..., 0], hi[..., 1] - lo[..., 1]
    side = np.where(w / h > 1, w, h) * 1.1
    scale = (side + np.maximum(w, h) * OBJECT_MARGIN) / 200.0
    out = np.stack([lo[..., 0] + w / 2, lo[..., 1] + h / 2, np.maximum(scale, MIN_SCALE)], -1)
    out[:, 0] = EGO_CROP
    return out


def validity(crops: np.ndarray, right_2d: np.ndarray, left_2d: np.ndarray, object_center_2d: np.ndarray,
             image_size: np.ndarray) -> dict[str, np.ndarray]:
    """ARCTIC's flags per frame and view (F, 9), 0/1: ``is_valid`` the mean of the object's projected vertices inside
    the view's box; a hand valid where its wrist and at least 3 of its 21 joints are inside. Boxes: view 0
    :data:`EGO_BOX`, views 1..8 the crop clamped to [1, width] x [1, height]. The 2D points of view 0 are
    the *distorted* egocentric projections (F, 9, J, 2; the object's centre (F, 9, 2))."""
    half = crops[:, 1:, 2] * 200.0 / 2
    size = np.asarray(image_size, np.float64)[1:]
    boxes = np.stack([np.maximum(crops[:, 1:, 0] - half, 1), np.maximum(crops[:, 1:, 1] - half, 1),
                      np.minimum(crops[:, 1:, 0] + half, size[:, 0]),
                      np.minimum(crops[:, 1:, 1] + half, size[:, 1])], -1)
    boxes = np.concatenate([np.broadcast_to(np.array(EGO_BOX), (len(crops), 1, 4)), boxes], 1)

    def inside(points):
        b = boxes[:, :, None, :]
        return ((b[..., 0] <= points[..., 0]) & (points[..., 0] <= b[..., 2]) &
                (b[..., 1] <= points[..., 1]) & (points[..., 1] <= b[..., 3]))

    out = {"is_valid": inside(object_center_2d[:, :, None, :])[..., 0].astype(np.int64)}
    for side, joints in (("right", right_2d), ("left", left_2d)):
        hit = inside(joints)
        out[f"{side}_valid"] = (hit[..., 0] & (hit.sum(-1) >= 3)).astype(np.int64)
    return out
