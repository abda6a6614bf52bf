"""Grasp sources for render-synthetic: hand pose and shape relative to an object, from a store or a dataset.

A grasp is expressed in the object's model frame (the hand's MANO pose, betas and translation such
that the MANO output lies in object coordinates), so that any new view of it is a rigid transform.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.hand.pose import change_frame


@dataclass(frozen=True)
class GraspSource:
    key: str  # where it came from (record key or frame id)
    object_name: str
    object_id: int
    pose: np.ndarray  # (48,) flat-hand-mean axis-angle, object frame
    betas: np.ndarray  # (10,)
    transl: np.ndarray  # (3,) metres, object frame


def to_object_frame(pose, betas, transl, object_pose: np.ndarray, rest_wrist: np.ndarray):
    """A camera-frame MANO pose -> the same hand in the object's model frame."""
    rot, trans = object_pose[:3, :3], object_pose[:3, 3]
    return change_frame(pose, transl, rest_wrist, rot.T, -rot.T @ trans)


def grasps_from_store(store_dir: Path, mano) -> list[GraspSource]:
    """Grasps of every record of a store (mirrored records are left out: their object is mirrored too)."""
    import torch

    from hoidata.store import read_index

    index = read_index(store_dir)
    lab = index.labels
    keep = [i for i in range(len(index.keys)) if not bool(lab["mirrored"][i]) and lab["kind"][i] == "full"]
    betas = torch.as_tensor(np.asarray(lab["mano_betas"], np.float64)[keep])
    wrists = mano.rest_joints(betas)[:, 0].double().numpy() if keep else np.zeros((0, 3))
    out = []
    for row, wrist in zip(keep, wrists):
        pose, transl = to_object_frame(lab["mano_pose"][row], lab["mano_betas"][row], lab["mano_transl"][row],
                                       np.asarray(lab["object_pose"][row], np.float64), wrist)
        out.append(GraspSource(index.keys[row], str(lab["object_name"][row]), int(lab["object_id"][row]), pose,
                               np.asarray(lab["mano_betas"][row], np.float64), transl))
    return out


def grasps_from_frames(frames, mano) -> list[GraspSource]:
    """Grasps of dataset frames (readers' Frame records with a hand pose; left hands are skipped)."""

    out = []
    for f in frames:
        if not f.has_hand_pose or f.side != "right":
            continue
        wrist = mano.rest_wrist(f.mano_betas)
        pose, transl = to_object_frame(f.mano_pose, f.mano_betas, f.mano_transl, f.object_pose, wrist)
        out.append(GraspSource(f"{f.dataset}-{f.split}-{f.frame_id}", f.object_name, int(f.object_id), pose,
                               np.asarray(f.mano_betas, np.float64), transl))
    return out


def load_grasps(source: Path, mano, mano_dir: Path | None = None, models_dir: Path | None = None) -> list[GraspSource]:
    """Grasps from a store folder (``index.zarr``), an HO-3D folder (``train.txt``) or a DexYCB folder.

    Args:
        source: the folder; mano: the right MANO layer (the grasps' rest wrist).
        mano_dir: the MANO folder a dataset reader uses (default ``source/mano``); models_dir: the YCB models the
            DexYCB proximity filter reads (default ``source/models``). Give render-synthetic's ``--mano`` and
            ``--models``, so the grasps are selected with the files that render them.
    """
    from dataclasses import replace

    from hoidata.datasets.dexycb import SETTINGS
    from hoidata.datasets.open import open_reader

    source = Path(source)
    mano_dir = source / "mano" if mano_dir is None else Path(mano_dir)
    if (source / "index.zarr").exists():
        grasps = grasps_from_store(source, mano)
    elif (source / "train.txt").is_file() or (source / "calibration").is_dir():
        dataset = "ho3d" if (source / "train.txt").is_file() else "dexycb"
        setting = replace(SETTINGS["dexycb"], complete_subjects=False)  # any grasps will do, splits do not matter
        reader = open_reader(dataset, source, mano_dir, "train", models_dir=models_dir, dexycb=setting)
        grasps = grasps_from_frames(reader.frames(), mano)
    else:
        raise DataError(source, None, "not a store (index.zarr), an HO-3D folder (train.txt) or a DexYCB folder "
                                      "(calibration/)")
    if not grasps:
        raise DataError(source, None, "no right-hand grasps with a MANO pose found")
    return grasps
