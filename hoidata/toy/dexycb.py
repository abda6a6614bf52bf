"""Write a small toy dataset in the exact DexYCB on-disk layout (docs/conventions.md,
"The datasets on disk").

Everything the toolkit reads is there with its real names, keys, dtypes and units: ``meta.yml``,
``pose.npz`` (world frame, quaternion x,y,z,w + translation), per camera ``color_%06d.jpg``,
``aligned_depth_to_color_%06d.png`` (uint16 mm) and ``labels_%06d.npz`` (``seg``, ``pose_y``,
``pose_m`` with the PCA pose, ``joint_3d``, ``joint_2d``), ``calibration/`` (intrinsics per serial,
extrinsics camera -> world, MANO betas per subject and side) and ``models/``.

The default size covers every split of setups s0, s1 and s2 and both hands (left-hand sequences in
train); s3 val/test need ``sequences >= 40`` because the toolkit picks them by sequence index.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml
from scipy.spatial.transform import Rotation

from hoidata.datasets.dexycb_layout import SERIALS, SUBJECTS
from hoidata.engine import Plan, ShardTask, run_task
from hoidata.geometry.crop import project
from hoidata.hand.pose import axis_angle_to_pca
from hoidata.render import skin_tone
from hoidata.toy import scenes as toy_scenes

HAND_LABEL = 255  # DexYCB seg: 0 background, 1..21 YCB class id, 255 hand
INVALID_FRAME = 7  # in every third sequence this frame's annotation is marked invalid, as the toolkit does


@dataclass(frozen=True)
class ToyDexYCBSize:
    subjects: tuple[int, ...] = (0, 2, 6, 7)  # indices into SUBJECTS: s0 val (0), test (2, 7); s1 val 6, test 7
    sequences: int = 5  # per subject; the toolkit's i % 5 == 4 rule puts the last in val/test
    serials: tuple[int, ...] = (0, 6, 7)  # indices into SERIALS: s2 train / val / test
    frames: int = 10
    invalid_frame: int = INVALID_FRAME  # marked invalid (every camera) in sequences 2, 5, 8, ...


def sequence_side(seq: int) -> str:
    """Left hands in sequences 1 and 3 (train); the rest, val and test included, are right hands."""
    return "left" if seq in (1, 3) else "right"


def _write_yaml(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def _seq_name(subject: str, seq: int) -> str:
    return f"{subject[:8]}_{141000 + 100 * seq:06d}"


def write_calibration(root: Path, size: ToyDexYCBSize, rng: np.random.Generator) -> tuple[dict, dict, dict]:
    """Intrinsics per serial, one extrinsics set, betas per subject; returns (K, cam->world, betas)."""
    serials = [SERIALS[c] for c in size.serials]
    Ks = {s: toy_scenes.intrinsics(rng) for s in serials}
    cams = dict(zip(serials, toy_scenes.ring_cameras(len(serials), rng)))
    for s, K in Ks.items():
        color = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "ppx": float(K[0, 2]), "ppy": float(K[1, 2])}
        _write_yaml(root / "calibration" / "intrinsics" / f"{s}_640x480.yml", {"serial": s, "color": color})
    extr = {s: [float(x) for x in cams[s][:3].ravel()] for s in serials}
    _write_yaml(root / "calibration" / "extrinsics_20200702_151821" / "extrinsics.yml",
                {"extrinsics": extr, "master": serials[0]})
    betas = {}
    for s in size.subjects:
        b = rng.normal(0.0, 0.8, size=10)
        for side in ("right", "left"):  # DexYCB uses the same betas for both hands of a subject
            calib = f"{SUBJECTS[s][:8]}_140042_{SUBJECTS[s][9:]}_{side}"
            _write_yaml(root / "calibration" / f"mano_{calib}" / "mano.yml", {"betas": [float(x) for x in b]})
            betas[(s, side)] = (calib, b)
    return Ks, cams, betas


def write_sequence(root, renderer, manos, objects, subject_pos, s, seq, size, calib, seed) -> int:
    """Render and write one sequence folder; returns the number of images written."""
    Ks, cams, betas = calib
    rng = np.random.default_rng([seed, s, seq])
    side = sequence_side(seq)
    names = sorted(objects)
    grasped, other = objects[names[(subject_pos + seq) % len(names)]], objects[names[(subject_pos + seq + 2) % len(names)]]
    calib_name, b = betas[(s, side)]
    mano = manos[side]
    sequence = toy_scenes.make_sequence(mano, grasped, b, size.frames, rng)
    other_pose = toy_scenes.rigid(Rotation.from_euler("z", rng.uniform(0, 6.28)).as_matrix(),
                                  np.array([rng.uniform(0.18, 0.25) * rng.choice([-1, 1]), rng.uniform(-0.25, 0.25), 0.05]))
    seq_dir = root / SUBJECTS[s] / _seq_name(SUBJECTS[s], seq)
    serials = [SERIALS[c] for c in size.serials]
    _write_yaml(seq_dir / "meta.yml", {
        "serials": serials, "num_frames": size.frames, "ycb_ids": [grasped.class_id, other.class_id],
        "ycb_grasp_ind": 0, "mano_sides": [side], "mano_calib": [calib_name], "extrinsics": "20200702_151821"})
    _write_pose_npz(seq_dir, mano, sequence, other_pose)
    skin = skin_tone(rng)  # one skin tone per sequence, seen by every camera
    invalid = size.invalid_frame if seq % 3 == 2 and size.frames > size.invalid_frame else None
    for serial in serials:
        (seq_dir / serial).mkdir(parents=True, exist_ok=True)
        look = toy_scenes.random_look(rng, renderer.width, renderer.height, skin)
        for f in range(size.frames):
            view = toy_scenes.render_view(renderer, mano, sequence, f, Ks[serial], cams[serial],
                                          [(other, other_pose)], look, HAND_LABEL)
            _write_frame(seq_dir / serial, f, view, mano, Ks[serial], other_pose, cams[serial], f == invalid)
    return len(serials) * size.frames


def _write_frame(cam_dir: Path, f: int, view, mano, K, other_pose_w, cam_to_world, invalid: bool) -> None:
    cv2.imwrite(str(cam_dir / f"color_{f:06d}.jpg"), cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, 92])
    depth_mm = np.clip(np.round(view.depth * 1000.0), 0, 65535).astype(np.uint16)
    cv2.imwrite(str(cam_dir / f"aligned_depth_to_color_{f:06d}.png"), depth_mm)
    rot, trans = toy_scenes.world_to_camera(cam_to_world)
    other = np.concatenate([rot @ other_pose_w[:3, :3], (rot @ other_pose_w[:3, 3] + trans)[:, None]], axis=1)
    pose_pca = axis_angle_to_pca(view.hand_pose[None], mano.hands_components.double().numpy(),
                                 mano.hands_mean.double().numpy())[0]
    labels = {
        "seg": view.labels.astype(np.uint8),
        "pose_y": np.stack([view.object_pose[:3], other]).astype(np.float32),
        "pose_m": np.concatenate([pose_pca, view.hand_transl])[None].astype(np.float32),
        "joint_3d": view.joints[None].astype(np.float32),
        "joint_2d": project(view.joints, K)[None].astype(np.float32),
    }
    if invalid:  # the toolkit marks a failed annotation with -1 joints and a zero pose
        labels["joint_3d"][:] = -1
        labels["joint_2d"][:] = -1
        labels["pose_m"][:] = 0
    np.savez_compressed(cam_dir / f"labels_{f:06d}.npz", **labels)


def _write_pose_npz(seq_dir: Path, mano, seq, other_pose) -> None:
    """Sequence-level world-frame poses: pose_y (F, n_obj, 7) quat x,y,z,w + t; pose_m (F, 1, 51) PCA."""
    def qt(p):
        return np.concatenate([Rotation.from_matrix(p[:3, :3]).as_quat(), p[:3, 3]])

    pose_y = np.array([[qt(p), qt(other_pose)] for p in seq.object_poses], dtype=np.float32)
    pca = axis_angle_to_pca(seq.hand_pose, mano.hands_components.double().numpy(), mano.hands_mean.double().numpy())
    pose_m = np.concatenate([pca, seq.hand_transl], axis=1)[:, None].astype(np.float32)
    np.savez_compressed(seq_dir / "pose.npz", pose_y=pose_y, pose_m=pose_m)


@dataclass
class ToyJob:
    """One toy sequence to write: its number, the tree's root, the subject (and its position), the sequence, the
    tree's size, calibration and seed."""

    number: int
    root: Path
    subject_pos: int
    subject: int  # index into SUBJECTS
    sequence: int
    size: ToyDexYCBSize
    calib: tuple  # write_calibration's
    seed: int


