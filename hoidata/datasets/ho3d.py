"""HO-3D v2 and v3 reader: list files, latin1 meta pickles, OpenGL -> OpenCV on reading.

Layout (docs/conventions.md, "The datasets on disk", HO-3D): ``ROOT/{train,evaluation}/<SEQ>/{rgb,depth,meta,seg}/<id>``
with the frame lists ``ROOT/train.txt`` and ``ROOT/evaluation.txt`` (lines ``<SEQ>/<id>``).

v3 (checked against shreyashampali/ho3d at 2fd6ee1: README "Update - Juy 1st, 2021", ``utils/vis_utils.py``
``read_RGB_img`` / ``db_size``, ``vis_pcl_all_cameras.py``, ``compare_manual_anno.py``, and the v3 dataset
README.txt) keeps v2's folders, list files, meta keys and OpenGL frame; what differs on disk:
- ``rgb/<id>.jpg`` (JPEG) instead of ``rgb/<id>.png``; depth stays PNG (vis_pcl_all_cameras swaps 'rgb'->'depth'
  and 'jpg'->'png' to find it);
- the lists are v3's own: 78,297 training and 20,137 evaluation frames (``db_size``), v2 66,034 / 11,524, so the
  challenge order is v3's ``evaluation.txt`` and its server (CodaLab 4393) wants 20,137 samples;
- extra folders this reader does not need: ``calibration/<SEQ>/calibration/`` (cam_orders.txt,
  trans_<i>.txt, cam_<i>_intrinsics.txt, cam_0_depth_scale.txt) of the multi-camera sequences, and
  ``manual_annotations/`` (fingertips of 53 frames).
``version`` picks the image format and is checked against the first listed frame: a v2 folder read as v3 (or the
reverse) is an error naming the image, since its list order would be the other challenge's.

HO-3D stores everything in the OpenGL camera frame (y up, the scene at negative z). Reading converts
with C = diag(1, -1, -1): points p' = C p, object rotation R' = C R and translation t' = C t, the MANO
global rotation R_g' = C R_g, and the MANO translation recomputed because the rotation pivots about
the rest wrist (:func:`hoidata.hand.pose.change_frame`). Its joints use HO-3D's order (MANO + tips)
and fingertip vertices; they are reordered to DexYCB order and marked ``tip_convention='ho3d'``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from hoidata.datasets.frame import Frame, Skip
from hoidata.errors import DataError
from hoidata.geometry.crop import project
from hoidata.hand.model import MANO_TO_DEXYCB
from hoidata.hand.pose import change_frame
from hoidata.objects import class_id
from hoidata.reading import read_lines
from hoidata.safe_pickle import load_pickle

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])
IMAGE_SIZE = (640, 480)
SPLITS = {"train": "train", "evaluation": "evaluation"}
VERSIONS = {"v2": ".png", "v3": ".jpg"}  # RGB format of each release (read_RGB_img tries .png, then .jpg)
LIST_SIZES = {"v2": {"train": 66034, "evaluation": 11524}, "v3": {"train": 78297, "evaluation": 20137}}  # db_size
TRAIN_KEYS = ("handPose", "handTrans", "handBeta", "handJoints3D", "objRot", "objTrans", "objName", "camMat")
EVAL_KEYS = ("handJoints3D", "handBoundingBox", "objRot", "objTrans", "objName", "camMat")


def read_list(root: Path, split: str) -> list[str]:
    """``<SEQ>/<id>`` entries of ``train.txt`` or ``evaluation.txt``."""
    if split not in SPLITS:
        raise ValueError(f"unknown HO-3D split {split!r}; expected one of {sorted(SPLITS)}")
    path = root / f"{split}.txt"
    entries = read_lines(path, "HO-3D frame list")
    for n, entry in enumerate(entries, 1):
        if entry.count("/") != 1:
            raise DataError(path, f"line {n}", f"expected '<SEQ>/<id>', got {entry!r}")
    return entries


def read_meta(path: Path, split: str) -> dict:
    """A ``meta/<id>.pkl`` with the keys of its split checked; values of failed annotations may be None."""
    meta = load_pickle(path)
    if not isinstance(meta, dict):
        raise DataError(path, None, f"expected a dict, got {type(meta).__name__}")
    for key in TRAIN_KEYS if split == "train" else EVAL_KEYS:
        if key not in meta:
            raise DataError(path, key, "missing key")
    return meta


def _vector(meta: dict, key: str, size: int, path: Path) -> np.ndarray:
    try:
        value = np.asarray(meta[key], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise DataError(path, key, f"expected {size} numbers: {e}") from e
    if value.size != size:
        raise DataError(path, key, f"expected {size} values, got {value.size}")
    return value


def _object_pose(meta: dict, path: Path) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = OPENGL_TO_OPENCV @ Rotation.from_rotvec(_vector(meta, "objRot", 3, path)).as_matrix()
    pose[:3, 3] = OPENGL_TO_OPENCV @ _vector(meta, "objTrans", 3, path)
    return pose


@dataclass
class HO3DReader:
    """Frames of HO-3D's ``train`` or ``evaluation`` split. Iterate with :meth:`frames`.

    Args:
        root: the HO-3D folder (``train/``, ``evaluation/``, ``train.txt``, ``evaluation.txt``).
        mano_dir: MANO folder; the right model's rest wrist is needed for the frame change.
        split: 'train' | 'evaluation'.
        version: 'v2' (PNG frames) | 'v3' (JPEG frames); see the module docstring.
        on_error: 'raise' stops at the first malformed file; 'skip' records it in ``skipped``.
    """

    root: Path
    mano_dir: Path
    split: str = "train"
    on_error: str = "raise"
    skipped: list[Skip] = field(default_factory=list)
    version: str = "v2"

    def __post_init__(self):
        self.root, self.mano_dir = Path(self.root), Path(self.mano_dir)
        if self.version not in VERSIONS:
            raise ValueError(f"unknown HO-3D version {self.version!r}; expected one of {sorted(VERSIONS)}")
        self.entries = read_list(self.root, self.split)
        self._mano = None
        if self.entries:
            self._check_version(*self.entries[0].split("/"))

    def _check_version(self, seq: str, fid: str) -> None:
        """DataError when the first listed frame's image exists only in the other release's format."""
        rgb = self.root / self.split / seq / "rgb"
        own = rgb / f"{fid}{VERSIONS[self.version]}"
        other = [v for v, ext in VERSIONS.items() if v != self.version and (rgb / f"{fid}{ext}").exists()]
        if not own.exists() and other:
            raise DataError(own, None, f"not found, but {fid}{VERSIONS[other[0]]} is: this folder looks like HO-3D "
                            f"{other[0]}, read as {self.version} (set dataset.version = \"{other[0]}\", e.g. "
                            f"--dataset {'ho3d_v3' if other[0] == 'v3' else 'ho3d'})")

    def __len__(self) -> int:
        return len(self.entries)

    def published_ids(self, frames) -> list[int]:
        """Each of ``frames``' (this reader's) line in ``<split>.txt``: HO-3D's id of a frame (annotation files)."""
        line = {entry: n for n, entry in enumerate(self.entries)}
        return [line[f"{f.source['sequence']}/{f.source['id']}"] for f in frames]

    def frames(self) -> Iterator[Frame]:
        for entry in self.entries:
            seq, fid = entry.split("/")
            frame_id = f"{seq}_{fid}"
            meta_path = self.root / self.split / seq / "meta" / f"{fid}.pkl"
            try:
                meta = read_meta(meta_path, self.split)
                missing = [k for k in (TRAIN_KEYS if self.split == "train" else EVAL_KEYS) if meta[k] is None]
                if missing:
                    self.skipped.append(Skip(frame_id, f"annotation failed ({', '.join(missing)} is None)", str(meta_path)))
                    continue
                yield self._frame(seq, fid, frame_id, meta, meta_path)
            except DataError as e:
                if self.on_error == "raise":
                    raise
                self.skipped.append(Skip(frame_id, str(e), str(meta_path)))

    def _image_path(self, seq: str, fid: str) -> Path:
        return self.root / self.split / seq / "rgb" / f"{fid}{VERSIONS[self.version]}"

    def _frame(self, seq: str, fid: str, frame_id: str, meta: dict, path: Path) -> Frame:
        K = _vector(meta, "camMat", 9, path).reshape(3, 3)
        name = str(meta["objName"])
        seg = self.root / self.split / seq / "seg" / f"{fid}.jpg"
        common = dict(dataset="ho3d", split=self.split, frame_id=frame_id, image_path=self._image_path(seq, fid),
                      image_size=IMAGE_SIZE, K=K, side="right", object_name=name, object_id=class_id(name),
                      object_pose=_object_pose(meta, path), tip_convention="ho3d",
                      segmentation_path=seg if seg.exists() else None,
                      source={"meta": str(path), "sequence": seq, "id": fid, "version": self.version})
        if self.split == "evaluation":
            root = OPENGL_TO_OPENCV @ _vector(meta, "handJoints3D", 3, path)
            return Frame(root_3d=root, hand_box=_vector(meta, "handBoundingBox", 4, path), **common)
        joints_gl = _vector(meta, "handJoints3D", 63, path).reshape(21, 3)
        joints = (joints_gl @ OPENGL_TO_OPENCV.T)[MANO_TO_DEXYCB]
        betas = _vector(meta, "handBeta", 10, path)
        pose, transl = change_frame(_vector(meta, "handPose", 48, path), _vector(meta, "handTrans", 3, path),
                                    self._rest_wrist(betas), OPENGL_TO_OPENCV, np.zeros(3))
        return Frame(root_3d=joints[0], mano_pose=pose, mano_betas=betas, mano_transl=transl, joints_3d=joints,
                     joints_2d=project(joints, K), **common)

    def _rest_wrist(self, betas: np.ndarray) -> np.ndarray:
        import torch

        from hoidata.hand import load_mano

        if self._mano is None:
            self._mano = load_mano(self.mano_dir, side="right", tips="ho3d", dtype=torch.float64)
        return self._mano.rest_wrist(betas)
