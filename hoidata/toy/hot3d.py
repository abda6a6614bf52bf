"""Write small toy HOT3D-Clips in the exact tar layout (docs/datasets.md, "HOT3D-Clips").

``<split>_<device>/clip-<id>.tar`` with one WebDataset sample per frame keyed ``%06d`` (``image_<stream>.jpg``,
``cameras.json``, ``hands.json``, ``hand_crops.json``, ``objects.json``, ``info.json``) and the clip's
``__hand_shapes.json__`` (``mano`` betas and a toy ``umetrack`` profile the
official reader accepts, :mod:`hoidata.toy.hot3d_umetrack`); ``object_models_eval/obj_<bop id>.glb`` (the toy objects, metres) beside them. A clip
shows both toy hands, each grasping a toy object, through the toy headset's FISHEYE624 streams
(:mod:`hoidata.toy.hot3d_rig`). Hand poses are MANO's 15 PCA coefficients (``flat_hand_mean=False``) with the
global orientation and translation in ``wrist_xform``, world frame; the hand drawn is exactly that pose. In frame
``MISSING_FRAME`` the left hand has no ``umetrack_pose`` (so no MANO pose either), as where HOT3D's tracking
failed. Beside the clips, ``toy_truth/clip-<id>.npz`` keeps what the toy drew from (not part of HOT3D): ``joints``
(F, 2, 21, 3) world, right then left, and ``world_from_camera`` (F, S, 4, 4) per stream (``streams``), so tests
compare the reader's chain against the matrices themselves rather than their JSON. Object masks are HOT3D's RLE (1-based starts); transforms are ``quaternion_wxyz`` + ``translation_xyz``.
"""

from __future__ import annotations

import io
import json
import tarfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from hoidata.datasets.hot3d_format import FISHEYE624, HAND_SHAPES, rle_encode
from hoidata.geometry.se3 import se3_to_wxyz
from hoidata.hand.pose import axis_angle_to_pca, change_frame, pca_to_axis_angle
from hoidata.toy import scenes as toy_scenes
from hoidata.toy.hot3d_rig import FisheyeView, box, crop_camera_for, device_streams, wide_side
from hoidata.toy.hot3d_umetrack import umetrack_profile

MISSING_FRAME = 1  # the left hand has no umetrack_pose (nor mano_pose) in this frame of every clip
SIDE_OFFSETS = {"right": 0.11, "left": -0.11}  # metres along world x of each hand's grasp
HAND_LABELS = {"right": 1, "left": 2}
TRUTH = "toy_truth"  # <root>/toy_truth/clip-<id>.npz: the toy's own poses, for tests (not a HOT3D file)
N_PCA = 15


DEFAULT_CLIPS = (("train_aria", 1, "Aria"), ("train_quest3", 2, "Quest3"), ("train_aria", 10, "Aria"))


