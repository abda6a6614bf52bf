"""``hoidata render-synthetic``: perturbed grasps rendered from new views, into a normal training store.

Sample i of a run with seed S is drawn from its own generator ``default_rng([S, i])``: a source grasp,
per-joint pose noise and hand translation noise (redrawn until the grasp passes the physical check:
penetration <= 2 mm and some hand vertex within 5 mm of the object, checked with python-fcl and exact
signed distances), a view over the sphere at 0.45-0.55 m with HO-3D-like intrinsics, skin tone,
lights, background, blur and noise. Each sample then becomes a record exactly as ``build-sdf`` makes
them (crop, masks, heatmap, SDF samples, labels; ``dataset: synthetic`` with the source grasp in
``source``), written by the same shard engine (:mod:`hoidata.engine.engine`, with :class:`SynthTask` and a
:class:`SynthWorker` per process): parallel, byte-identical whatever the number of workers, resumable,
splittable with ``--part``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from hoidata import schema
from hoidata.datasets.frame import Frame, Skip
from hoidata.engine import Plan, RunSummary, run_task
from hoidata.errors import DataError
from hoidata.geometry.crop import project
from hoidata.hand.pose import change_frame
from hoidata.records import (
    RecordSettings,
    RecordWorker,
    ShardJob,
    StoreTask,
    StoreWriter,
    extra_name,
    fingerprint,
    read_shard_skips,
)
from hoidata.synth import views

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
MAX_COUNT = 10_000_000  # samples of one run: its key list (~0.9 GB at the bound) is made before any rendering


@dataclass(frozen=True)
class SynthSettings:
    distance: tuple[float, float] = (0.45, 0.55)  # metres from the camera to the hand-object centre
    angle_sigma: float = 0.1  # rad, per finger joint
    transl_sigma: float = 0.003  # metres, per axis
    max_penetration: float = 0.002  # metres
    contact_distance: float = 0.005  # metres: some hand vertex must be this close to the object
    max_tries: int = 20  # perturbations tried per sample before the sample is skipped
    blur_sigma: float = 1.0  # max Gaussian blur, pixels
    noise_sigma: float = 4.0  # max pixel noise, grey levels


class Rejected(Exception):
    """No perturbation of the drawn grasp passed the physical check."""


@dataclass(frozen=True)
class SynthWorkerSpec:
    """What a worker process needs to render samples (picklable: the engine sends it to every worker)."""

    mano_dir: Path
    models_dir: Path
    source: Path  # the store or dataset the grasps come from
    backgrounds: tuple[str, ...]  # background image files, sorted (none: procedural backgrounds)
    crop_size: int  # px of the records

    def open(self) -> SynthWorker:
        return SynthWorker(self)


class SynthWorker:
    """One process's renderer, right MANO layer (HO-3D tips), grasps and per-object caches, and the
    :class:`RecordWorker` that turns the rendered samples into records; the engine's worker context."""

    def __init__(self, spec: SynthWorkerSpec):
        from hoidata.hand import load_mano
        from hoidata.render import Renderer
        from hoidata.synth.source import load_grasps

        self.records = RecordWorker(spec.mano_dir, spec.models_dir, spec.crop_size)
        self.rgb = None
        try:
            self.mano = load_mano(spec.mano_dir, side="right", tips="ho3d", dtype=torch.float64)
            self.backgrounds = list(spec.backgrounds)
            self.collision = {}
            self.rgb = Renderer(*views.HO3D_SIZE)
            self.grasps = load_grasps(spec.source, self.mano, spec.mano_dir, spec.models_dir)  # as the parent's
        except BaseException:
            self.close()
            raise

    def object(self, name: str):
        """Repaired geometry (SDF, physics), textured mesh (render) and an fcl collision model, cached."""
        from hoidata.synth.contact import HandObjectCollision

        asset = self.records.object_asset(name)
        if name not in self.collision:
            self.collision[name] = HandObjectCollision(asset.vertices, asset.faces)
        return asset, self.records.object_mesh(name), self.collision[name]

    def hand(self, pose, betas, transl):
        """MANO's output and the closed hand vertices (779, 3) of a pose, betas and translation (metres)."""
        with torch.no_grad():
            out = self.mano(torch.as_tensor(pose)[None], torch.as_tensor(betas)[None], torch.as_tensor(transl)[None])
        return out, self.mano.close(out.vertices)[0].double().numpy()

    def run(self, job: SynthJob) -> tuple[int, int, list]:
        """Render one shard's samples and write them as records; returns (number, records, skips)."""
        frames, kept, rejected, attempts = [], [], [], 0
        for index, key in zip(job.indices, job.keys):
            try:
                frame, n = make_sample(self, index, job.seed, job.settings)
                frames.append(frame)
                kept.append(key)
                attempts += n
            except Rejected as e:
                attempts += job.settings.max_tries
                rejected.append({"frame_id": f"{job.seed}_{index:08d}", "reason": str(e), "path": ""})
        stats = {"attempts": attempts, "accepted": len(frames), "rejected_samples": rejected}
        result = self.records.run(ShardJob(job.number, frames, kept, job.record, job.out, extra={"synthetic": stats}))
        return result[0], result[1], result[2] + rejected

    def close(self) -> None:
        if self.rgb is not None:
            self.rgb.close()
            self.rgb = None
        self.records.close()