@dataclass(frozen=True)
class ToyWorkerSpec:
    """What a worker process needs to render toy sequences (picklable: the engine sends it to every worker)."""

    mano_dir: Path
    models_dir: Path

    def open(self) -> ToyWorker:
        return ToyWorker(self.mano_dir, self.models_dir)


class ToyWorker:
    """One process's MANO layers, toy objects and offscreen renderer (GL contexts do not fork); writes sequences."""

    def __init__(self, mano_dir: Path, models_dir: Path):
        from hoidata.hand import load_mano
        from hoidata.render import Renderer

        torch.set_num_threads(1)
        # Left labels are made with MANO_LEFT as shipped (no shapedirs fix), as DexYCB's were.
        self.manos = {side: load_mano(mano_dir, side=side, fix_left_shapedirs=False, dtype=torch.float64)
                      for side in ("right", "left")}
        self.objects = toy_scenes.load_toy_objects(models_dir)
        self.renderer = Renderer(640, 480)

    def run(self, job: ToyJob) -> tuple[int, int, list]:
        """Write one sequence; returns (its number, images written, no skips)."""
        images = write_sequence(job.root, self.renderer, self.manos, self.objects, job.subject_pos, job.subject,
                                job.sequence, job.size, job.calib, job.seed)
        return job.number, images, []

    def close(self) -> None:
        self.renderer.close()


