"""The frame rules of the field's DexYCB selections, each as the public code that defines it applies it.

A :class:`~hoidata.datasets.dexycb.DexYCBSetting` combines them (``pipelines/*.toml`` name the combinations):

- the hand box rule of HandOccNet / HFL-Net / HOISDF (``common/utils/preprocessing.py`` ``get_bbox`` with
  expansion 1.5, then ``process_bbox``): :func:`hand_box_ok`;
- hand-object proximity, either to the MANO vertices (gSDF ``preprocess/cocoify_dexycb.py``: a cKDTree on
  the 778 hand vertices queried with every posed object vertex, kept if the minimum is <= 5 mm) or to the 21
  labelled joints (ArtiBoost ``anakin/datasets/dexycb.py``: ``cdist(obj_verts, joints_3d).min() * 1000 >
  50`` drops the frame): :func:`selection_reasons`;
- the object's motion since the camera's first frame (UniHOPE ``data_creation/prepare_grasp_dexycb.py``:
  grasping if the relative rotation exceeds 5 degrees or the translation 0.05 m): :func:`object_motion`.

And, for the presets' stated sizes, :func:`count_warnings`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from hoidata.datasets.dexycb_layout import IMAGE_SIZE, label_path, read_labels

PROXIMITY_TARGETS = ("hand_vertices", "hand_joints")


def hand_box_ok(joints_2d: np.ndarray, size=IMAGE_SIZE, expansion: float = 1.5) -> bool:
    """Whether HandOccNet's ``process_bbox`` accepts the ``get_bbox`` box of 2D joints (N, 2) pixels.

    ``get_bbox`` scales the joints' min/max box about its centre (float32, as the loaders read the joints);
    ``process_bbox`` clips the top-left corner to the image and returns None unless ``w * h > 0`` and the
    clipped corner lies inside the image (``x1 <= W - 1``, ``y1 <= H - 1``). So a box wholly left of or above
    the image passes (its corner clips to 0) while one past the right or bottom edge does not.
    """
    uv = np.asarray(joints_2d, dtype=np.float32)
    lo, hi = uv.min(0), uv.max(0)
    centre, extent = (lo + hi) / np.float32(2.0), (hi - lo) * np.float32(expansion)
    x, y = centre - np.float32(0.5) * extent
    w, h = extent
    return bool(w * h > 0 and max(0.0, float(x)) <= size[0] - 1 and max(0.0, float(y)) <= size[1] - 1)


def object_motion(pose: np.ndarray, first: np.ndarray) -> tuple[float, float]:
    """(degrees, metres) between an object pose and its pose in the camera's first frame, both (3, 4) [R | t].

    UniHOPE composes ``inverse(pose) @ first``: the angle of ``R^T R0`` and the length of ``R^T (t0 - t)``,
    which is ``|t0 - t|`` (camera frame, the model origin's displacement).
    """
    R, t, R0, t0 = pose[:3, :3], pose[:3, 3], first[:3, :3], first[:3, 3]
    cos = np.clip(0.5 * (np.trace(R.T @ R0) - 1.0), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(R.T @ (t0 - t)))


def selection_reasons(reader, mano, full: np.ndarray, transl: np.ndarray, kept: list, ctx: dict) -> list[str | None]:
    """Why each kept frame of one camera leaves the setting (None: it stays), by proximity and motion.

    Args:
        reader: the DexYCBReader (its setting, split, object vertices, root).
        mano: the side's MANO layer; full (K, 48) flat-hand-mean poses and transl (K, 3) of the K frames.
        kept: [(frame number, frame id, labels)] of the camera; ctx: the camera context of dexycb_frames.
    """
    setting, reasons = reader.setting, [None] * len(kept)
    if reader.frame_ids is not None:  # a frame list names its frames: no rule applies
        return reasons
    if setting.proximity_mm is not None and reader.split in setting.proximity_splits:
        if setting.proximity_to not in PROXIMITY_TARGETS:
            raise ValueError(f"proximity_to must be one of {PROXIMITY_TARGETS}, got {setting.proximity_to!r}")
        distances = _hand_object_distances(reader, mano, full, transl, kept, ctx, setting.proximity_to)
        target = setting.proximity_to.replace("_", " ")
        for k, d in enumerate(distances):
            if d * 1000.0 > setting.proximity_mm:
                reasons[k] = f"hand-object distance {d * 1000:.1f} mm > {setting.proximity_mm} mm (to the {target})"
    if setting.motion_deg is not None or setting.motion_m is not None:
        path = label_path(ctx["seq_dir"], ctx["serial"], 0)
        first = read_labels(path, int(ctx["num_objects"]), keys=("pose_y",))["pose_y"][ctx["grasp"]].astype(np.float64)
        for k, (_, _, lab) in enumerate(kept):
            deg, metres = object_motion(lab["pose_y"][ctx["grasp"]].astype(np.float64), first)
            moved = (setting.motion_deg is not None and deg > setting.motion_deg) or \
                    (setting.motion_m is not None and metres > setting.motion_m)
            if not moved and reasons[k] is None:
                reasons[k] = (f"object not moved since frame 0 ({deg:.1f} deg, {metres * 1000:.1f} mm; "
                              f"the setting asks > {setting.motion_deg} deg or > {setting.motion_m} m)")
    return reasons


def _hand_object_distances(reader, mano, full, transl, kept, ctx, target: str) -> np.ndarray:
    """Min distance (m) per frame from the grasped object's posed model vertices to the hand vertices or joints."""
    if target == "hand_vertices":
        import torch

        betas = np.tile(ctx["betas"], (len(kept), 1))
        with torch.no_grad():
            hand = mano(torch.as_tensor(full), torch.as_tensor(betas), torch.as_tensor(transl)).vertices.numpy()
    else:
        hand = np.stack([lab["joint_3d"][0].astype(np.float64) for _, _, lab in kept])
    obj = reader.object_vertices(ctx["name"])
    out = np.empty(len(kept))
    for k, (_, _, lab) in enumerate(kept):
        rt = lab["pose_y"][ctx["grasp"]].astype(np.float64)
        out[k] = cKDTree(hand[k]).query(obj @ rt[:, :3].T + rt[:, 3])[0].min()
    return out


def count_warnings(expected: dict, counts: dict, setting: str, source: str) -> list[str]:
    """One line per split whose selected frame count differs from the count a preset states for the full dataset.

    Args:
        expected: {split: frames} as the TOML states it (``[dataset.expected_frames]``).
        counts: {split: frames} this build selected.
        setting: the setting's name (named in the line).
        source: its TOML file (named in the line).
    """
    lines = []
    for split, want in expected.items():
        got = counts.get(split)
        if got is not None and got != want:
            lines.append(f"hoidata: warning: setting {setting!r} selected {got} {split} frames; {source} states "
                         f"{want} for the full dataset")
    return lines
