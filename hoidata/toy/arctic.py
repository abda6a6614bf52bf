"""Write a small toy ARCTIC in the exact layout of ``arctic_data/data/`` (docs/datasets.md, "ARCTIC").

``raw_seqs/<subject>/<object>_<action>_<nn>.{mano,object,egocam.dist,smplx}.npy`` per sequence (world frame:
MANO ``rot`` / ``pose`` (``flat_hand_mean=False``) / ``trans`` metres / ``shape`` (10,) / ``fitting_err`` per hand;
the object's articulation (radians), axis-angle and translation in **millimetres**; the egocentric camera's
world -> camera pose per frame, intrinsics and 8 rational distortion parameters; a body left at zero),
``meta/misc.json`` (8 allocentric cameras per subject, image sizes, ``ioi_offset``, gender),
``meta/object_vtemplates/`` and ``meta/object_meta.json`` (:mod:`hoidata.toy.arctic_objects`) and
``splits_json/protocol_p1.json`` / ``protocol_p2.json``. No images are written.

Each sequence: the right hand grasps the object's base and the left hand its lid (grasps synthesized on each
part), both hands approach, hold for the middle frames while the object lifts and turns and the lid opens, then
let go; the left hand then leaves every view upwards (frames where ARCTIC flags it invalid), and for
:data:`EGO_AWAY` frames the head turns away from the object (frames invalid in the egocentric view).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from hoidata.atomic import write_atomic
from hoidata.hand.pose import change_frame, flat_to_mean_relative
from hoidata.objects.arctic import ARTICULATION_AXIS
from hoidata.toy.arctic_objects import toy_object, write_toy_templates
from hoidata.toy.scenes import look_at, ring_cameras

MIN_FRAMES = 51  # ARCTIC's loader refuses a sequence of 50 frames or fewer
SUBJECTS = (("s01", "train", 1), ("s05", "val", 2), ("s03", "test", 1))  # name, protocol split, ioi_offset
SEQUENCE_OBJECTS = (("box", "grab"), ("mixer", "use"), ("espressomachine", "grab"), ("capsulemachine", "use"),
                    ("waffleiron", "grab"), ("microwave", "use"))
IMAGE_SIZE = (2800, 2000)  # width, height of every view (ARCTIC fixes the egocentric one at this size)
EGO_AWAY = (20, 24)  # frames [a, b) in which the head looks away from the object
APPROACH, RELEASE, STEP = 12, 16, 0.012  # frames before contact / after it, metres per frame of approach
DIST8 = np.array([0.04, -0.015, 0.0008, -0.0006, 0.002, 0.03, -0.008, 0.001])  # k1 k2 p1 p2 k3 k4 k5 k6


@dataclass(frozen=True)
class ToyArcticSize:
    sequences: int = 1  # per subject
    frames: int = 64


def sequence_names(sequences: int) -> list[tuple[str, str, str]]:
    """(subject, sequence name, object name) of every toy sequence: ``sequences`` per subject."""
    out = []
    for s, (subject, _, _) in enumerate(SUBJECTS):
        for k in range(sequences):
            obj, action = SEQUENCE_OBJECTS[(s + k * len(SUBJECTS)) % len(SEQUENCE_OBJECTS)]
            out.append((subject, f"{obj}_{action}_{k + 1:02d}", obj))
    return out


def _npy(path: Path, value) -> None:
    import io

    buf = io.BytesIO()
    np.save(buf, value, allow_pickle=True)
    write_atomic(path, buf.getvalue())


def _json_bytes(value) -> bytes:
    return (json.dumps(value) + "\n").encode()


def subject_meta(rng: np.random.Generator, ioi_offset: int, gender: str) -> dict:
    """One subject's ``misc.json`` entry: 8 allocentric cameras around the scene (world -> camera, metres)."""
    w, h = IMAGE_SIZE
    world2cam, intris = [], []
    for cam in ring_cameras(8, rng, radius=(1.1, 1.5), elevation_deg=(20.0, 50.0)):
        inv = np.linalg.inv(cam)
        world2cam.append(inv.tolist())
        f = rng.uniform(3400.0, 3800.0)
        intris.append([[f, 0.0, w / 2 + rng.uniform(-20, 20)], [0.0, f, h / 2 + rng.uniform(-20, 20)], [0, 0, 1.0]])
    return {"gender": gender, "image_size": [list(IMAGE_SIZE)] * 9, "intris_mat": intris, "world2cam": world2cam,
            "ioi_offset": ioi_offset}


