"""Write a small toy dataset in the exact HO-3D v2 on-disk layout (docs/conventions.md,
"The datasets on disk").

``train/<SEQ>/{rgb/<id>.png, depth/<id>.png, seg/<id>.jpg, meta/<id>.pkl}``, the same for
``evaluation/`` with the reduced ground truth, and ``train.txt`` / ``evaluation.txt``; plus the challenge's hidden
ground truth of the evaluation split, ``evaluation_xyz.json`` / ``evaluation_verts.json`` (what its eval.py scores
against). Annotations
are in HO-3D's OpenGL camera frame (y up, scene at negative z), the MANO pose is full axis-angle in
the flat-hand-mean convention, and ``handJoints3D`` uses HO-3D's joint order and fingertip vertices.
Meta pickles are written with protocol 2 and read back through the restricted unpickler.

``version="v3"`` writes v3's on-disk differences (:mod:`hoidata.datasets.ho3d`): JPEG ``rgb/<id>.jpg`` frames, and
an ``evaluation.txt`` of its own order (the toy lists v3's evaluation frames last-to-first, so a submission that
follows the frames' natural order instead of the list is caught), the challenge's ground truth in that order.
The v3 calibration of multi-camera sequences and its manual fingertip annotations are not written (no reader
uses them).
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from hoidata.datasets.ho3d import VERSIONS as RGB_FORMAT
from hoidata.geometry.crop import box_from_points, project
from hoidata.hand.model import DEXYCB_TO_MANO
from hoidata.hand.pose import change_frame
from hoidata.objects import box_corners
from hoidata.toy import scenes as toy_scenes

GL = np.diag([1.0, -1.0, -1.0])  # OpenCV <-> OpenGL camera frame (its own inverse)
DEPTH_SCALE = 0.00012498664727900177  # metres per unit of HO-3D's packed depth
# Real HO-3D sequence names, each paired with a toy object that HO-3D also uses.
TRAIN_SEQUENCES = (("BB10", "011_banana"), ("MC1", "003_cracker_box"), ("SM2", "006_mustard_bottle"))
EVAL_SEQUENCES = (("SM1", "006_mustard_bottle"),)


@dataclass(frozen=True)
class ToyHO3DSize:
    train_sequences: int = 3
    eval_sequences: int = 1
    frames: int = 8


def pack_depth(depth_m: np.ndarray) -> np.ndarray:
    """Depth (H, W) metres -> HO-3D's RGB PNG packing (H, W, 3) uint8 in BGR order for cv2.imwrite."""
    units = np.clip(np.round(depth_m / DEPTH_SCALE), 0, 65535).astype(np.uint16)
    bgr = np.zeros(depth_m.shape + (3,), np.uint8)
    bgr[..., 2] = units & 0xFF  # red: low byte
    bgr[..., 1] = units >> 8  # green: high byte
    return bgr


def unpack_depth(bgr: np.ndarray) -> np.ndarray:
    """HO-3D depth PNG as read by cv2 (BGR) -> metres, as the dataset's ``read_depth_img`` decodes it."""
    return (bgr[..., 2].astype(np.float64) + bgr[..., 1].astype(np.float64) * 256.0) * DEPTH_SCALE


def _gl_meta(view, mano, seq, K) -> dict:
    """Full training annotation of one view, converted to HO-3D's OpenGL frame and joint order."""
    pose_gl, transl_gl = change_frame(view.hand_pose, view.hand_transl, seq.rest_wrist, GL, np.zeros(3))
    obj_rot = GL @ view.object_pose[:3, :3]
    obj_t = GL @ view.object_pose[:3, 3]
    rest = box_corners(np.asarray(seq.object.mesh.vertices))
    return {
        "handPose": pose_gl, "handTrans": transl_gl, "handBeta": np.asarray(seq.betas, np.float64),
        "handJoints3D": (view.joints @ GL.T)[DEXYCB_TO_MANO],
        "objRot": Rotation.from_matrix(obj_rot).as_rotvec()[:, None], "objTrans": obj_t,
        "objCorners3DRest": rest, "objCorners3D": rest @ obj_rot.T + obj_t,
        "objName": seq.object.name, "objLabel": seq.object.class_id, "camMat": K,
    }


def _eval_meta(full: dict, view, K) -> dict:
    """HO-3D's evaluation split keeps only the root joint and the hand box (plus object pose and camera)."""
    box = box_from_points(project(view.vertices, K))
    keep = ("objRot", "objTrans", "objCorners3DRest", "objName", "camMat")
    return {"handJoints3D": full["handJoints3D"][0], "handBoundingBox": box, **{k: full[k] for k in keep}}


HAND_LABEL = 255


