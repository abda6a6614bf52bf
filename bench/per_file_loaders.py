"""The two per-file baselines of bench_loader.py: one folder per kind of file, one file per frame, a map-style
``torch.utils.data.Dataset`` that opens and decodes the files of an item in the worker.

``SameCropsDataset`` reads the store's own pre-cut members as separate files (``rgb/<key>.jpg`` the 512 px crop,
``seg/<key>.png`` the packed masks, ``sdf/<key>.npz`` the store's SDF rows as float32 columns, ``meta/<key>.pkl``
the labels) and gives the tensors our loader gave before issue 17's batch layout (float32 image, four bool mask
planes), value for value: it isolates the container (per-file reads vs tar shards) and the decode path.

``UpstreamDataset`` does the work the upstream code bases do per item (read with the search tools:
``amathislab/HOISDF`` ``data/dexycb.py`` ``Dataset.__getitem__``, ``zerchen/gSDF`` ``datasets/sdf_dataset.py``
``SDFDataset.__getitem__`` and ``unpack_sdf``): the original 640x480 frame (``rgb/<key>.jpg``, DexYCB's
``color_*.jpg``) decoded and cut to the crop with an affine warp in the worker; the dataset's label map
(``labels/<key>.npz``, DexYCB's ``labels_*.npz``: hand 255, object its class id) for the hand and object masks,
each warped (nearest) to the mask resolution; AlignSDF's SDF files (``sdf_hand/``, ``sdf_obj/``, ``norm/<key>.npz``
as ``hoidata export --format gsdf`` writes them: 20,000 rows per mesh split into ``pos`` / ``neg`` with the other
mesh's distance and the part labels) unpacked as gSDF does (NaN rows dropped, rows beyond 2 normalised units
dropped, de-normalised to metres) and drawn as HOISDF does (rows without replacement, "pre" rows within
``near`` of the surface); the labels from a per-frame pickle (``meta/<key>.pkl``); the image converted to float32
in the worker (upstream's ToTensor). Same keys, shapes and dtypes as SameCropsDataset; the values differ where
the source differs: the image is the crop of the original JPEG (ours: the JPEG of the crop), the masks are the
dataset's visible masks (ours: rendered, with amodal planes; the dataset has none, so its visible planes
stand in), the SDF points come from AlignSDF-sized pools. Upstream's augmentation (also in the worker there) is
left out of both baselines: ours runs it on the device, so leaving it out can only favour the baselines.
"""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch

from hoidata import schema
from hoidata.export.gsdf import file_name
from hoidata.geometry import crop as crop_ops
from hoidata.store import decode_record, read_shard_members
from hoisdf.data.loader import _key_seed, crop_entries, sample_sdf_arrays

LABEL_FIELDS = ("K", "hand_root", "joints_3d", "joints_2d", "mano_pose", "mano_betas", "object_pose", "hand_box",
                "object_box")
HAND_LABEL = 255  # DexYCB's label maps: the hand is 255, an object its YCB class id


def store_records(store: Path):
    """(members, decoded record) of every record of a store, in shard order."""
    for shard in sorted(store.glob("shard-*.tar")):
        for members in read_shard_members(shard):
            yield members, decode_record(members, str(shard))


def _labels(meta: dict, key: str) -> dict:
    out = {name: np.asarray(meta[name], dtype=np.float32) for name in LABEL_FIELDS}
    out.update(crop_entries(meta), object_id=np.int64(meta["object_id"]), mirrored=np.bool_(meta["mirrored"]),
               is_synthetic=np.bool_(meta["dataset"] == "synthetic"), key=key)
    return out


def _float_chw(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32) / 255.0


class PerFileDataset(torch.utils.data.Dataset):
    """Common part: the keys, the folder, the SDF draw sizes and the per-key seeded generator (as ours)."""

    def __init__(self, root: Path, keys: list[str], n_hand: int, n_object: int, near: float, seed: int = 0):
        self.root, self.keys = Path(root), list(keys)
        self.n_hand, self.n_object, self.near, self.seed = n_hand, n_object, near, seed

    def __len__(self) -> int:
        return len(self.keys)

    def rng(self, key: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, 0, _key_seed(key)])


