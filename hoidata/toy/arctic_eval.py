"""A toy ARCTIC evaluation: the ground truth the leaderboard holds and a noisy submission, from a toy ARCTIC tree
(:mod:`hoidata.toy.arctic`), in the files ARCTIC's extraction writes (docs/scoring.md, "ARCTIC").

``<out>/gt/<subject>_<sequence>_<view>/{targets,meta_info}/<key>.pt``: every key of ARCTIC's evaluation lists
for the task (poses in each view's camera frame, ``flat_hand_mean=False``; validity flags by ARCTIC's rules,
:mod:`hoidata.datasets.arctic_format`). ``<out>/<task>_<setup>_<split>/eval/<...>/preds/pred.*.pt`` and
``meta_info/meta_info.imgname.pt``: the ground truth plus Gaussian noise (pose task: MANO rotations as
matrices, the object's axis-angle, translations, articulation; field task: the four distance fields), float16
as ARCTIC's extraction saves them, and its ``.zip``. The first sequence's predictions are :data:`EXTRA` frames
longer than its ground truth and its object fields wider than the object (both trimmed by the server).
``python -m hoidata.toy.arctic_eval --root TOY --out DIR`` writes them (:func:`main`).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import hoidata.datasets.arctic_format as af
from hoidata.hand.pose import change_frame
from hoidata.objects.arctic import BOTTOM, TOP, load_arctic_object, pose_object, pose_points

TIPS = (744, 320, 443, 554, 671)  # ARCTIC's fingertip vertices (thumb .. pinky) after MANO's 16 joints
EXTRA = 3  # frames the first sequence's predictions run past its ground truth
POSE_TARGETS = ("mano.pose.r", "mano.pose.l", "mano.beta.r", "mano.beta.l", "object.radian", "object.rot",
                "is_valid", "left_valid", "right_valid", "joints_valid_r", "joints_valid_l", "mano.cam_t.r",
                "mano.cam_t.l", "object.cam_t", "object.bbox3d.cam")
META = ("imgname", "query_names", "window_size", "center", "is_flipped", "rot_angle", "diameter")


@dataclass(frozen=True)
class Noise:
    pose: float = 0.06  # radians, every MANO axis-angle value
    beta: float = 0.15
    cam_t: float = 0.006  # metres
    rot: float = 0.04  # radians, the object's axis-angle
    radian: float = 0.06  # the articulation
    field: float = 0.004  # metres, the distance fields


def hand_forward(mano, pose_arctic: np.ndarray, betas: np.ndarray, transl=None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 778, 3) and ARCTIC's 21 joints (16 MANO joints + :data:`TIPS`) of ARCTIC poses (N, 48,
    ``flat_hand_mean=False``), metres."""
    flat = np.array(pose_arctic, np.float64)
    flat[:, 3:] += mano.hands_mean.double().numpy()
    zero = np.zeros((len(flat), 3)) if transl is None else transl
    with torch.no_grad():
        out = mano(torch.as_tensor(flat), torch.as_tensor(np.asarray(betas, np.float64)), torch.as_tensor(zero))
    v = out.vertices.double().numpy()
    return v, np.concatenate([out.mano_joints.double().numpy(), v[:, list(TIPS)]], 1)