@dataclass
class ToyTask(ShardTask):
    """The toy writer's task for :func:`hoidata.engine.run_task`: one unit per sequence (no resume: a toy tree is
    written whole, so ``done`` and ``check_kept`` keep the base's no-op defaults)."""

    jobs: list[ToyJob]  # one per sequence, in unit order
    worker: ToyWorkerSpec
    plan: Plan
    desc: str = "toy dexycb sequences"

    def job(self, number: int) -> ToyJob:
        return self.jobs[number]


def write_toy_dexycb(root: str | Path, mano_dir: Path, models_dir: Path, size: ToyDexYCBSize = ToyDexYCBSize(),
                     seed: int = 0, workers: int = 2, progress: bool = True) -> dict:
    """Write the toy DexYCB tree under `root` (MANO files and models must exist). Returns counts.

    Sequences are independent (each seeds its own generator), so the files are the same whatever the
    number of worker processes.
    """
    root = Path(root)
    calib = write_calibration(root, size, np.random.default_rng(seed))
    pairs = [(pos, s, q) for pos, s in enumerate(size.subjects) for q in range(size.sequences)]
    jobs = [ToyJob(n, root, pos, s, q, size, calib, seed) for n, (pos, s, q) in enumerate(pairs)]
    run = run_task(ToyTask(jobs, ToyWorkerSpec(Path(mano_dir), Path(models_dir)), Plan(len(jobs), 1)), workers,
                   progress=progress)
    return {"subjects": len(size.subjects), "sequences": len(jobs), "images": run.written}
