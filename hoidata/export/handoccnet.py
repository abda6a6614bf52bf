"""The HandOccNet family's COCO-style annotation files (HandOccNet, H2ONet, HandBooster read the same layout).

Written as ``namepllet/HandOccNet@495aa16:data_parsing/DEX_YCB.py`` and ``data_parsing/HO3D.py`` write them,
with the names and places its loaders open (``data/DEX_YCB/DEX_YCB.py`` and ``data/HO3D/HO3D.py``, class
``DEX_YCB`` / ``HO3D``, ``load_data``)::

    OUT/annotations/DEX_YCB_s0_train_data.json   DEX_YCB_s0_test_data.json  (+ DEX_YCB_s0_val_data.json -> test,
                                                  the name HandOccNet's loader opens for testing since bee013f)
    OUT/<subject>/...                             -> the DexYCB subject folders (links); file_name is relative to OUT
    OUT/annotations/HO3D_train_data.json         HO3D_evaluation_data.json
    OUT/train, OUT/evaluation                     -> HO-3D's split folders; file_name is relative to OUT/<split>

``{"images": [...], "annotations": [...]}`` (pycocotools reads it; no categories). DexYCB: image and
annotation ``id`` = the toolkit's sample index; ``joints_coord_cam`` (21, 3) metres, OpenCV camera frame,
DexYCB joint order; ``joints_img`` (21, 2) pixels; ``cam_param`` {focal [fx, fy], princpt [cx, cy]};
``mano_param`` {pose (48): the global axis-angle then the 45 finger values *without* MANO's hands_mean (the
loaders' MANO layer has ``flat_hand_mean=False`` and adds it; left hands with the left model's mean, as the
writer's left PCA basis gives), shape (10)}; ``hand_type`` 'right' | 'left'. HO-3D: ``id`` = the line in
``train.txt`` / ``evaluation.txt``; train has ``joints_coord_cam`` (OpenCV, DexYCB order), ``cam_param``
and ``mano_param`` (global rotation in OpenCV); evaluation has ``root_joint_cam`` (3,), ``cam_param`` and
``bbox`` (HO-3D's ``handBoundingBox`` as x, y, w, h). Annotations follow the reader's order, which for
HO-3D's evaluation split is ``evaluation.txt``'s (the order its predictions are dumped in).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.export.files import link, write_coco
from hoidata.hand.pose import flat_to_mean_relative
from hoidata.reading import read_lines


def cam_param(K: np.ndarray) -> dict:
    return {"focal": [float(K[0, 0]), float(K[1, 1])], "princpt": [float(K[0, 2]), float(K[1, 2])]}


def frame_entry(worker, frame, ident: int) -> dict:
    """The image and annotation entries of one frame (see the module docstring); ``worker``: the process's
    :class:`~hoidata.export.worker.ExportWorker` (its MANO layers give ``hands_mean``)."""
    width, height = (int(v) for v in frame.image_size)
    if frame.dataset == "ho3d":
        rel = f"{frame.source['sequence']}/rgb/{Path(frame.image_path).name}"
    else:
        src = frame.source
        rel = f"{src['subject']}/{src['sequence']}/{src['serial']}/{Path(frame.image_path).name}"
    image = {"id": ident, "file_name": rel, "width": width, "height": height}
    ann = {"id": ident, "image_id": ident, "cam_param": cam_param(frame.K)}
    if frame.dataset == "ho3d" and frame.split == "evaluation":
        x1, y1, x2, y2 = (float(v) for v in frame.hand_box)
        ann.update(root_joint_cam=np.asarray(frame.root_3d, float).tolist(), bbox=[x1, y1, x2 - x1, y2 - y1])
    else:
        pose = flat_to_mean_relative(np.asarray(frame.mano_pose, float), worker.hands_mean(frame.side))
        ann.update(joints_coord_cam=np.asarray(frame.joints_3d, float).tolist(),
                   mano_param={"pose": pose.tolist(), "shape": np.asarray(frame.mano_betas, float).tolist()})
        if frame.dataset != "ho3d":  # HandOccNet's HO-3D file has neither (its loader projects the joints)
            ann.update(joints_img=np.asarray(frame.joints_2d, float).tolist(), hand_type=frame.side)
    return {"split": frame.split, "image": image, "annotation": ann, "files": []}


def annotation_name(dataset: str, setup: str, split: str) -> str:
    """The file a loader opens, relative to its data root."""
    if dataset == "ho3d":
        return f"annotations/HO3D_{split}_data.json"
    return f"annotations/DEX_YCB_{setup}_{split}_data.json"


def listed_frames(path: Path) -> int:
    """How many frames an HO-3D split list (``evaluation.txt``) names: its non-empty lines."""
    return len(read_lines(path, "HO-3D frame list"))


def finish(out: Path, cfg, splits, entries, root: Path, models_dir: Path) -> tuple[list[str], dict, list[str]]:
    """Write the annotation files and link the image folders; returns (files written, {}, notes)."""
    dataset, files, notes = cfg.dataset.name, [], []
    for split in splits:
        name = annotation_name(dataset, cfg.dataset.setup, split)
        n = write_coco(out / name, entries, split)
        files.append(name)
        notes.append(f"{name}: {n} annotations")
        listed = root / f"{split}.txt"
        if dataset == "ho3d" and split == "evaluation" and listed.is_file():
            lines = listed_frames(listed)
            if n != lines:  # HandOccNet dumps its predictions in annotation order, the challenge scores all lines
                notes.append(f"warning: {name} holds {n} of the {lines} frames of {listed.name}: a prediction file "
                             "made from it would not be complete")
    test = annotation_name(dataset, cfg.dataset.setup, "test")
    alias = out / annotation_name(dataset, cfg.dataset.setup, "val")
    if dataset == "dexycb" and "test" in splits and "val" not in splits:
        if alias.is_symlink() or not alias.exists():
            alias.unlink(missing_ok=True)
            alias.symlink_to(Path(test).name)
            files.append(alias.relative_to(out).as_posix())
            notes.append(f"{alias.relative_to(out).as_posix()} -> {Path(test).name} "
                         "(HandOccNet's loader at HEAD opens 'val')")
    if dataset == "dexycb":
        folders = sorted({e["image"]["file_name"].split("/")[0] for e in entries()})
    else:
        folders = list(splits)
    linked = [name for name in folders if link(root / name, out / name)]
    if linked:
        notes.append(f"linked {', '.join(linked)} -> {root}")
    return files, {}, notes
