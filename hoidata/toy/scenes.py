"""Procedural hand-object sequences shared by the toy DexYCB and HO-3D writers.

A sequence is one synthesized grasp (hand placed against the object, fingers closed until contact,
checked with python-fcl) carried along a short lift-and-turn motion in a world frame, preceded by a
few approach frames in which the hand has not reached the object yet (those frames exercise the
readers' hand-object proximity filter). Rendering a view returns pixels and labels from the same
poses, so labels and images agree by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hoidata.hand.pose import change_frame


@dataclass
class ToyObject:
    name: str
    class_id: int
    mesh: object  # textured trimesh for rendering (model frame, metres)
    vertices: np.ndarray  # repaired, watertight geometry for contact checks
    faces: np.ndarray


def load_toy_objects(models_dir) -> dict[str, ToyObject]:
    """Every object of a YCB-layout folder, with its repaired geometry."""
    from hoidata.objects import (
        class_id,
        list_objects,
        load_object_mesh,
        object_mesh_path,
        repair_mesh,
    )

    out = {}
    for name in list_objects(models_dir):
        mesh = load_object_mesh(object_mesh_path(models_dir, name))
        geo, _ = repair_mesh(mesh)
        out[name] = ToyObject(name, class_id(name), mesh, np.asarray(geo.vertices), np.asarray(geo.faces))
    return out


@dataclass
class Sequence:
    """World-frame motion of one grasp. Poses per frame: object (F, 4, 4) model -> world, MANO (F, 48), (F, 3)."""

    side: str
    betas: np.ndarray
    object: ToyObject
    object_poses: np.ndarray
    hand_pose: np.ndarray
    hand_transl: np.ndarray
    rest_wrist: np.ndarray  # (3,) MANO rest wrist for these betas: the pivot of every frame change

def rigid(rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """The (4, 4) transform [rot | trans] of a (3, 3) rotation and a (3,) translation (metres)."""
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rot, trans
    return t


def retreat_direction(mano, obj: ToyObject, grasp, frames: int, step: float, max_penetration: float = 0.002):
    """A direction (object frame) along which the hand can back off `frames` x `step` without entering
    the object: the reverse of the palm's approach, else away from the object's centre, else None."""
    from hoidata.synth.contact import penetration_depth

    if frames == 0:
        return None
    closed = mano.closed_faces
    for direction in (-np.asarray(grasp.approach, np.float64), grasp.transl - obj.vertices.mean(0)):
        direction = direction / (np.linalg.norm(direction) + 1e-12)
        offsets = [k * step * direction for k in range(1, frames + 1)]
        with torch.no_grad():
            out = mano(torch.as_tensor(np.tile(grasp.pose, (frames, 1))), torch.as_tensor(np.tile(grasp.betas, (frames, 1))),
                       torch.as_tensor(np.array([grasp.transl + o for o in offsets])))
        hands = mano.close(out.vertices).double().numpy()
        if all(penetration_depth(h, obj.vertices, obj.faces, hand_faces=closed) <= max_penetration for h in hands):
            return direction
    return None  # the sequence then starts in contact


def make_sequence(mano, obj: ToyObject, betas: np.ndarray, n_frames: int, rng: np.random.Generator,
                  approach_frames: int = 2, approach_step: float = 0.015) -> Sequence:
    """Synthesize a grasp of `obj` and move the hand-object pair over `n_frames` frames (world: z up)."""
    from hoidata.synth.grasp import synthesize_grasp

    grasp = synthesize_grasp(mano, obj.vertices, obj.faces, rng, betas=betas)
    wrist = mano.rest_wrist(betas)
    away = retreat_direction(mano, obj, grasp, approach_frames, approach_step)
    base_rot = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)).as_matrix()
    lift = rng.uniform(0.02, 0.06)
    turn = rng.normal(0.0, 0.25, size=3)
    poses, hand_pose, hand_transl = [], [], []
    for f in range(n_frames):
        s = max(0, f - approach_frames) / max(1, n_frames - approach_frames - 1)
        rot = Rotation.from_rotvec(turn * s).as_matrix() @ base_rot
        obj_pose = rigid(rot, np.array([0.0, 0.0, 0.05 + lift * s]))
        retreat = max(0, approach_frames - f) * approach_step * away if away is not None else np.zeros(3)
        pose, transl = change_frame(grasp.pose, grasp.transl + retreat, wrist, obj_pose[:3, :3], obj_pose[:3, 3])
        poses.append(obj_pose)
        hand_pose.append(pose)
        hand_transl.append(transl)
    return Sequence(mano.side, betas, obj, np.array(poses), np.array(hand_pose), np.array(hand_transl), wrist)


def look_at(eye: np.ndarray, target: np.ndarray, up=np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Camera -> world transform (4, 4) of an OpenCV camera at `eye` looking at `target` (image y down)."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return rigid(np.stack([x, y, z], axis=1), eye)


def ring_cameras(n: int, rng: np.random.Generator, radius=(0.55, 0.8), elevation_deg=(25.0, 55.0)) -> list[np.ndarray]:
    """`n` camera -> world transforms around the scene centre, evenly spread in azimuth."""
    target = np.array([0.0, 0.0, 0.08])
    cams = []
    for k in range(n):
        az = 2 * np.pi * k / n + rng.uniform(-0.2, 0.2)
        el = np.deg2rad(rng.uniform(*elevation_deg))
        r = rng.uniform(*radius)
        eye = target + r * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        cams.append(look_at(eye, target))
    return cams


def intrinsics(rng: np.random.Generator, size=(640, 480)) -> np.ndarray:
    """A RealSense-like K (3, 3) for a 640x480 image, slightly different per camera."""
    f = rng.uniform(605.0, 620.0)
    return np.array([[f, 0.0, size[0] / 2 + rng.uniform(-8, 8)], [0.0, f * rng.uniform(0.995, 1.0),
                                                                  size[1] / 2 + rng.uniform(-6, 6)], [0, 0, 1.0]])


def world_to_camera(cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rot = cam_to_world[:3, :3].T
    return rot, -rot @ cam_to_world[:3, 3]


@dataclass
class View:
    """One rendered camera view and its labels (camera frame, OpenCV, metres)."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    hand_pose: np.ndarray  # (48,)
    hand_transl: np.ndarray  # (3,)
    vertices: np.ndarray  # (778, 3)
    joints: np.ndarray  # (21, 3) DexYCB order, the model's tip convention
    mano_joints: np.ndarray  # (16, 3)
    object_pose: np.ndarray  # (4, 4) model -> camera


