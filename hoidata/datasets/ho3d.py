"""HO-3D v2 (and v3) reader: list files, latin1 meta pickles, OpenGL -> OpenCV on reading.

Layout (``reference/datasets.md`` section 2): ``ROOT/{train,evaluation}/<SEQ>/{rgb,depth,meta,seg}/<id>``
with the frame lists ``ROOT/train.txt`` and ``ROOT/evaluation.txt`` (lines ``<SEQ>/<id>``).

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

from hoidata.datasets.frame import Frame, Skip, project
from hoidata.errors import DataError, decoding
from hoidata.hand.model import MANO_TO_DEXYCB
from hoidata.hand.pose import change_frame
from hoidata.objects import class_id
from hoidata.safe_pickle import load_pickle

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])
IMAGE_SIZE = (640, 480)
SPLITS = {"train": "train", "evaluation": "evaluation"}
TRAIN_KEYS = ("handPose", "handTrans", "handBeta", "handJoints3D", "objRot", "objTrans", "objName", "camMat")
EVAL_KEYS = ("handJoints3D", "handBoundingBox", "objRot", "objTrans", "objName", "camMat")


def read_list(root: Path, split: str) -> list[str]:
    """``<SEQ>/<id>`` entries of ``train.txt`` or ``evaluation.txt``."""
    if split not in SPLITS:
        raise ValueError(f"unknown HO-3D split {split!r}; expected one of {sorted(SPLITS)}")
    path = root / f"{split}.txt"
    if not path.is_file():
        raise DataError(path, None, "HO-3D frame list not found")
    with decoding(path, "frame list"):  # bytes that are not text
        entries = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
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
        on_error: 'raise' stops at the first malformed file; 'skip' records it in ``skipped``.
    """

    root: Path
    mano_dir: Path
    split: str = "train"
    on_error: str = "raise"
    skipped: list[Skip] = field(default_factory=list)

    def __post_init__(self):
        self.root, self.mano_dir = Path(self.root), Path(self.mano_dir)
        self.entries = read_list(self.root, self.split)
        self._mano = None

    def __len__(self) -> int:
        return len(self.entries)

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
        rgb = self.root / self.split / seq / "rgb"
        png = rgb / f"{fid}.png"  # v2 is png, v3 jpg
        return png if png.exists() or not (rgb / f"{fid}.jpg").exists() else rgb / f"{fid}.jpg"

    def _frame(self, seq: str, fid: str, frame_id: str, meta: dict, path: Path) -> Frame:
        K = _vector(meta, "camMat", 9, path).reshape(3, 3)
        name = str(meta["objName"])
        seg = self.root / self.split / seq / "seg" / f"{fid}.jpg"
        common = dict(dataset="ho3d", split=self.split, frame_id=frame_id, image_path=self._image_path(seq, fid),
                      image_size=IMAGE_SIZE, K=K, side="right", object_name=name, object_id=class_id(name),
                      object_pose=_object_pose(meta, path), tip_convention="ho3d",
                      segmentation_path=seg if seg.exists() else None,
                      source={"meta": str(path), "sequence": seq, "id": fid})
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