def toy_clips(count: int) -> tuple:
    """The first ``count`` toy clips as (folder, clip number, device): the default three (two train, the val clip
    10), then clips 3, 4, 5, ... (odd numbers Aria, even Quest 3), skipping 10; the reader puts every multiple of 10
    in ``val`` (20, 30, ...), the rest in ``train``. Each clip is its own grasp of each hand (its own seed)."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"the toy HOT3D-Clips needs a whole number of clips >= 1, got {count!r}")
    out, number = list(DEFAULT_CLIPS[:count]), 3
    while len(out) < count:
        if number != 10:
            device = "Aria" if number % 2 else "Quest3"
            out.append((f"train_{device.lower()}", number, device))
        number += 1
    return tuple(out)


@dataclass(frozen=True)
class ToyHOT3DSize:
    frames: int = 4
    clips: tuple = DEFAULT_CLIPS


def bop_model_name(bop_id: int) -> str:
    return f"obj_{bop_id:06d}.glb"


def write_object_models(out: Path, objects: dict) -> None:
    """The toy objects as ``obj_<class id>.glb`` (HOT3D's object_models_eval layout; BOP id = the toy's class id)."""
    out.mkdir(parents=True, exist_ok=True)
    for obj in objects.values():
        (out / bop_model_name(obj.class_id)).write_bytes(obj.mesh.export(file_type="glb"))


def _json(value) -> bytes:
    return json.dumps(value, sort_keys=True).encode()


def _add(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = len(data), 0, 0o644
    tar.addfile(info, io.BytesIO(data))


@dataclass
class ToyHand:
    side: str
    mano: object
    seq: object  # toy_scenes.Sequence, grasp frame; placed at world x = SIDE_OFFSETS[side]
    thetas: np.ndarray  # (F, 15) PCA coefficients
    wrist_xform: np.ndarray  # (F, 6) world: global orientation (axis-angle), translation
    vertices: np.ndarray  # (F, 778, 3) world
    joints: np.ndarray  # (F, 21, 3) world, DexYCB order
    object_poses: np.ndarray  # (F, 4, 4) the grasped object, model -> world


def make_hand(side: str, mano, obj, betas: np.ndarray, frames: int, rng) -> ToyHand:
    """One hand grasping ``obj``, its pose cut to 15 PCA coefficients (the hand drawn is the one written)."""
    seq = toy_scenes.make_sequence(mano, obj, betas, frames, rng, approach_frames=0)
    shift = np.array([SIDE_OFFSETS[side], 0.0, 0.0])
    pose, transl = change_frame(seq.hand_pose, seq.hand_transl, seq.rest_wrist, np.eye(3), shift)
    comps, mean = mano.hands_components.double().numpy(), mano.hands_mean.double().numpy()
    pca = axis_angle_to_pca(pose, comps, mean)[:, :3 + N_PCA]
    full = pca_to_axis_angle(pca, comps, mean)
    with torch.no_grad():
        out = mano(torch.as_tensor(full), torch.as_tensor(np.tile(betas, (frames, 1))), torch.as_tensor(transl))
    objects = seq.object_poses.copy()
    objects[:, :3, 3] += shift
    return ToyHand(side, mano, seq, pca[:, 3:], np.concatenate([pca[:, :3], transl], 1),
                   out.vertices.double().numpy(), out.joints.double().numpy(), objects)


def rest_joints(mano, betas: np.ndarray) -> np.ndarray:
    """The hand's 21 joints (metres) in MANO's flat rest pose for ``betas``."""
    with torch.no_grad():
        zero = torch.zeros(1, 48, dtype=torch.float64)
        out = mano(zero, torch.as_tensor(betas)[None], zero[:, :3])
    return out.joints[0].double().numpy()


def _hand_entry(hand: ToyHand, f: int, boxes: dict, vis: dict) -> dict:
    entry = {"boxes_amodal": boxes, "visibilities_modeled": vis}
    if hand.side == "left" and f == MISSING_FRAME:
        return entry
    wrist = np.eye(4)
    wrist[:3, :3] = cv2.Rodrigues(hand.wrist_xform[f, :3])[0]
    wrist[:3, 3] = hand.vertices[f].mean(0)  # a stand-in: the toy has no UmeTrack model
    entry["umetrack_pose"] = {"joint_angles": [0.0] * 20, "wrist_xform": wrist.tolist(),
                              "T_world_from_wrist": se3_to_wxyz(wrist)}
    entry["mano_pose"] = {"thetas": hand.thetas[f].tolist(), "wrist_xform": hand.wrist_xform[f].tolist()}
    return entry


def _camera_entry(stream, world_from_camera: np.ndarray) -> dict:
    cam = stream.camera
    return {"calibration": {"label": stream.label, "stream_id": stream.stream_id, "serial_number": f"toy-{stream.label}",
                            "image_width": cam.width, "image_height": cam.height, "projection_model_type": FISHEYE624,
                            "projection_params": cam.params(), "T_device_from_camera": se3_to_wxyz(stream.device_from_camera),
                            "max_solid_angle": 1.1},
            "T_world_from_camera": se3_to_wxyz(world_from_camera)}


def _render_stream(renderer, view, stream, world_from_camera, hands, objects, look):
    """One stream of one frame: the fisheye image, its visible labels and each object's amodal mask."""
    from hoidata.render import RenderMesh

    camera_from_world = np.linalg.inv(world_from_camera)
    meshes = []
    for hand, f in hands:
        verts = hand.vertices[f] @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        closed = hand.mano.close(torch.as_tensor(verts)[None])[0].double().numpy()
        meshes.append(RenderMesh(vertices=closed, faces=hand.mano.closed_faces, color=look.skin,
                                 label=HAND_LABELS[hand.side]))
    obj_meshes = [RenderMesh.from_trimesh(obj.mesh, transform=camera_from_world @ pose, label=obj.class_id)
                  for obj, pose in objects]
    result = renderer.render(view.K, meshes + obj_meshes, background=look.background, lighting=look.lighting)
    _, amodal = renderer.masks(view.K, obj_meshes)
    rgb = view.image(result.rgb)
    image = rgb if stream.is_rgb else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return image, view.labels(result.labels), [view.labels(m.astype(np.uint8)) > 0 for m in amodal]