class SameCropsDataset(PerFileDataset):
    """The store's pre-cut members as per-frame files (see the module docstring)."""

    @staticmethod
    def export(store: Path, out: Path) -> list[str]:
        """Write every record of ``store`` as per-frame files under ``out``; returns the keys in store order."""
        for kind in ("rgb", "seg", "sdf", "meta"):
            (out / kind).mkdir(parents=True, exist_ok=True)
        keys = []
        for members, rec in store_records(store):
            key = rec["__key__"]
            (out / "rgb" / f"{key}.jpg").write_bytes(members[schema.IMG])
            (out / "seg" / f"{key}.png").write_bytes(members[schema.SEG])
            xyz, sdf_hand, sdf_obj, part = schema.dequantize_sdf(rec[schema.SDF])
            np.savez(out / "sdf" / f"{key}.npz", xyz=xyz, sdf_hand=sdf_hand, sdf_obj=sdf_obj, part=part)
            with open(out / "meta" / f"{key}.pkl", "wb") as f:
                pickle.dump(rec[schema.META], f)
            keys.append(key)
        return keys

    def __getitem__(self, i: int) -> dict:
        key, root = self.keys[i], self.root
        img = cv2.imread(str(root / "rgb" / f"{key}.jpg"), cv2.IMREAD_COLOR)[:, :, ::-1]
        seg = cv2.imread(str(root / "seg" / f"{key}.png"), cv2.IMREAD_UNCHANGED)
        with np.load(root / "sdf" / f"{key}.npz") as z:
            xyz, sdf_hand, sdf_obj = z["xyz"], z["sdf_hand"], z["sdf_obj"]
        with open(root / "meta" / f"{key}.pkl", "rb") as f:
            meta = pickle.load(f)
        out = sample_sdf_arrays(xyz, sdf_hand, sdf_obj, meta["sdf_counts"], self.rng(key), self.n_hand,
                                self.n_object, self.near)
        out.update(_labels(meta, key), img=_float_chw(img),
                   seg=((seg[None] >> np.arange(4, dtype=np.uint8)[:, None, None]) & 1).astype(bool))
        return out