def _write_view(seq_dir: Path, fid: str, view, meta: dict, object_label: int, version: str = "v2") -> None:
    for sub in ("rgb", "depth", "seg", "meta"):
        (seq_dir / sub).mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(seq_dir / "rgb" / f"{fid}{RGB_FORMAT[version]}"), cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(seq_dir / "depth" / f"{fid}.png"), pack_depth(view.depth))
    # seg: rendered at 1/4 resolution, hand in red, object in blue (as HOISDF reads it after BGR->RGB)
    h, w = view.labels.shape
    seg = np.zeros((h, w, 3), np.uint8)
    seg[view.labels == HAND_LABEL, 0] = 255
    seg[view.labels == object_label, 2] = 255
    small = cv2.resize(seg, (w // 4, h // 4), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(seq_dir / "seg" / f"{fid}.jpg"), cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
    (seq_dir / "meta" / f"{fid}.pkl").write_bytes(pickle.dumps(meta, protocol=2))


def write_ho3d_sequence(root: Path, split: str, name: str, obj, renderer, mano, frames: int,
                        seed: int, version: str = "v2") -> tuple[list[str], list[tuple[np.ndarray, np.ndarray]]]:
    """Render one sequence from a single camera; returns its ``<SEQ>/<id>`` list entries and, per frame, the
    challenge's ground truth: joints (21, 3) and vertices (778, 3), OpenGL frame, HO-3D joint order, metres."""
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    betas = rng.normal(0.0, 0.8, size=10)
    seq = toy_scenes.make_sequence(mano, obj, betas, frames, rng, approach_frames=0)
    cam = toy_scenes.ring_cameras(1, rng, radius=(0.45, 0.6))[0]
    K = toy_scenes.intrinsics(rng)
    look = toy_scenes.random_look(rng, renderer.width, renderer.height)
    entries, truth = [], []
    for f in range(frames):
        view = toy_scenes.render_view(renderer, mano, seq, f, K, cam, [], look, HAND_LABEL)
        meta = _gl_meta(view, mano, seq, K)
        truth.append((meta["handJoints3D"], view.vertices @ GL.T))
        if split == "evaluation":
            meta = _eval_meta(meta, view, K)
        fid = f"{f:04d}"
        _write_view(root / split / name, fid, view, meta, obj.class_id, version)
        entries.append(f"{name}/{fid}")
    return entries, truth


def write_challenge_truth(root: Path, truth: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """``evaluation_xyz.json`` and ``evaluation_verts.json`` in ``root``, as the challenge's eval.py reads them: JSON
    lists, in ``evaluation.txt`` order, of (21, 3) joints and (778, 3) vertices, metres, OpenGL, HO-3D joint order."""
    import json

    for name, part in (("evaluation_xyz.json", 0), ("evaluation_verts.json", 1)):
        (root / name).write_text(json.dumps([np.asarray(t[part], np.float64).tolist() for t in truth]))


def write_toy_ho3d(root: str | Path, mano_dir: Path, models_dir: Path, size: ToyHO3DSize = ToyHO3DSize(),
                   seed: int = 0, progress: bool = True, version: str = "v2") -> dict:
    """Write the toy HO-3D tree under `root` (MANO files and models must exist), in the layout of ``version``
    ('v2' or 'v3', see the module docstring). Returns counts."""
    from hoidata.hand import load_mano
    from hoidata.render import Renderer

    if version not in RGB_FORMAT:
        raise ValueError(f"unknown HO-3D version {version!r}; expected one of {sorted(RGB_FORMAT)}")
    root = Path(root)
    mano = load_mano(mano_dir, side="right", tips="ho3d", dtype=torch.float64)
    objects = toy_scenes.load_toy_objects(models_dir)
    plan = [("train", n, o) for n, o in TRAIN_SEQUENCES[: size.train_sequences]]
    plan += [("evaluation", n, o) for n, o in EVAL_SEQUENCES[: size.eval_sequences]]
    lists, truth = {"train": [], "evaluation": []}, []
    with Renderer(640, 480) as renderer:
        for split, name, obj in tqdm(plan, desc="toy ho3d sequences", disable=not progress):
            entries, gt = write_ho3d_sequence(root, split, name, objects[obj], renderer, mano, size.frames, seed,
                                              version)
            lists[split] += entries
            truth += gt if split == "evaluation" else []
    if version == "v3":  # the evaluation list in an order of its own
        lists["evaluation"], truth = lists["evaluation"][::-1], truth[::-1]
    for split, entries in lists.items():
        (root / f"{split}.txt").write_text("".join(e + "\n" for e in entries))
    write_challenge_truth(root, truth)
    return {"train": len(lists["train"]), "evaluation": len(lists["evaluation"])}