def perturbed_grasp(worker: SynthWorker, grasp, asset, collision, rng, s: SynthSettings):
    """(pose, transl, hand output, attempts) of the first perturbation that passes the physical check."""
    from hoidata.synth.contact import penetration_depth

    for attempt in range(1, s.max_tries + 1):
        pose = views.perturb_pose(grasp.pose, rng, s.angle_sigma)
        transl = grasp.transl + rng.normal(0.0, s.transl_sigma, 3)
        out, closed = worker.hand(pose, grasp.betas, transl)
        depth = penetration_depth(closed, asset.vertices, asset.faces, hand_faces=worker.mano.closed_faces)
        touching = len(collision.contact_vertices(closed[:-1], within=s.contact_distance)) > 0
        if depth <= s.max_penetration and touching:
            return pose, transl, out, attempt
    raise Rejected(f"no perturbation of grasp {grasp.key} passed the physical check in {s.max_tries} tries")


def _finish_image(rgb: np.ndarray, rng, s: SynthSettings) -> np.ndarray:
    import cv2

    sigma = rng.uniform(0.0, s.blur_sigma)
    img = cv2.GaussianBlur(rgb, (0, 0), sigma) if sigma > 0.2 else rgb
    noisy = img.astype(np.float32) + rng.normal(0.0, rng.uniform(0.0, s.noise_sigma), img.shape).astype(np.float32)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def make_sample(worker: SynthWorker, index: int, seed: int, s: SynthSettings) -> tuple[Frame, int]:
    """Sample `index` of run `seed` as a Frame holding its rendered image, and the attempts it took (``worker``:
    the process's renderer, hand model, grasps and objects)."""
    from hoidata.render import (
        RenderMesh,
        load_background,
        procedural_background,
        random_lighting,
        skin_tone,
    )

    rng = np.random.default_rng([seed, index])
    grasp = worker.grasps[int(rng.integers(len(worker.grasps)))]
    asset, textured, collision = worker.object(grasp.object_name)
    pose, transl, out, attempts = perturbed_grasp(worker, grasp, asset, collision, rng, s)
    rot = views.sample_view_rotation(rng)
    box_centre = 0.5 * (asset.vertices.min(0) + asset.vertices.max(0))
    centre = 0.5 * (box_centre + out.joints[0, 9].double().numpy())  # object centre and middle knuckle
    trans = views.place_on_axis(rot, centre, rng.uniform(*s.distance))
    obj_pose = np.eye(4)
    obj_pose[:3, :3], obj_pose[:3, 3] = rot, trans
    wrist = worker.mano.rest_wrist(grasp.betas)
    pose_c, transl_c = change_frame(pose, transl, wrist, rot, trans)
    out_c, closed_c = worker.hand(pose_c, grasp.betas, transl_c)
    K = views.ho3d_intrinsics(rng)
    w, h = views.HO3D_SIZE
    files = worker.backgrounds
    background = load_background(files[int(rng.integers(len(files)))], w, h, rng) if files else procedural_background(rng, w, h)
    meshes = [RenderMesh(vertices=closed_c, faces=worker.mano.closed_faces, color=skin_tone(rng), label=1),
              RenderMesh.from_trimesh(textured, transform=obj_pose, label=2)]
    result = worker.rgb.render(K, meshes, background=background, lighting=random_lighting(rng, scene_depth=trans[2]))
    joints = out_c.joints[0].double().numpy()
    frame = Frame(dataset="synthetic", split="train", frame_id=f"{seed}_{index:08d}", image_path=Path(f"render-{index}"),
                  image_size=(w, h), K=K, side="right", root_3d=joints[0], object_name=grasp.object_name,
                  object_id=grasp.object_id, object_pose=obj_pose, mano_pose=pose_c, mano_betas=grasp.betas,
                  mano_transl=transl_c, joints_3d=joints, joints_2d=project(joints, K), tip_convention="ho3d",
                  source={"synthetic": True, "source_grasp": grasp.key, "seed": seed, "index": index,
                          "attempts": attempts}, image=_finish_image(result.rgb, rng, s), labels=result.labels)
    return frame, attempts