def _smooth(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def object_track(frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Articulation (F,), object -> world rotations (F, 3, 3) and translations (F, 3) metres: the lid up, the
    object on the table (canonical +y up), lifted and turned while held."""
    yaw, lift, turn = rng.uniform(-np.pi, np.pi), rng.uniform(0.03, 0.06), rng.uniform(0.2, 0.5)
    upright = Rotation.from_euler("x", 90, degrees=True)
    radian, rots, trans = [], [], []
    for f in range(frames):
        s = _smooth((f - APPROACH) / max(1, frames - APPROACH - RELEASE))
        radian.append(0.1 + 1.1 * s + 0.05 * np.sin(0.4 * f))
        rots.append((Rotation.from_euler("z", yaw + turn * s) * upright).as_matrix())
        trans.append([0.0, 0.0, 0.08 + lift * s])
    return np.array(radian), np.array(rots), np.array(trans)


def hand_track(mano, grasp, radian, rots, trans, moving_part: bool, leaves: bool) -> tuple[np.ndarray, np.ndarray]:
    """World MANO pose (F, 48, flat hand mean) and translation (F, 3) of a grasp held on one part."""
    frames = len(radian)
    wrist = mano.rest_wrist(grasp.betas)
    away = -np.asarray(grasp.approach, np.float64) / np.linalg.norm(grasp.approach)
    poses, transl = [], []
    for f in range(frames):
        out = max(0, APPROACH - f) + max(0, f - (frames - RELEASE) + 1)
        offset = out * STEP * away
        hinge = Rotation.from_rotvec(radian[f] * ARTICULATION_AXIS).as_matrix() if moving_part else np.eye(3)
        p, t = change_frame(grasp.pose, grasp.transl + offset, wrist, rots[f] @ hinge, trans[f])
        if leaves and f >= frames - RELEASE + 2:  # the hand flies off upwards, out of every camera
            t = t + np.array([0.0, 0.0, 0.4 * (f - (frames - RELEASE + 1))])
        poses.append(p)
        transl.append(t)
    return np.array(poses), np.array(transl)


def ego_track(frames: int, center: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """World -> egocentric camera (F, 4, 4): a head above and behind the object, looking away in EGO_AWAY."""
    base = np.array([0.0, -0.32, 0.48]) + rng.uniform(-0.03, 0.03, 3)
    out = []
    for f in range(frames):
        eye = base + np.array([0.02 * np.sin(0.2 * f), 0.01 * f / frames, 0.015 * np.cos(0.15 * f)])
        target = center[f] + (np.array([1.6, 0.4, 0.0]) if EGO_AWAY[0] <= f < EGO_AWAY[1] else 0.0)
        out.append(np.linalg.inv(look_at(eye, target)))
    return np.array(out)


def write_sequence(root: Path, subject: str, name: str, obj_name: str, manos: dict, frames: int,
                   rng: np.random.Generator, ego_k: np.ndarray) -> None:
    from hoidata.objects.arctic import ARCTIC_OBJECTS
    from hoidata.synth.grasp import synthesize_grasp

    parts = toy_object(ARCTIC_OBJECTS.index(obj_name))
    betas = rng.normal(0.0, 0.6, 10)
    radian, rots, trans = object_track(frames, rng)
    mano_out = {}
    for side, part in (("right", "bottom"), ("left", "top")):
        verts, faces = parts[part]
        grasp = synthesize_grasp(manos[side], verts / 1000.0, faces, rng, betas=betas, name=f"{obj_name} {part}")
        pose, transl = hand_track(manos[side], grasp, radian, rots, trans, part == "top", side == "left")
        mean = manos[side].hands_mean.double().numpy()
        arctic_pose = flat_to_mean_relative(pose, mean)  # ARCTIC's files: flat_hand_mean=False
        mano_out[side] = {"rot": arctic_pose[:, :3].astype(np.float32), "pose": arctic_pose[:, 3:].astype(np.float32),
                          "trans": transl.astype(np.float32), "shape": betas.astype(np.float32),
                          "fitting_err": rng.uniform(0.002, 0.006, frames).astype(np.float32)}
    rotvec = Rotation.from_matrix(rots).as_rotvec()
    obj = np.concatenate([radian[:, None], rotvec, trans * 1000.0], 1).astype(np.float32)  # translation in mm
    w2e = ego_track(frames, trans, rng)
    ego = {"R_k_cam_np": w2e[:, :3, :3].astype(np.float32), "T_k_cam_np": w2e[:, :3, 3:].astype(np.float32),
           "intrinsics": ego_k.astype(np.float32), "dist8": DIST8.astype(np.float32),
           "R0": np.eye(3, dtype=np.float32), "T0": np.zeros((3, 1), np.float32),
           "ego_markers.ref": np.zeros((4, 3), np.float32), "ego_markers.label": np.array(["m0", "m1", "m2", "m3"])}
    zeros = {k: np.zeros((frames, n), np.float32) for k, n in (("transl", 3), ("global_orient", 3), ("body_pose", 63),
                                                              ("jaw_pose", 3), ("leye_pose", 3), ("reye_pose", 3),
                                                              ("left_hand_pose", 45), ("right_hand_pose", 45))}
    folder = root / "raw_seqs" / subject
    folder.mkdir(parents=True, exist_ok=True)
    _npy(folder / f"{name}.mano.npy", mano_out)
    _npy(folder / f"{name}.object.npy", obj)
    _npy(folder / f"{name}.egocam.dist.npy", ego)
    _npy(folder / f"{name}.smplx.npy", zeros)


def write_toy_arctic(root: str | Path, mano_dir: Path, size: ToyArcticSize = ToyArcticSize(), seed: int = 0,
                     progress: bool = True) -> dict:
    """Write the toy ARCTIC tree under ``root`` (the ``arctic_data/data`` folder; MANO files must exist)."""
    from hoidata.hand import load_mano

    if size.frames < MIN_FRAMES:
        raise ValueError(f"--frames {size.frames}: ARCTIC's loader refuses sequences of 50 frames or fewer; give "
                         f"{MIN_FRAMES} or more (nothing was written)")
    root = Path(root)
    manos = {side: load_mano(mano_dir, side=side, dtype=torch.float64) for side in ("right", "left")}
    write_toy_templates(root / "meta")
    misc, splits = {}, {"train": [], "val": [], "test": []}
    for i, (subject, split, offset) in enumerate(SUBJECTS):
        misc[subject] = subject_meta(np.random.default_rng([seed, i, 0]), offset, ("female", "male")[i % 2])
    names = sequence_names(size.sequences)
    for n, (subject, name, obj_name) in enumerate(tqdm(names, desc="toy arctic sequences", disable=not progress)):
        rng = np.random.default_rng([seed, n, 1])
        f = rng.uniform(1050.0, 1150.0)
        ego_k = np.array([[f, 0.0, IMAGE_SIZE[0] / 2], [0.0, f, IMAGE_SIZE[1] / 2], [0.0, 0.0, 1.0]])
        write_sequence(root, subject, name, obj_name, manos, size.frames, rng, ego_k)
        splits[dict((s, sp) for s, sp, _ in SUBJECTS)[subject]].append(f"{subject}/{name}")
    write_atomic(root / "meta" / "misc.json", _json_bytes(misc))
    for protocol in ("p1", "p2"):
        write_atomic(root / "splits_json" / f"protocol_{protocol}.json", _json_bytes(splits))
    return {"sequences": len(names), "frames": len(names) * size.frames}
