"""gSDF's DexYCB files (its ``datasets/dexycb/`` folder), with AlignSDF's per-frame SDF files.

Layout, as ``zerchen/gSDF:datasets/dexycb/dexycb.py`` (class ``dexycb``, ``load_data``) and
``datasets/sdf_dataset.py`` (class ``SDFDataset``) read it::

    OUT/dexycb_train_s0.json, dexycb_test_s0.json     COCO annotations ('dexycb_' + stage split)
    OUT/splits/train_s0_29k.json, test_s0_5k.json     the ids, 8-digit strings; named <split>_<setup>_<n // 1000>k
                                                      (the config's trainset_3d_split / testset_split)
    OUT/data/sdf_data/{sdf_hand,sdf_obj,norm}/<name>.npz   train frames (:mod:`hoidata.export.sdf_files`)
    OUT/data/mesh_data/{mesh_hand,mesh_obj}/<name>.obj     test frames: the ground-truth meshes tools/eval.py loads
    OUT/data/<subject>, OUT/data/models               -> the DexYCB folders (links): images and labels by name

``<name>`` = ``'{subject number}_{sequence}_{serial}_{frame}'`` unpadded (``1_20200709_141754_836212060125_30``),
from which the loader rebuilds the image path. The annotation fields (all read with ``ann[...]`` on every
split) are those ``preprocess/cocoify_dexycb.py`` (``preprocess``) writes: fx, fy, cx, cy; hand_joints_3d
(21, 3) m; hand_poses (48) the *absolute* axis-angle (hands_mean included: manopth's ``th_full_pose``, which is
our flat-hand-mean pose); hand_trans (3) MANO's translation; hand_shapes (10); ycb_id; obj_transform (4, 4),
obj_center_3d (3), obj_corners_3d (8, 3) and obj_rest_corners_3d (8, 3) in the frame of the object's
bounding-box centre c (``[R | R c + t]``, corners in trimesh.bounds.corners order); bbox (x, y, w, h): the box
of the 2D joints and the projected corners, padded 10 px, squared and scaled 1.25; train also sdf_scale (1)
and sdf_offset (3), the frame's ``norm`` file. gSDF sets ``hand_side = 1``: right hands only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hoidata.export import sdf_files
from hoidata.export.files import link, write_coco, write_json, write_npz, write_obj

# trimesh.bounds.corners order over (min, max) per axis
_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])


def file_name(frame) -> str:
    """gSDF's sample name ``'{subject number}_{sequence}_{serial}_{frame}'`` (no zero padding)."""
    src = frame.source
    return f"{int(src['subject'].split('-')[-1])}_{src['sequence']}_{src['serial']}_{int(src['frame'])}"