def list_backgrounds(folder: Path | None) -> list[str]:
    """Image files of a backgrounds folder, sorted (so a seed means the same thing on every machine)."""
    if folder is None:
        return []
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, None, "backgrounds folder not found")
    files = sorted(str(p) for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise DataError(folder, None, f"no images ({', '.join(IMAGE_SUFFIXES)}) in the backgrounds folder")
    return files


def check_count(count: int) -> None:
    """``--count`` within 1 .. MAX_COUNT, checked before the key list and the shard plan are allocated."""
    if not 1 <= count <= MAX_COUNT:
        raise ValueError(f"--count must be between 1 and {MAX_COUNT:,}, got {count:,}; render more as several "
                         "stores (another --seed each) and train on all of them (--shards A B)")


def default_count(grasps: list) -> int:
    """``--count`` when it is not given: one render per grasp of the source, so that the renders and the store they
    were drawn from mix 1:1 at weight 1 each (the paper does not say how many it rendered; docs/synthetic.md)."""
    return min(len(grasps), MAX_COUNT)


@dataclass
class SynthJob:
    """One shard to render: its sample indices and keys, the run's seed and settings, the store folder."""

    number: int
    indices: list[int]
    keys: list[str]
    seed: int
    settings: SynthSettings
    record: RecordSettings
    out: Path


@dataclass
class SynthTask(StoreTask):
    """render-synthetic's task for :func:`hoidata.engine.run_task`: shard n holds samples n*R .. (n+1)*R-1."""

    keys: list[str]
    seed: int
    settings: SynthSettings
    record: RecordSettings
    store: StoreWriter
    worker: SynthWorkerSpec
    plan: Plan
    desc: str = "render-synthetic"

    def job(self, number: int) -> SynthJob:
        indices = list(range(number * self.plan.per, number * self.plan.per + self.plan.size(number)))
        return SynthJob(number, indices, [self.keys[i] for i in indices], self.seed, self.settings, self.record,
                        self.store.out)


def render_synthetic(source: Path, out: Path, count: int | None, mano_dir: Path, models_dir: Path, seed: int = 0,
                     backgrounds: Path | None = None, workers: int = 1, part: tuple[int, int] = (0, 1),
                     settings: SynthSettings = SynthSettings(), record: RecordSettings = RecordSettings(),
                     records_per_shard: int = 256, progress: bool = True, executor=None,
                     inputs: dict | None = None) -> RunSummary:
    """Render `count` synthetic samples (None: one per grasp of the source, :func:`default_count`) from the grasps
    of `source` into the store `out` (``executor``: what runs the shard jobs, see :func:`hoidata.engine.run_task`;
    ``inputs``: where the inputs came from, recorded in the index, :mod:`hoidata.provenance`); the summary
    counts samples (items) and shards (units)."""
    import time

    from hoidata.hand import load_mano
    from hoidata.synth.source import load_grasps

    start = time.perf_counter()
    out, source = Path(out), Path(source)
    if count is not None:
        check_count(count)
    files = list_backgrounds(backgrounds)
    if records_per_shard < 1:
        raise ValueError(f"--records-per-shard must be at least 1, got {records_per_shard}")
    # fail early, in the parent; the grasps are picked with the MANO and models that render them (as in the workers)
    grasps = load_grasps(source, load_mano(mano_dir, dtype=torch.float64), Path(mano_dir), Path(models_dir))
    if count is None:
        count = default_count(grasps)
        print(f"count = {count} (default: one render per right-hand grasp of the source)", flush=True)
    keys = [schema.record_key("synthetic", "train", f"{seed}_{i:08d}") for i in range(count)]
    # the source resolved: a resume with --source spelled another way (relative, absolute, a link) is the same run
    config = {"synthetic": asdict(settings), "record": asdict(record), "source": str(source.resolve()), "count": count,
              "seed": seed, "backgrounds": [Path(f).name for f in files], "records_per_shard": records_per_shard}
    writer = StoreWriter(out, config, Path(models_dir), inputs=inputs)
    writer.pin(keys, _inputs(grasps, mano_dir, models_dir, files))
    spec = SynthWorkerSpec(Path(mano_dir), Path(models_dir), source, tuple(files), record.crop_size)
    summary = run_task(SynthTask(keys, seed, settings, record, writer, spec, Plan(count, records_per_shard)), workers,
                       part, progress, executor)
    rejected, provenance = [], None
    if summary.all_done:
        stats = [_shard_stats(out, n) for n in summary.units]
        attempts = sum(st["attempts"] for st in stats)
        accepted = sum(st["accepted"] for st in stats)
        provenance = {**_source_dataset(source),
                      "synthetic": {"source_grasps": len(grasps), "attempts": attempts, "accepted": accepted,
                                    "rejection_rate": round(1.0 - accepted / attempts, 4) if attempts else 0.0}}
        rejected = [Skip(r["frame_id"], r["reason"], r["path"]) for st in stats for r in st["rejected_samples"]]
    writer.finish(summary, rejected, provenance)
    summary.seconds = time.perf_counter() - start
    return summary


def _source_dataset(source: Path) -> dict:
    """``{"source_dataset": id}`` of the grasps' source for the store's card (:mod:`hoidata.store.sources`): a store's
    own, "toy" for a folder make-toy wrote, nothing for another dataset folder (the card then says it is not
    recorded)."""
    from hoidata.store import INDEX_NAME, read_index
    from hoidata.store.sources import TOY_MARKER, source_of

    if (source / INDEX_NAME).is_dir():
        index = read_index(source)
        return {"source_dataset": source_of(index.config, index.provenance)}
    return {"source_dataset": "toy"} if (source / TOY_MARKER).is_file() else {}


def _shard_stats(out: Path, number: int) -> dict:
    """The physical-check statistics a shard's skips file holds."""
    stats = read_shard_skips(out, number).get("synthetic")
    if not isinstance(stats, dict) or not {"attempts", "accepted", "rejected_samples"} <= set(stats):
        raise DataError(out / extra_name(number), "synthetic", "missing; rerun render-synthetic to rebuild it")
    return stats


def _inputs(grasps, mano_dir: Path, models_dir: Path, backgrounds: list[str]) -> dict:
    """What build.json pins besides the settings: the MANO file, the rendered object folders, the grasps and
    the background images (see hoidata.records.fingerprint)."""
    import hashlib

    digest = hashlib.sha256()
    for g in grasps:
        digest.update(f"{g.key}|{g.object_name}|{g.object_id}|".encode())
        digest.update(np.concatenate([g.pose, g.betas, g.transl]).astype(np.float64).tobytes())
    return {"mano": fingerprint.files(mano_dir, fingerprint.MANO_FILES[:1]),
            "models": fingerprint.models(models_dir, {g.object_name for g in grasps}, whole_folder=True),
            "grasps": digest.hexdigest(),
            "backgrounds": {Path(f).name: fingerprint.file_sha256(Path(f)) for f in backgrounds}}
