"""What the benchmark scripts share: toy inputs (DexYCB trees, stores, the MANO folder, SDF frames) and device helpers.

The scripts run as modules of the ``bench`` package from the repository root (``python -m bench.bench_build``),
so they import this file and their helper modules (``bench.compile_bench``, ``bench.per_file_loaders``) by
package name, and never one another.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hoidata.hand import load_mano
from hoidata.objects import load_object_mesh, repair_mesh
from hoidata.toy.dexycb import ToyDexYCBSize, write_toy_dexycb
from hoidata.toy.hand import write_toy_mano
from hoidata.toy.make import write_assets
from hoidata.toy.objects import TOY_OBJECTS, write_toy_objects

CURLS = (0.0, 0.5, 0.8, 1.0, 1.2)
CAMERA_T = np.array([0.03, -0.02, 0.55])
NOISE = 0.03  # half-width of the "gt" query-point jitter (scaled units), the training schedule's first value


def toy_root(frames: int, work: Path) -> Path:
    """A toy DexYCB under ``work/data`` with about `frames` frames in all (subject 0, 4 sequences, 3 cameras,
    every split), and its MANO and model folders. Returns the dataset root."""
    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=4, serials=(0, 6, 7), frames=max(1, -(-frames // 12)))
    write_toy_dexycb(root, mano, models, size, workers=2, progress=False)
    return root


def toy_train_root(frames: int, work: Path) -> Path:
    """A toy DexYCB under ``work/data`` whose s0 train split holds about `frames` right-hand frames (sequences 0
    and 2 of 3, 3 cameras). Returns the dataset root."""
    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=3, serials=(0, 6, 7), frames=max(2, -(-frames // 6)))
    write_toy_dexycb(root, mano, models, size, workers=2, progress=False)
    return root


def resolve_device(name: str | None) -> torch.device:
    """`name` ('cpu', 'cuda', 'cuda:1'), or CUDA when there is one, else the CPU."""
    return torch.device(name or ("cuda" if torch.cuda.is_available() else "cpu"))


def sync(device: torch.device) -> None:
    """Wait for the device's queued work, so a timer around it measures the work (a no-op on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def toy_store(work: Path, records: int = 32, workers: int = 1) -> tuple[Path, Path]:
    """Build a toy DexYCB train store (512 px crops) of about ``records`` records; returns (store, mano dir)."""
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=4, serials=(0,), frames=max(1, math.ceil(records / 4)))
    write_toy_dexycb(root, mano, models, size, workers=workers, progress=False)
    cfg = load_build_config("toy", ['dataset.splits=["train"]', "record.crop_size=512", "store.records_per_shard=8"])
    build_store(cfg, root, mano, models, work / "store", workers=workers, progress=False)
    return work / "store", mano


def store_and_mano(args, work: Path, records: int) -> tuple[Path, Path]:
    """``args.store`` / ``args.mano``, or a toy store and the toy MANO written into ``work``."""
    if args.store is None:
        store, mano = toy_store(work, records, workers=min(4, os.cpu_count() or 1))
        return store, Path(args.mano) if args.mano else mano
    if args.mano:
        return Path(args.store), Path(args.mano)
    from hoidata.toy.hand import write_toy_mano

    write_toy_mano(work / "mano")
    return Path(args.store), work / "mano"


def test_inputs(batch: dict, config, device: torch.device) -> dict:
    """A loader batch -> the network's test-time input on ``device`` (no SDF rows: nothing but inference)."""
    from hoisdf.data.augment import augment_batch
    from hoisdf.training.trainer import to_device

    keep = {k: v for k, v in batch.items() if not k.endswith(("_points", "_sdf", "_rows"))}
    return augment_batch(to_device(keep, device), config.augment, None, train=False)


def sdf_toy_frames(workdir: str, n_frames: int) -> list[dict]:
    """bench_sdf's frames (and bench_scaling's), written under ``workdir``. Frame k: the closed toy MANO hand at
    curl CURLS[k % 5] with a random rotation, toy object k % 5 beside it; camera frame, metres."""
    write_toy_mano(workdir)
    mano = load_mano(workdir, dtype=torch.float64)
    objects = [repair_mesh(load_object_mesh(p)) for p in write_toy_objects(f"{workdir}/models")]
    frames = []
    for k in range(n_frames):
        pose = torch.zeros(1, 48, dtype=torch.float64)
        pose[0, :3] = torch.as_tensor(Rotation.random(random_state=k).as_rotvec())
        pose[0, 3:] = mano.hands_mean * CURLS[k % len(CURLS)]
        out = mano(pose, transl=torch.as_tensor(CAMERA_T)[None])
        hand = mano.close(out.vertices)[0].numpy()
        mesh, report = objects[k % len(objects)]
        rot = Rotation.random(random_state=100 + k).as_matrix()
        offset = Rotation.random(random_state=200 + k).apply([0.05, 0.0, 0.0])
        obj = np.asarray(mesh.vertices) @ rot.T + hand.mean(0) + offset
        frames.append(dict(name=f"curl {CURLS[k % len(CURLS)]:.1f} + {list(TOY_OBJECTS)[k % len(objects)]}",
                           hand=hand, hand_faces=np.asarray(mano.closed_faces), parts=mano.closed_face_parts,
                           root=out.joints[0, 0].numpy(), obj=obj, obj_faces=np.asarray(mesh.faces),
                           watertight=report.watertight))
    return frames