def view_targets(seq, view: int, misc: dict, manos: dict, obj) -> dict:
    """The ground truth of one sequence in one view over its evaluated frames (float64 arrays)."""
    m = misc[seq.subject]
    idx = np.array(af.image_indices(seq.frames)) - m["ioi_offset"]
    w2c = seq.world2ego[idx] if view == 0 else np.broadcast_to(m["world2cam"][view - 1], (len(idx), 4, 4))
    out, cam = {}, {}
    for side, s in (("right", "r"), ("left", "l")):
        h = seq.mano[side]
        pose = np.concatenate([h["rot"], h["pose"]], 1)[idx]
        betas = np.tile(h["shape"], (len(idx), 1))
        rest = manos[side].rest_wrist(h["shape"])
        moved = [change_frame(p, t, rest, w[:3, :3], w[:3, 3]) for p, t, w in zip(pose, h["trans"][idx], w2c)]
        out[f"mano.pose.{s}"] = np.array([m[0] for m in moved])
        out[f"mano.cam_t.{s}"], out[f"mano.beta.{s}"] = np.array([m[1] for m in moved]), betas
        cam[side] = hand_forward(manos[side], out[f"mano.pose.{s}"], betas, out[f"mano.cam_t.{s}"])[1]
    rot = Rotation.from_matrix(w2c[:, :3, :3]) * Rotation.from_rotvec(seq.rotvec[idx])
    out["object.rot"], out["object.radian"] = rot.as_rotvec(), seq.radian[idx]
    out["object.cam_t"] = np.einsum("nij,nj->ni", w2c[:, :3, :3], seq.transl[idx]) + w2c[:, :3, 3]
    verts = pose_object(obj, out["object.radian"], out["object.rot"], out["object.cam_t"])
    out["object.bbox3d.cam"] = pose_points(obj.bbox3d, np.repeat([TOP, BOTTOM], 8), out["object.radian"],
                                           out["object.rot"], out["object.cam_t"])
    K = seq.ego_k if view == 0 else m["intris_mat"][view - 1]
    flags = _flags(K, seq.dist8 if view == 0 else None, cam["right"], cam["left"], verts,
                   m["image_size"][view], view)
    for side in ("right", "left"):  # ARCTIC's dataset stores a hand's flag times the frame's
        flags[f"{side}_valid"] = flags[f"{side}_valid"] * flags["is_valid"]
    out.update(flags)
    out["joints_valid_r"] = np.repeat(flags["right_valid"][:, None], 21, 1)
    out["joints_valid_l"] = np.repeat(flags["left_valid"][:, None], 21, 1)
    names = [f"./data/arctic_data/data/cropped_images/{seq.subject}/{seq.name}/{view}/{i:05d}.jpg"
             for i in af.image_indices(seq.frames)]
    meta = {"imgname": names, "query_names": [seq.object_name] * len(idx), "window_size": np.full(len(idx), 1),
            "center": np.zeros((len(idx), 2)), "is_flipped": np.zeros(len(idx)), "rot_angle": np.zeros(len(idx)),
            "diameter": np.full(len(idx), obj.diameter)}
    return {"targets": out, "meta_info": meta, "verts": verts}


def _flags(K, dist8, right, left, verts, image_size, view) -> dict:
    """ARCTIC's flags of one view (its crop from the undistorted object; egocentric points distorted)."""
    def pix(points):
        return af.project(K, af.distort(points, dist8) if dist8 is not None else points)

    crops = af.crop_boxes(np.repeat(af.project(K, verts)[:, None], 9, 1))  # one view, placed in every slot
    size = np.broadcast_to(np.asarray(image_size, np.float64), (9, 2))
    flags = af.validity(crops, *[np.repeat(pix(p)[:, None], 9, 1) for p in (right, left)],
                        np.repeat(pix(verts).mean(1)[:, None], 9, 1), size)
    slot = 0 if view == 0 else 1
    return {k: v[:, slot].astype(np.float64) for k, v in flags.items()}


def interaction_fields(hand_r, hand_l, verts) -> dict:
    """ARCTIC's interaction fields (N, V): each vertex's distance to the nearest vertex of the other mesh,
    clamped to [0, 0.1] m."""
    out = {k: [] for k in ("dist.ro", "dist.lo", "dist.or", "dist.ol")}
    for hr, hl, vo in zip(hand_r, hand_l, verts):
        for key, a, b in (("dist.ro", hr, vo), ("dist.lo", hl, vo), ("dist.or", vo, hr), ("dist.ol", vo, hl)):
            out[key].append(np.minimum(cKDTree(b).query(a)[0], 0.1))
    return {k: np.array(v) for k, v in out.items()}


def _save(path: Path, value, half: bool = True) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(value, np.ndarray):
        value = torch.as_tensor(value)
        value = value.half() if half and value.is_floating_point() and value.dtype != torch.float64 else value
    torch.save(value, path)


def _noisy_prediction(rng, t: dict, noise: Noise, task: str, fields: dict | None, extra: int) -> dict:
    n = len(t["object.radian"]) + extra
    pad = (lambda a: np.concatenate([a, a[-1:].repeat(extra, 0)])) if extra else (lambda a: a)
    if task == "field":
        out = {}
        for key, value in fields.items():
            wide = np.pad(value, ((0, 0), (0, 7))) if key in ("dist.or", "dist.ol") and extra else value
            out[key] = np.clip(pad(wide) + rng.normal(0, noise.field, (n, wide.shape[1])), 0, 0.1)
        return out
    out = {}
    for s in ("r", "l"):
        pose = pad(t[f"mano.pose.{s}"]) + rng.normal(0, noise.pose, (n, 48))
        out[f"mano.pose.{s}"] = Rotation.from_rotvec(pose.reshape(-1, 3)).as_matrix().reshape(n, 16, 3, 3)
        out[f"mano.beta.{s}"] = pad(t[f"mano.beta.{s}"]) + rng.normal(0, noise.beta, (n, 10))
        out[f"mano.cam_t.{s}"] = pad(t[f"mano.cam_t.{s}"]) + rng.normal(0, noise.cam_t, (n, 3))
    out["object.rot"] = pad(t["object.rot"]) + rng.normal(0, noise.rot, (n, 3))
    out["object.cam_t"] = pad(t["object.cam_t"]) + rng.normal(0, noise.cam_t, (n, 3))
    out["object.radian"] = pad(t["object.radian"]) + rng.normal(0, noise.radian, n)
    return out


