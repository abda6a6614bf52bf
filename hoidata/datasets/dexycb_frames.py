"""Turning one DexYCB sequence into Frames: label checks, PCA -> axis-angle, the setting's frame rules."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hoidata.datasets.dexycb_layout import (
    IMAGE_SIZE,
    SERIALS,
    SUBJECTS,
    color_path,
    label_path,
    object_name,
    read_betas,
    read_intrinsics,
    read_labels,
)
from hoidata.datasets.dexycb_selection import hand_box_ok, selection_reasons
from hoidata.datasets.frame import Frame, Skip
from hoidata.errors import DataError
from hoidata.hand.pose import pca_to_axis_angle


# what a frame is made from: the readers do not decode the 300 kB seg image (read_labels checks its header; the
# build's mask check decodes it)
FRAME_KEYS = ("pose_y", "pose_m", "joint_3d", "joint_2d")

# The one marker the toolkit's own evaluators skip a sample for (hpe_eval: joint_3d all -1): a result file
# that leaves out only such samples is complete.
TOOLKIT_INVALID = "hand annotation missing (joint_3d is -1)"


def invalid_reason(labels: dict, grasp: int, check_box: bool = True) -> str | None:
    """Why a frame's annotation cannot be used, or None if it can (the toolkit's invalid markers; with
    ``check_box`` also HandOccNet's hand box rule)."""
    if np.all(labels["joint_3d"] == -1):
        return TOOLKIT_INVALID
    if not np.any(labels["pose_m"]):
        return "MANO pose missing (pose_m is all zeros)"
    if not np.any(labels["pose_y"][grasp]):
        return "grasped object pose missing (pose_y is all zeros)"
    if not np.isfinite(labels["joint_3d"]).all() or not np.isfinite(labels["pose_m"]).all():
        return "non-finite values in joint_3d or pose_m"
    if check_box and not hand_box_ok(labels["joint_2d"][0]):
        return "hand box (1.5x the 2D joints) fails HandOccNet's process_bbox"
    return None


def sequence_frames(reader, s: int, seq_index: int, seq_dir: Path, meta: dict) -> Iterator[Frame]:
    """Frames of one sequence for `reader` (a DexYCBReader), cameras in SERIALS order, then frames."""
    subject, setting = SUBJECTS[s], reader.setting
    side = str(meta["mano_sides"][0])
    if side not in setting.sides and reader.frame_ids is None:
        reader.skipped.append(Skip(f"{subject}_{seq_dir.name}", f"{side} hand: setting {setting.name} keeps {setting.sides}",
                                   str(seq_dir / "meta.yml")))
        return
    try:
        betas = read_betas(reader.root, str(meta["mano_calib"][0]))
        name = object_name(meta["ycb_ids"][int(meta["ycb_grasp_ind"])], seq_dir / "meta.yml")
    except DataError as e:
        reader._fail(e, f"{subject}_{seq_dir.name}")
        return
    grasp = int(meta["ycb_grasp_ind"])
    for serial in sorted({str(x) for x in meta["serials"]} - set(SERIALS)):  # a typo would drop a camera silently
        reader.skipped.append(Skip(f"{subject}_{seq_dir.name}_{serial}", f"meta.yml lists camera serial {serial!r}, "
                                   "which is not a DexYCB camera: its frames are not read", str(seq_dir / "meta.yml")))
    for c in reader._serials:
        serial = SERIALS[c]
        if serial not in [str(x) for x in meta["serials"]]:
            continue
        try:
            K = read_intrinsics(reader.root, serial)
        except DataError as e:
            reader._fail(e, f"{subject}_{seq_dir.name}_{serial}")
            continue
        kept = []
        for f in _frames_to_read(reader, subject, seq_dir.name, serial, int(meta["num_frames"])):
            fid = f"{subject}_{seq_dir.name}_{serial}_{f:06d}"
            try:
                labels = read_labels(label_path(seq_dir, serial, f), len(meta["ycb_ids"]), keys=FRAME_KEYS)
            except DataError as e:
                reader._fail(e, fid)
                continue
            reason = invalid_reason(labels, grasp, reader.split in setting.box_splits and reader.frame_ids is None)
            if reason:
                sample = -1 if reader.toolkit is None else reader.toolkit.sample_index(subject, seq_dir.name, serial, f)
                reader.skipped.append(Skip(fid, reason, str(label_path(seq_dir, serial, f)), sample))
                continue
            kept.append((f, fid, labels))
        try:
            frames = list(_frames_for_camera(reader, kept, dict(subject=subject, seq_dir=seq_dir, seq_index=seq_index,
                                                         serial=serial, K=K, side=side, betas=betas,
                                                         grasp=grasp, name=name, class_id=int(meta["ycb_ids"][grasp]),
                                                         num_objects=len(meta["ycb_ids"]))))
        except DataError as e:  # e.g. the grasped object's model is missing (proximity filter)
            reader._fail(e, f"{subject}_{seq_dir.name}_{serial}")
            continue
        yield from frames


def _frames_to_read(reader, subject: str, sequence: str, serial: str, num_frames: int) -> list[int]:
    """The frames of one camera the reader looks at: every ``frame_stride``-th, or those a frame list names."""
    if reader.frame_ids is None:
        return list(range(0, num_frames, reader.setting.frame_stride))
    first = reader.toolkit.sample_index(subject, sequence, serial, 0) if num_frames else 0
    return [f for f in range(num_frames) if first + f in reader.frame_ids]


def _frames_for_camera(reader, kept: list, ctx: dict) -> Iterator[Frame]:
    if not kept:
        return
    mano = reader.mano(ctx["side"])
    pose_m = np.stack([lab["pose_m"][0] for _, _, lab in kept]).astype(np.float64)
    full = pca_to_axis_angle(pose_m[:, :48], mano.hands_components.double().numpy(), mano.hands_mean.double().numpy())
    transl = pose_m[:, 48:51]
    reasons, toolkit = selection_reasons(reader, mano, full, transl, kept, ctx), reader.toolkit
    for k, (f, fid, lab) in enumerate(kept):
        lpath = label_path(ctx["seq_dir"], ctx["serial"], f)
        sample = -1 if toolkit is None else toolkit.sample_index(ctx["subject"], ctx["seq_dir"].name, ctx["serial"], f)
        if reasons[k]:
            reader.skipped.append(Skip(fid, reasons[k], str(lpath), sample))
            continue
        pose = np.eye(4)
        pose[:3] = lab["pose_y"][ctx["grasp"]]
        joints = lab["joint_3d"][0].astype(np.float64)
        yield Frame(
            dataset="dexycb", split=reader.split, frame_id=fid, image_path=color_path(ctx["seq_dir"], ctx["serial"], f),
            image_size=IMAGE_SIZE, K=ctx["K"], side=ctx["side"], root_3d=joints[0], object_name=ctx["name"],
            object_id=ctx["class_id"], object_pose=pose, mano_pose=full[k], mano_betas=ctx["betas"],
            mano_transl=transl[k], joints_3d=joints, joints_2d=lab["joint_2d"][0].astype(np.float64),
            tip_convention="manopth", mirror=(reader.setting.mirror_left or reader.frame_ids is not None)
            and ctx["side"] == "left",
            fix_left_shapedirs=reader.setting.fix_left_shapedirs,
            segmentation_path=lpath, sample_index=sample,
            source={"labels": str(lpath), "subject": ctx["subject"], "sequence": ctx["seq_dir"].name,
                    "sequence_index": ctx["seq_index"], "serial": ctx["serial"], "frame": f,
                    "num_objects": len(lab["pose_y"])},
        )
