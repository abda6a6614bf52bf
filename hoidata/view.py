"""``hoidata view``: records of a store as a rerun recording (``.rrd``), the 3D viewer the HOT3D toolkit uses.

Each record, in its camera frame (OpenCV axes: x right, y down, z forward; metres):

- ``world/camera``: the crop's pinhole (its ``K``, square side) and ``world/camera/image`` the crop in it, with the
  2D joints; so the crop sits in its camera frustum;
- ``world/hand/mesh`` (with ``--mano``: the right MANO mesh of the record's ``mano_pose``, ``mano_betas``,
  ``mano_transl``) and ``world/object/mesh`` (the index's mesh of ``object_name`` posed by ``object_pose``; a mirrored
  record's is the mirrored model, as its labels are);
- ``world/hand/joints`` and ``world/hand/bones``: the 21 joints and the kinematic tree;
- ``world/sdf/hand_distance``, ``world/sdf/object_distance``: the SDF samples coloured by their signed distance
  (blue inside, red outside, white at the surface, saturated at 2 cm), and ``world/sdf/hand_part`` by hand part.

A sequence is one record per step of the ``record`` timeline, the viewer's time slider. Records of kind ``eval`` have
no hand labels or SDF samples: only their image, camera and object are logged.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.geometry.mirror import mirror_mesh
from hoidata.schema import IMG, META, SDF, dequantize_sdf
from hoidata.store import KEY, decode_record, read_checked_shard, read_index

APPLICATION = "hoidata"
DISTANCE_LIMIT = 0.02  # metres at which the distance colours saturate
PART_NAMES = ("wrist", "index 1", "index 2", "index 3", "middle 1", "middle 2", "middle 3", "little 1", "little 2",
              "little 3", "ring 1", "ring 2", "ring 3", "thumb 1", "thumb 2", "thumb 3")  # MANO's own joint order
NO_PART = len(PART_NAMES)  # the class id of a sample without a part (-1 in sdf.npy)
# the 21 joints (DexYCB order: wrist, then 4 per finger from thumb to little): each finger a strip from the wrist
BONES = [[0, 1, 2, 3, 4], [0, 5, 6, 7, 8], [0, 9, 10, 11, 12], [0, 13, 14, 15, 16], [0, 17, 18, 19, 20]]
_FRAME_NUMBER = re.compile(r"^(.*)_(\d+)$")


def sequence_of(key: str) -> str:
    """The sequence a record key belongs to: the key without its trailing ``_<frame number>``."""
    match = _FRAME_NUMBER.match(key)
    return match.group(1) if match else key


def select_rows(index, key: str | None = None, row: int | None = None, sequence: str | None = None) -> list[int]:
    """The index rows to show: the record ``key``, the record at ``row``, every record of ``sequence`` (in store
    order), or the first record; anything not in the store is a DataError naming it."""
    keys = index.keys
    if key is not None:
        if key not in keys:
            raise DataError(index.path, "--key", f"no record {key!r} in the store")
        return [keys.index(key)]
    if sequence is not None:
        rows = [i for i, k in enumerate(keys) if sequence_of(k) == sequence]
        if not rows:
            some = sorted({sequence_of(k) for k in keys})[:3]
            raise DataError(index.path, "--sequence", f"no record of sequence {sequence!r}; sequences are the keys "
                                                      f"without their frame number, e.g. {some}")
        return rows
    row = 0 if row is None else row
    if not 0 <= row < len(keys):
        raise DataError(index.path, "--index", f"{row} is not a record index (the store has {len(keys)} records)")
    return [row]


def read_rows(store: Path, index, rows: list[int]) -> list[dict]:
    """The decoded records at ``rows``, in that order (each shard read once, checked against the index)."""
    wanted, shard_of = set(rows), index.labels["shard"]
    found = {}
    for number in sorted({int(shard_of[r]) for r in rows}):
        span = index.shard_rows(number)
        info = index.shards[number]
        for offset, members in enumerate(read_checked_shard(store / info.name, index.keys[span], info.size)):
            if span.start + offset in wanted:
                found[span.start + offset] = decode_record(members, str(store / info.name))
    return [found[r] for r in rows]


def distance_colours(distance: np.ndarray) -> np.ndarray:
    """Signed distances (metres) -> RGB uint8: blue inside, white at the surface, red outside."""
    from matplotlib import colormaps

    scaled = np.clip(distance / DISTANCE_LIMIT, -1.0, 1.0) * 0.5 + 0.5
    return (colormaps["coolwarm"](scaled)[:, :3] * 255).astype(np.uint8)


def posed_object(index, meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """The record's object mesh in its camera frame (a mirrored record poses the mirrored model)."""
    name = meta["object_name"]
    if name not in index.objects:
        raise DataError(index.path, "objects", f"no mesh for {name!r} (record {meta['key']})")
    vertices, faces = (np.asarray(a) for a in index.objects[name])
    if meta["mirrored"]:
        vertices, faces = mirror_mesh(vertices, faces)
    pose = np.asarray(meta["object_pose"], np.float64)
    return vertices @ pose[:3, :3].T + pose[:3, 3], faces