def head_pose(f: int) -> np.ndarray:
    """Device -> world in frame ``f``: the head moves a little; the hands sit ~30 degrees below the view axis,
    where the lens distorts, and the objects inside the toy's field of view."""
    return toy_scenes.look_at(np.array([0.03 * np.sin(f), -0.38, 0.42 + 0.01 * f]), np.array([0.0, 0.1, 0.30]))


def _frame_members(key: str, f: int, device: str, streams, rig, hands, objects, looks) -> list[tuple[str, bytes]]:
    head = head_pose(f)
    cameras, crops, images = {}, {"left": {}, "right": {}}, []
    hand_boxes, hand_vis = {h.side: {} for h in hands}, {h.side: {} for h in hands}
    obj_info = {obj.class_id: {"boxes_amodal": {}, "masks_amodal": {}, "masks_modal": {}, "visibilities_modeled": {},
                               "visibilities_predicted": {}} for obj, _ in objects}
    for stream in streams:
        renderer, view = rig[stream.stream_id]
        world_from_camera = head @ stream.device_from_camera
        cameras[stream.stream_id] = _camera_entry(stream, world_from_camera)
        image, labels, amodal = _render_stream(renderer, view, stream, world_from_camera, [(h, f) for h in hands],
                                               [(o, p[f]) for o, p in objects], looks[stream.stream_id])
        ok, jpg = cv2.imencode(".jpg", image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, 95])
        images.append((f"{key}.image_{stream.stream_id}.jpg", jpg.tobytes()))
        camera_from_world = np.linalg.inv(world_from_camera)
        for hand in hands:
            eye = hand.vertices[f] @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
            pix = stream.camera.project(eye)
            inside = (eye[:, 2] > 0) & (pix >= 0).all(1) & (pix < [stream.camera.width, stream.camera.height]).all(1)
            hand_boxes[hand.side][stream.stream_id] = box(pix)
            hand_vis[hand.side][stream.stream_id] = float(inside.mean())
            if inside.mean() > 0.1:  # HOT3D saves a crop camera where the hand's visibility exceeds 0.1
                world_from_crop, fov = crop_camera_for(eye, world_from_camera)
                crops[hand.side][stream.stream_id] = {"T_world_from_crop_camera": se3_to_wxyz(world_from_crop),
                                                      "crop_camera_fov": fov}
        for (obj, _), mask in zip(objects, amodal):
            info, modal = obj_info[obj.class_id], labels == obj.class_id
            if mask.any():
                ys, xs = np.nonzero(mask)
                info["boxes_amodal"][stream.stream_id] = [float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())]
            info["masks_amodal"][stream.stream_id] = rle_encode(mask)
            info["masks_modal"][stream.stream_id] = rle_encode(modal)
            vis = float(modal.sum() / max(mask.sum(), 1))
            info["visibilities_modeled"][stream.stream_id] = info["visibilities_predicted"][stream.stream_id] = vis
    objects_json = {str(100000 + obj.class_id): [{"object_bop_id": obj.class_id,
                                                  "T_world_from_object": se3_to_wxyz(poses[f]),
                                                  **obj_info[obj.class_id]}] for obj, poses in objects}
    hands_json = {h.side: _hand_entry(h, f, hand_boxes[h.side], hand_vis[h.side]) for h in hands}
    info = {"device": device, "image_timestamps_ns": {s.stream_id: int(1e9 + f * 33_333_333) for s in streams}}
    return images + [(f"{key}.cameras.json", _json(cameras)), (f"{key}.hands.json", _json(hands_json)),
                     (f"{key}.hand_crops.json", _json(crops)), (f"{key}.objects.json", _json(objects_json)),
                     (f"{key}.info.json", _json(info))]