def box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of an axis-aligned box, in trimesh.bounds.corners order."""
    return np.where(_CORNERS == 0, lo, hi).astype(np.float64)


def gsdf_bbox(joints_2d: np.ndarray, corners_2d: np.ndarray) -> list[float]:
    """gSDF's crop box (x, y, w, h) pixels: min/max of both point sets, padded 10 px, then its
    ``process_bbox``: squared about the centre and scaled 1.25 (no clipping to the image)."""
    pts = np.concatenate([joints_2d, corners_2d])
    tl, br = pts.min(0), pts.max(0)
    x, y = tl - 10
    w, h = br - tl + 20
    cx, cy = x + w / 2.0, y + h / 2.0
    w = h = max(w, h)
    w, h = w * 1.25, h * 1.25
    return [float(cx - w / 2.0), float(cy - h / 2.0), float(w), float(h)]


def annotation(frame, ident: int, raw_vertices: np.ndarray) -> dict:
    """The COCO annotation of one frame (without the SDF normalisation, see :func:`frame_entry`)."""
    K, pose = np.asarray(frame.K, float), np.asarray(frame.object_pose, float)
    R, t = pose[:3, :3], pose[:3, 3]
    lo, hi = raw_vertices.min(0), raw_vertices.max(0)
    c = (lo + hi) / 2.0
    rest = box_corners(lo, hi) - c
    centre = R @ c + t
    corners = rest @ R.T + centre
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = R, centre
    corners_2d = corners[:, :2] / corners[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return {"id": ident, "image_id": ident, "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
            "cy": float(K[1, 2]), "hand_joints_3d": np.asarray(frame.joints_3d, float).tolist(),
            "hand_poses": np.asarray(frame.mano_pose, float).tolist(),
            "hand_trans": np.asarray(frame.mano_transl, float).tolist(),
            "hand_shapes": np.asarray(frame.mano_betas, float).tolist(), "ycb_id": int(frame.object_id),
            "obj_transform": transform.tolist(), "obj_center_3d": centre.tolist(), "obj_corners_3d": corners.tolist(),
            "obj_rest_corners_3d": rest.tolist(), "bbox": gsdf_bbox(np.asarray(frame.joints_2d, float), corners_2d)}


def check_store_inputs(store: Path, inputs: dict) -> None:
    """Refuse a ``--store`` built from other inputs than the export's (``inputs``: MANO and model fingerprints,
    as :func:`hoidata.records.build_inputs` gives them): its SDF rows are distances to its own meshes.

    The store's ``build.json`` must hold input fingerprints; every MANO file and every object model both
    fingerprint must be the same file. Frames are compared one by one when rows are re-used (:func:`_store_fits`:
    key, mirroring, hand and object pose). The sampling settings need not match: each row is the exact distance
    at its own point. A mismatch is one DataError naming the input, before anything is written.
    """
    from hoidata.errors import DataError
    from hoidata.reading import read_json

    path = Path(store) / "build.json"
    built = read_json(path, "store build file", "export without --store, or rebuild the store")
    theirs = built.get("inputs") if isinstance(built, dict) else None
    if not isinstance(theirs, dict) or not isinstance(theirs.get("mano"), dict):
        raise DataError(path, "inputs", "no input fingerprints (a store of an older hoidata, or not a build-sdf "
                                        "store): its SDF rows cannot be checked against this export's inputs")
    for kind, words, option in (("mano", "MANO file", "--mano"), ("models", "object model", "--models")):
        ours, stored = inputs.get(kind, {}), theirs.get(kind) or {}
        for name in sorted(set(ours) & set(stored)):
            if ours[name] != stored[name]:
                raise DataError(path, f"inputs.{kind}.{name}", f"the store was built from another {words} {name} "
                                f"than this export's {option}; its SDF rows would be distances to other meshes "
                                "(rebuild the store from these inputs, or export without --store)")


def _store_fits(record: dict | None, frame, key: str) -> bool:
    """A store record's SDF rows are this frame's: same key, not mirrored, same hand and object pose."""
    if record is None:
        return False
    meta = record["meta"]
    same = [np.allclose(meta[k], v, rtol=0, atol=1e-9) for k, v in
            (("hand_root", frame.root_3d), ("mano_pose", frame.mano_pose), ("mano_betas", frame.mano_betas),
             ("mano_transl", frame.mano_transl), ("object_pose", frame.object_pose))]
    return meta.get("key") == key and not meta.get("mirrored") and all(same)


def sdf_arrays(worker, frame, key: str) -> tuple[dict, str]:
    """The three SDF files of one frame and where their rows came from ('store' or 'sampled'); ``worker``: the
    process's :class:`~hoidata.export.worker.ExportWorker` (MANO layers, objects, the store's rows)."""
    from hoidata.records import frame_seed, posed_hand, posed_object

    mano = worker.mano(frame.side, frame.fix_left_shapedirs)
    hand, hand_faces = posed_hand(frame, mano), mano.closed_faces
    asset = worker.object_asset(frame.object_name)
    obj, obj_faces, _ = posed_object(frame, asset)
    offset, scale = sdf_files.normalisation(hand, obj)
    record = worker.store_record(key)
    if _store_fits(record, frame, key):
        rows_h, rows_o = sdf_files.store_rows(record["sdf"], record["meta"]["sdf_counts"], frame.root_3d)
        pts_h, pts_o = rows_h[:, :3], rows_o[:, :3]
        d_h, d_o = rows_h[:, 3:5].T, rows_o[:, 3:5].T
        face_h, face_o = (sdf_files.closest_faces(p, hand, hand_faces) for p in (pts_h, pts_o))
        source = "store"
    else:
        rng = np.random.default_rng(frame_seed(key + "/gsdf"))
        pts_h, pts_o = sdf_files.alignsdf_points(hand, hand_faces, obj, obj_faces, offset, scale, rng)
        sdf_h, sdf_o, faces = sdf_files.exact_distances(np.concatenate([pts_h, pts_o]), hand, hand_faces, obj,
                                                        obj_faces, asset.watertight)
        n = len(pts_h)
        d_h, d_o = np.stack([sdf_h[:n], sdf_o[:n]]), np.stack([sdf_h[n:], sdf_o[n:]])
        face_h, face_o = faces[:n], faces[n:]
        source = "sampled"
    n_open = len(mano.faces)
    labels = [sdf_files.hand_labels(f, mano.closed_face_parts, n_open) for f in (face_h, face_o)]
    return sdf_files.frame_files(pts_h, pts_o, d_h, d_o, labels[0], labels[1], offset, scale), source


def frame_entry(worker, frame, ident: int, key: str, out: Path, opts: dict) -> dict:
    """One frame's annotation, and its files: the SDF files for train, the ground-truth meshes otherwise
    (``worker``: the process's :class:`~hoidata.export.worker.ExportWorker`)."""
    from hoidata.records import posed_hand

    if frame.side != "right" or frame.mirror:
        raise ValueError("gSDF reads right hands only (its dexycb dataset sets hand_side = 1)")
    raw_v, raw_f = worker.raw_object(frame.object_name)
    name = file_name(frame)
    ann = annotation(frame, ident, raw_v)
    entry = {"split": frame.split, "image": {"id": ident, "file_name": name}, "annotation": ann, "files": []}
    if frame.split == "train":
        arrays, entry["sdf_source"] = sdf_arrays(worker, frame, key)
        for branch in ("sdf_hand", "sdf_obj"):
            problem = sdf_files.loader_problem(arrays[branch])
            if problem:
                raise ValueError(f"{branch}: {problem}")
        for folder, values in arrays.items():
            rel = f"data/sdf_data/{folder}/{name}.npz"
            write_npz(out / rel, values)
            entry["files"].append(rel)
        ann["sdf_scale"] = arrays["norm"]["scale"].astype(float).tolist()
        ann["sdf_offset"] = arrays["norm"]["offset"].astype(float).tolist()
    else:
        mano = worker.mano(frame.side, frame.fix_left_shapedirs)
        pose = np.asarray(frame.object_pose, float)
        # the evaluation meshes: the closed MANO mesh, and the model file posed (not the repaired SDF mesh)
        meshes = {"mesh_hand": (posed_hand(frame, mano), mano.closed_faces),
                  "mesh_obj": (raw_v @ pose[:3, :3].T + pose[:3, 3], raw_f)}
        for folder, (v, f) in meshes.items():
            rel = f"data/mesh_data/{folder}/{name}.obj"
            write_obj(out / rel, v, f)
            entry["files"].append(rel)
    return entry


def split_file(split: str, setup: str, n: int) -> str:
    """``splits/<split>_<setup>_<n // 1000>k.json``: gSDF's naming (29,656 ids -> train_s0_29k)."""
    return f"splits/{split}_{setup}_{n // 1000}k.json"


def finish(out: Path, cfg, splits, entries, root: Path, models_dir: Path) -> tuple[list[str], dict, list[str]]:
    """COCO files, split lists and the data links; returns (files, {'store': n, 'sampled': m}, notes)."""
    setup, files, notes, sources = cfg.dataset.setup, [], [], {}
    keys = {"train": "trainset_3d_split", "test": "testset_split"}
    for split in splits:
        name = f"dexycb_{split}_{setup}.json"
        write_coco(out / name, entries, split)
        ids = sorted(e["image"]["id"] for e in entries() if e["split"] == split)
        lst = split_file(split, setup, len(ids))
        write_json(out / lst, [str(i).rjust(8, "0") for i in ids], indent=2)
        files += [name, lst]
        tag = Path(lst).stem.split("_", 1)[1]
        notes.append(f"{lst}: {len(ids)} ids; gSDF config: {keys.get(split, split + '_split')}: {tag}"
                     + (f", num_testset_samples: {len(ids)}" if split == "test" else ""))
    for e in entries():
        if "sdf_source" in e:
            sources[e["sdf_source"]] = sources.get(e["sdf_source"], 0) + 1
    folders = sorted({_subject(e["image"]["file_name"]) for e in entries()})
    linked = [f for f in folders if link(root / f, out / "data" / f)]
    if link(models_dir, out / "data" / "models"):
        linked.append("models")
    if linked:
        notes.append(f"linked data/{{{', '.join(linked)}}} -> the DexYCB folders")
    return files, sources, notes


def _subject(name: str) -> str:
    from hoidata.datasets.dexycb_layout import SUBJECTS

    return SUBJECTS[int(name.split("_")[0]) - 1]