def posed_hand(mano, meta: dict) -> np.ndarray:
    """The right MANO mesh's vertices (778, 3) of the record's labels."""
    import torch

    pose, betas, transl = (torch.as_tensor(np.asarray(meta[k], np.float64))[None]
                           for k in ("mano_pose", "mano_betas", "mano_transl"))
    with torch.no_grad():
        return mano(pose, betas, transl).vertices[0].numpy()


def log_record(rec, index, record: dict, mano=None) -> None:
    """Log one decoded record into the rerun stream ``rec`` at its current time (see the module docstring)."""
    import rerun as rr

    meta, image = record[META], record[IMG]
    side = image.shape[0]
    rec.log("world/camera", rr.Pinhole(image_from_camera=np.asarray(meta["K"]), resolution=[side, side],
                                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.15))
    rec.log("world/camera/image", rr.Image(image))
    rec.log("world/record", rr.TextDocument(f"{record[KEY]}\nobject: {meta['object_name']}\n"
                                            f"mirrored: {meta['mirrored']}"))
    vertices, faces = posed_object(index, meta)
    rec.log("world/object/mesh", rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces,
                                           albedo_factor=[230, 160, 60, 255]))
    if "joints_3d" not in meta:  # an eval record: no hand labels, no SDF samples
        return
    rec.log("world/camera/image/joints", rr.Points2D(np.asarray(meta["joints_2d"]), radii=1.0,
                                                      colors=[40, 220, 40]))
    joints = np.asarray(meta["joints_3d"])
    rec.log("world/hand/joints", rr.Points3D(joints, radii=0.003, colors=[40, 220, 40]))
    rec.log("world/hand/bones", rr.LineStrips3D([joints[b] for b in BONES], colors=[40, 220, 40]))
    if mano is not None:
        hand = rr.Mesh3D(vertex_positions=posed_hand(mano, meta), triangle_indices=np.asarray(mano.faces),
                         albedo_factor=[240, 200, 180, 255])
        rec.log("world/hand/mesh", hand)
    xyz, sdf_hand, sdf_object, part = dequantize_sdf(record[SDF])
    points = xyz + np.asarray(meta["hand_root"], np.float32)
    rec.log("world/sdf/hand_distance", rr.Points3D(points, radii=0.001, colors=distance_colours(sdf_hand)))
    rec.log("world/sdf/object_distance", rr.Points3D(points, radii=0.001, colors=distance_colours(sdf_object)))
    rec.log("world/sdf/hand_part", rr.Points3D(points, radii=0.001,
                                               class_ids=np.where(part < 0, NO_PART, part).astype(np.uint16)))


def blueprint(hand_root: np.ndarray):
    """The viewer's layout: the 3D scene seen from beside the first record's hand (the SDF samples by their distance
    to the hand; the object-distance and hand-part colourings one click away), the crop, the record's key."""
    import rerun.blueprint as rrb

    root = np.asarray(hand_root, np.float64)  # seen from behind the camera, a little above and to the side
    eye = rrb.EyeControls3D(position=[0.25, -0.2, -0.25], look_target=root, eye_up=[0.0, -1.0, 0.0])
    scene = rrb.Spatial3DView(origin="world", name="scene", eye_controls=eye,
                              contents=["+ world/**", "- world/sdf/object_distance", "- world/sdf/hand_part"])
    side = rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="crop"),
                        rrb.TextDocumentView(origin="world/record", name="record"), row_shares=[3, 1])
    return rrb.Blueprint(rrb.Horizontal(scene, side, column_shares=[3, 2]), collapse_panels=True)


def write_recording(store, out, key: str | None = None, row: int | None = None, sequence: str | None = None,
                    mano_dir=None) -> tuple[Path, int]:
    """Write the selected records of ``store`` (see :func:`select_rows`) into the rerun file ``out``; returns
    (``out``, records written). ``mano_dir``: the MANO folder whose right model poses the hand mesh (None: no hand
    mesh, the joints only)."""
    import rerun as rr

    from hoidata.atomic import atomic_path

    store, out = Path(store), Path(out)
    index = read_index(store)
    rows = select_rows(index, key, row, sequence)
    mano = None
    if mano_dir is not None:
        import torch

        from hoidata.hand import load_mano

        mano = load_mano(mano_dir, side="right", dtype=torch.float64)
    records = read_rows(store, index, rows)
    with atomic_path(out) as tmp:
        rec = rr.RecordingStream(APPLICATION, recording_id=f"{store.name}-{rows[0]}-{len(rows)}")
        rec.save(str(tmp), default_blueprint=blueprint(records[0][META]["hand_root"]))
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        rec.log("world/sdf/hand_part", rr.AnnotationContext(
            [(i, name) for i, name in enumerate(PART_NAMES)] + [(NO_PART, "no part")]), static=True)
        for step, record in enumerate(records):
            rec.set_time("record", sequence=step)
            log_record(rec, index, record, mano)
        rec.flush()
        rec.disconnect()
    return out, len(records)