def write_toy_evaluation(root: str | Path, out: str | Path, task: str = "pose", setup: str = "p1",
                         split: str = "test", noise: Noise = Noise(), seed: int = 0, mano_dir=None) -> dict:
    """Write the ground truth and a noisy submission of the toy ``root`` (MANO in ``root/mano``)."""
    from hoidata.hand import load_mano

    if task not in ("pose", "field") or setup not in ("p1", "p2"):
        raise ValueError(f"task must be pose or field and setup p1 or p2, got {task!r}, {setup!r}")
    root, out = Path(root), Path(out)
    manos = {s: load_mano(mano_dir or root / "mano", side=s, fix_left_shapedirs=False, dtype=torch.float64)
             for s in ("right", "left")}
    misc = af.read_misc(root)
    task_name = f"{task}_{setup}_{split}"
    sub = out / task_name / "eval"
    rng = np.random.default_rng(seed)
    folders = []
    for n, full in enumerate(af.read_protocol(root, setup)[split]):
        seq = af.read_sequence(root, *full.split("/"))
        obj = load_arctic_object(root / "meta", seq.object_name)
        for view in af.protocol_views(setup):
            key = f"{seq.subject}_{seq.name}_{view}"
            gt = view_targets(seq, view, misc, manos, obj)
            t = gt["targets"]
            fields = None
            if task == "field":
                hands = [hand_forward(manos[side], t[f"mano.pose.{s}"], t[f"mano.beta.{s}"], t[f"mano.cam_t.{s}"])[0]
                         for side, s in (("right", "r"), ("left", "l"))]
                fields = interaction_fields(*hands, gt["verts"])
            keys = POSE_TARGETS if task == "pose" else POSE_TARGETS[:-1]
            for k in keys:
                _save(out / "gt" / key / "targets" / f"targets.{k}.pt", t[k].astype(
                    np.float64 if "valid" in k else np.float32))
            for k in META if task == "pose" else META[:-1]:
                v = gt["meta_info"][k]
                _save(out / "gt" / key / "meta_info" / f"meta_info.{k}.pt",
                      v if isinstance(v, list) else v.astype(np.int64 if k == "window_size" else np.float32))
            pred = _noisy_prediction(rng, t, noise, task, fields, EXTRA if n == 0 else 0)
            for k, v in pred.items():
                _save(sub / key / "preds" / f"pred.{k}.pt", v.astype(np.float32))
            _save(sub / key / "meta_info" / "meta_info.imgname.pt", gt["meta_info"]["imgname"])
            folders.append(key)
    archive = shutil.make_archive(str(out / task_name), "zip", root_dir=out, base_dir=task_name)
    return {"task": task_name, "folders": len(folders), "gt": str(out / "gt"), "submission": str(out / task_name),
            "zip": archive}


def main(argv: list[str] | None = None) -> int:
    """``python -m hoidata.toy.arctic_eval --root TOY --out DIR [--task pose|field] [--setup p1|p2]``."""
    from hoidata.cli_types import ArgumentParser, local_path
    from hoidata.errors import run_cli

    p = ArgumentParser(prog="python -m hoidata.toy.arctic_eval",
                       description="a toy ARCTIC's leaderboard ground truth and a noisy submission")
    p.add_argument("--root", required=True, type=local_path, help="a toy ARCTIC (hoidata make-toy --layout arctic)")
    p.add_argument("--out", required=True, type=local_path, help="output folder (gt/, <task>_<setup>_<split>/, .zip)")
    p.add_argument("--task", choices=("pose", "field"), default="pose")
    p.add_argument("--setup", choices=("p1", "p2"), default="p1")
    p.add_argument("--split", choices=("val", "test"), default="test")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    args = p.parse_args(argv)
    return run_cli("hoidata.toy.arctic_eval", lambda: print(write_toy_evaluation(
        args.root, args.out, args.task, args.setup, args.split, seed=args.seed)) or 0, args.debug)


if __name__ == "__main__":
    raise SystemExit(main())