@dataclass
class Look:
    """What stays fixed for one camera over a sequence, as in a real capture: background and lights."""

    background: np.ndarray  # (H, W, 3) uint8
    lighting: object  # hoidata.render.Lighting
    skin: tuple  # sRGB


def random_look(rng: np.random.Generator, width: int, height: int, skin=None) -> Look:
    from hoidata.render import procedural_background, random_lighting, skin_tone

    return Look(procedural_background(rng, width, height), random_lighting(rng), skin or skin_tone(rng))


def render_view(renderer, mano, seq: Sequence, frame: int, K: np.ndarray, cam_to_world: np.ndarray,
                extra_objects: list, look: Look, hand_label: int) -> View:
    """Render frame `frame` of `seq` from one camera; extra_objects: [(ToyObject, model->world 4x4)]."""
    from hoidata.render import RenderMesh

    rot, trans = world_to_camera(cam_to_world)
    pose, transl = change_frame(seq.hand_pose[frame], seq.hand_transl[frame], seq.rest_wrist, rot, trans)
    with torch.no_grad():
        out = mano(torch.as_tensor(pose)[None], torch.as_tensor(seq.betas)[None], torch.as_tensor(transl)[None])
    verts = out.vertices[0].double().numpy()
    w2c = rigid(rot, trans)
    obj_pose = w2c @ seq.object_poses[frame]
    meshes = [RenderMesh(vertices=mano.close(out.vertices)[0].double().numpy(), faces=mano.closed_faces,
                         color=look.skin, label=hand_label),
              RenderMesh.from_trimesh(seq.object.mesh, transform=obj_pose, label=seq.object.class_id)]
    for obj, pose_w in extra_objects:
        meshes.append(RenderMesh.from_trimesh(obj.mesh, transform=w2c @ pose_w, label=obj.class_id))
    result = renderer.render(K, meshes, background=look.background, lighting=look.lighting)
    return View(result.rgb, result.depth, result.labels, pose, transl, verts, out.joints[0].double().numpy(),
                out.mano_joints[0].double().numpy(), obj_pose)