class UpstreamDataset(PerFileDataset):
    """Original frames, label maps, AlignSDF files and pickles, cut and unpacked per item (module docstring)."""

    def __init__(self, root: Path, keys: list[str], n_hand: int, n_object: int, near: float, crop_size: int,
                 seed: int = 0):
        super().__init__(root, keys, n_hand, n_object, near, seed)
        self.crop_size = crop_size  # the store's crop side: the baseline cuts the same crop

    @staticmethod
    def export(store: Path, dataset_root: Path, gsdf_export: Path, out: Path) -> list[str]:
        """Per-frame files for the records of ``store`` from their dataset folder ``dataset_root`` (the frame and
        its label map, named in the records' ``source`` relative to that folder, as build-sdf stores them) and a
        ``hoidata export --format gsdf`` of the same frames (its SDF files); returns the keys in store order."""
        for kind in ("rgb", "labels", "sdf_hand", "sdf_obj", "norm", "meta"):
            (out / kind).mkdir(parents=True, exist_ok=True)
        keys, sdf_data = [], gsdf_export / "data" / "sdf_data"
        for _, rec in store_records(store):
            key, meta = rec["__key__"], rec[schema.META]
            labels = Path(dataset_root) / meta["source"]["labels"]  # an absolute stored path stays as it is
            frame = labels.parent / labels.name.replace("labels_", "color_").replace(".npz", ".jpg")
            shutil.copyfile(frame, out / "rgb" / f"{key}.jpg")
            shutil.copyfile(labels, out / "labels" / f"{key}.npz")
            name = file_name(SimpleNamespace(source=meta["source"]))
            for kind in ("sdf_hand", "sdf_obj", "norm"):
                shutil.copyfile(sdf_data / kind / f"{name}.npz", out / kind / f"{key}.npz")
            with open(out / "meta" / f"{key}.pkl", "wb") as f:
                pickle.dump(meta, f)
            keys.append(key)
        return keys

    def _unpack(self, kind: str, hand: bool, scale: float, offset: np.ndarray) -> np.ndarray:
        """(N, 5) float32 rows [x, y, z (camera frame, m), hand sdf, object sdf (m)] of one AlignSDF file."""
        with np.load(self.root / kind) as npz:
            blocks = []
            for sign in ("pos", "neg"):
                rows, other = npz[sign], npz[f"{sign}_other"]
                _ = npz[f"lab_{sign}" if hand else f"lab_{sign}_other"]  # read as gSDF does (labels unused here)
                keep = ~np.isnan(rows[:, 3])
                rows, other = rows[keep], other[keep]
                cols = [rows, other] if hand else [rows[:, :3], other, rows[:, 3:4]]
                blocks.append(np.concatenate(cols, 1))
        rows = np.concatenate(blocks)
        rows = rows[(np.abs(rows[:, 3]) < 2.0) & (np.abs(rows[:, 4]) < 2.0)]
        rows[:, :3] = rows[:, :3] / scale - offset
        rows[:, 3:] /= scale
        return rows

    def _draw(self, rows: np.ndarray, column: int, n: int, rng: np.random.Generator, prefix: str) -> dict:
        out = {}
        near = np.flatnonzero(np.abs(rows[:, column]) < self.near)
        for name, pool in ((prefix, np.arange(len(rows))), (f"{prefix}_near", near if len(near) else None)):
            pool = np.argsort(np.abs(rows[:, column]))[:n] if pool is None else pool
            idx = rng.choice(pool, size=n, replace=len(pool) < n)
            out[f"{name}_points"], out[f"{name}_sdf"] = rows[idx, :3], rows[idx, column]
            out[f"{name}_rows"] = idx.astype(np.int64)
        return out

    def __getitem__(self, i: int) -> dict:
        key, root = self.keys[i], self.root
        with open(root / "meta" / f"{key}.pkl", "rb") as f:
            meta = pickle.load(f)
        x1, y1, x2, _ = np.asarray(meta["crop_box"], dtype=np.float64)
        size = self.crop_size
        to_crop = crop_ops.crop_affine((x1, y1, x2 - x1), size)
        frame = cv2.cvtColor(cv2.imread(str(root / "rgb" / f"{key}.jpg"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        img = crop_ops.warp_image(frame, to_crop, size)
        with np.load(root / "labels" / f"{key}.npz") as npz:
            label_map = npz["seg"]
        to_mask = crop_ops.resize_affine(size, size // 2) @ to_crop
        hand, obj = (crop_ops.warp_image((label_map == v).astype(np.uint8), to_mask, size // 2, nearest=True) > 0
                     for v in (HAND_LABEL, meta["object_id"]))
        with np.load(root / "norm" / f"{key}.npz") as npz:
            scale, offset = float(npz["scale"][0]), npz["offset"].astype(np.float32)
        root_3d = np.asarray(meta["hand_root"], dtype=np.float32)
        rng = self.rng(key)
        out = {}
        for kind, hand_file, column, n, prefix in (("sdf_hand", True, 3, self.n_hand, "hand"),
                                                   ("sdf_obj", False, 4, self.n_object, "obj")):
            rows = self._unpack(f"{kind}/{key}.npz", hand_file, scale, offset)
            rows[:, :3] -= root_3d
            out.update(self._draw(rows, column, n, rng, prefix))
        out.update(_labels(meta, key), img=_float_chw(img), seg=np.stack([hand, obj, hand, obj]))
        return out