def write_clip(path: Path, device: str, manos: dict, objects: dict, views: dict, frames: int, seed: int,
               clip_id: int) -> int:
    """Render one clip to ``path`` (a tar); returns the number of frames written."""
    from hoidata.render import skin_tone

    rng = np.random.default_rng([seed, clip_id])
    betas = rng.normal(0.0, 0.8, size=10)  # one shape per clip, shared by both hands (``mano``)
    names = sorted(objects)
    picks = {"right": objects[names[clip_id % len(names)]], "left": objects[names[(clip_id + 2) % len(names)]]}
    hands = [make_hand(side, manos[side], picks[side], betas, frames, rng) for side in ("right", "left")]
    streams = device_streams(device)
    rig = {s.stream_id: views[s.camera] for s in streams}
    skin = skin_tone(rng)  # one skin for both hands, seen by every stream
    looks = {s.stream_id: toy_scenes.random_look(rng, rig[s.stream_id][0].width, rig[s.stream_id][0].height, skin)
             for s in streams}
    path.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tar:
        for f in range(frames):
            for name, data in _frame_members(f"{f:06d}", f, device, streams, rig, hands,
                                             [(h.seq.object, h.object_poses) for h in hands], looks):
                _add(tar, name, data)
        umetrack = umetrack_profile(rest_joints(manos["right"], betas))
        _add(tar, HAND_SHAPES, _json({"mano": betas.tolist(), "umetrack": umetrack}))
    truth = path.parent.parent / TRUTH / f"{path.stem}.npz"
    truth.parent.mkdir(parents=True, exist_ok=True)
    np.savez(truth, streams=np.array([s.stream_id for s in streams]), joints=np.stack([h.joints for h in hands], 1),
             world_from_camera=np.array([[head_pose(f) @ s.device_from_camera for s in streams] for f in range(frames)]))
    return frames


def write_toy_hot3d(root: str | Path, mano_dir: Path, models_dir: Path, size: ToyHOT3DSize = ToyHOT3DSize(),
                    seed: int = 0, progress: bool = True) -> dict:
    """Write the toy HOT3D-Clips tree under ``root`` (MANO files and toy objects must exist). Returns counts."""
    from hoidata.hand import load_mano
    from hoidata.render import Renderer

    root = Path(root)
    manos = {side: load_mano(mano_dir, side=side, dtype=torch.float64) for side in ("right", "left")}
    objects = toy_scenes.load_toy_objects(models_dir)
    write_object_models(root / "object_models_eval", objects)
    streams = [s for device in sorted({d for _, _, d in size.clips}) for s in device_streams(device)]
    side = max(wide_side(s.camera) for s in streams)  # one GL context for every stream (pyrender's display is shared)
    frames = 0
    with Renderer(side, side) as renderer:
        views = {s.camera: (renderer, FisheyeView.of(s.camera, side)) for s in streams}
        for folder, clip_id, device in tqdm(size.clips, desc="toy hot3d clips", disable=not progress):
            frames += write_clip(root / folder / f"clip-{clip_id:06d}.tar", device, manos, objects, views,
                                 size.frames, seed, clip_id)
    return {"clips": len(size.clips), "frames": frames}
