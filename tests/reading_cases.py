"""Every reader of the project as a corpus case (tests/test_reading_corpus.py): its valid file, where it lies, how
the reader is called and the damages its contract lets it take. Scorers first, then HOT3D, the data side, training.
"""

from __future__ import annotations

import hashlib
import io
import json
import pickle
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch
from reading_corpus import CONTENT, TYPED, Case, tar_bytes, zip_bytes
from test_store import make_record

from hoidata.errors import DataError

JSON_NUMBERS = lambda value: json.dumps(value).encode()  # noqa: E731
# a text list holds words, not numbers (a bracket is a character of a word); a list cut at a line is a shorter list
TEXT_LENIENT = frozenset({"truncated", "empty", "deep_json", *TYPED})
ALL = frozenset(CONTENT)  # a reader that hashes bytes or falls back (a cache) takes whatever the file holds


def _image(ext: str, size=(16, 16)) -> bytes:
    yy, xx = np.mgrid[:size[1], :size[0]]
    return cv2.imencode(ext, np.stack([xx * 9, yy * 9, xx + yy], -1).astype(np.uint8))[1].tobytes()


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def _torch(value) -> bytes:
    buf = io.BytesIO()
    torch.save(value, buf)
    return buf.getvalue()


def _refused(result, path):
    """check_mesh's (None, why) as the refusal it is."""
    mesh, why = result
    if mesh is None:
        raise DataError(path, None, why)


def _ply() -> bytes:
    import trimesh

    return trimesh.creation.icosahedron().export(file_type="ply")


def scorer_cases() -> list[Case]:
    from hoisdf.scoring import recon_files, recon_gsdf, score_contact, score_ho3d, score_hot3d, submissions
    from hoisdf.scoring.ho3d_list import read_evaluation_list
    from hoisdf.scoring.official import read_ho3d_gt

    pred = JSON_NUMBERS([[[[0.1 * i, -0.2, -0.5] for i in range(21)]], [[[0.01 * i, 0.0, -0.5] for i in range(778)]]])
    gt_verts = JSON_NUMBERS([[[0.0, 0.0, -0.5]] * 778])
    hot3d = JSON_NUMBERS([{"sequence_name": "s", "frame_id": 0, "mano_theta": [0.5] * 15, "wrist_xform": [0.0] * 6,
                           "hand_side": 1}])
    pose = {k: (n,) for k, n in score_hot3d.POSE_FIELDS.items()}
    name = "result_pose_hot3d.json"

    def hot3d_entries(source, where):
        entries = score_hot3d._member(source, name)
        if entries is None:
            raise DataError(where, name, "absent")
        return score_hot3d.read_entries(entries, where, pose)

    hpe = ("0," + ",".join(f"{v:.3f}" for v in np.linspace(1, 63, 63)) + "\n").encode()
    order = ["SEQ/0000", "SEQ/0001"]
    return [
        Case("score ho3d pred.json", "json", pred, submissions.read_ho3d_lists, "pred.json"),
        Case("score ho3d pred.zip member", "json", pred, submissions.read_ho3d_lists, "pred.zip", member="pred.json",
             container=zip_bytes, duplicate_as="{}"),
        Case("score ho3d pred.zip", "zip", zip_bytes([("pred.json", pred)]), submissions.read_ho3d_lists, "pred.zip",
             frozenset({"not_utf8"})),  # a zip is found from its end: bytes before it are a valid prefix
        Case("HO-3D ground truth", "json", JSON_NUMBERS([[[0.0, 0.0, -0.5]] * 21]),
             lambda p: read_ho3d_gt(p.parent), "evaluation_xyz.json", sibling={"evaluation_verts.json": gt_verts}),
        Case("score ho3d evaluation.txt", "text", b"SEQ/0000\nSEQ/0001\n", lambda p: score_ho3d.read_order(p.parent),
             "evaluation.txt", TEXT_LENIENT),
        Case("score ho3d --ids", "text", b"SEQ/0001\n", lambda p: score_ho3d.subset_rows(order, None, p), "ids.txt"),
        Case("evaluation list (--ho3d-order)", "text", b"SEQ/0000\nSEQ/0001\n", read_evaluation_list,
             "evaluation.txt", frozenset({"truncated"})),
        Case("score dexycb result", "text", hpe, submissions.read_dexycb_hpe, "result.txt", frozenset({"empty"})),
        Case("score contact hands.npz", "npz", _npz(verts=np.zeros((1, 778, 3)), keys=np.array(["k0"])),
             score_contact.read_hands, "hands.npz"),
        Case("score contact --order", "text", b"SEQ/0000\n", score_contact.read_order, "evaluation.txt",
             TEXT_LENIENT),
        Case("score recon --ids", "text", b"f0\nf1\n", recon_files.read_ids, "ids.txt", TEXT_LENIENT - {"empty"}),
        Case("score recon mesh", "ply", _ply(), lambda p: _refused(recon_files.check_mesh(p), p), "f0_hand.ply",
             frozenset({"not_utf8"})),  # trimesh reads a PLY past bytes before its header, as gSDF's does
        Case("gSDF's mesh load", "ply", _ply(), recon_gsdf.load_mesh, "f0_hand.ply", ALL),  # scored as gSDF does
        Case("score hot3d folder", "json", hot3d, lambda p: hot3d_entries(p.parent, p), name),
        Case("score hot3d tar member", "json", hot3d, lambda p: hot3d_entries(p, f"{p}:{name}"), "sub.tar",
             member=name, container=tar_bytes, shows=name),
        Case("score hot3d tar", "tar", tar_bytes([(name, hot3d)]), lambda p: hot3d_entries(p, p), "sub.tar",
             frozenset({"truncated"})),  # cut after its one member, which is whole
    ]


def _se3() -> dict:
    return {"quaternion_wxyz": [1.0, 0.0, 0.0, 0.0], "translation_xyz": [0.0, 0.0, 0.3]}


def hot3d_cases(mano_dir, manos: dict) -> list[Case]:
    from hoidata.datasets.hot3d import HOT3DClipsReader, object_mask_iou
    from hoidata.datasets.hot3d_format import FISHEYE624, HAND_SHAPES

    k = "000000"
    members = {
        f"{k}.cameras.json": {"214-1": {"calibration": {"image_width": 64, "image_height": 48, "label": "camera-rgb",
                                                         "projection_model_type": FISHEYE624,
                                                         "projection_params": [60.0, 31.5, 23.5] + [0.0] * 12},
                                         "T_world_from_camera": _se3()}},
        f"{k}.hands.json": {"left": {"umetrack_pose": {}, "mano_pose": {"thetas": [0.1] * 15,
                                                                        "wrist_xform": [0.0] * 6}}},
        f"{k}.hand_crops.json": {"left": {"214-1": {"crop_camera_fov": 1.0, "T_world_from_crop_camera": _se3()}}},
        f"{k}.objects.json": {"uid1": [{"object_bop_id": 1, "T_world_from_object": _se3()}]},
        f"{k}.info.json": {},
        HAND_SHAPES: {"mano": [0.0] * 10, "umetrack": {}},
    }
    members = {n: JSON_NUMBERS(v) for n, v in members.items()}
    members[f"{k}.image_214-1.jpg"] = _image(".jpg", (64, 48))

    def read(tar: Path):
        reader = HOT3DClipsReader(tar.parents[1], mano_dir, on_error="raise", crop_size=32)
        reader._manos = manos  # MANO loaded once for every case
        frames = list(reader.frames())
        if not frames:
            raise DataError(tar, None, "no frame")
        for frame in frames:
            frame.image_source()
            object_mask_iou(frame, np.zeros((8, 8), bool), np.eye(3))

    tar = "train_aria/clip-000001.tar"
    cases = [Case("HOT3D clip tar", "tar", tar_bytes(list(members.items())), read, tar)]
    for name, data in members.items():
        if name.endswith("info.json"):
            continue  # the reader does not read it (the official one neither)
        kind = "image" if name.endswith(".jpg") else "json"
        others = [(n, d) for n, d in members.items() if n != name]
        cases.append(Case(f"HOT3D member {name}", kind, data, read, tar, member=name, others=others,
                          container=tar_bytes))
    return cases


def _shard(records: list[tuple[str, dict]]) -> bytes:
    return tar_bytes([(f"{key}.{name}", data) for key, members in records for name, data in members.items()])


def _record_members():
    from hoidata import schema
    from hoidata.store import encode_record

    key, img, seg, hm, sdf, meta = make_record(0)
    plain = encode_record(key, img, seg, hm, sdf, meta)
    region = {**meta, "key": "toy-train-f0001", "frame_id": "f0001", "region": schema.UPSTREAM_REGION,
              "region_origin": np.zeros(2), "frame_size": np.array([64.0, 64.0]), "frame_K": np.eye(3),
              "frame_joints_2d": np.zeros((21, 2)), "frame_box21_2d": np.zeros((21, 2))}
    framed = encode_record("toy-train-f0001", img, seg, hm, sdf, region, _image(".jpg", (64, 64)))
    return [(key, plain), ("toy-train-f0001", framed)]


def store_cases(tmp: Path) -> list[Case]:
    from hoidata import schema, store
    from hoidata.export import handoccnet, job
    from hoidata.export.gsdf import check_store_inputs
    from hoidata.export.worker import chunk_path, shard_rows
    from hoidata.records import store_writer
    from hoidata.store.index import ShardInfo

    records = _record_members()
    (first_key, first), (region_key, region) = records

    def decode_all(path):
        return [store.decode_record(m, str(path)) for m in store.read_shard_members(path)]

    def shard_metas(path):
        data = path.read_bytes()
        info = SimpleNamespace(size=len(data), sha256=hashlib.sha256(data).hexdigest())
        return store_writer._shard_metas(path, info)

    def shard_record_metas(path):
        from hoidata.store.loader_files import ShardMembers, record_metas
        from hoidata.store.spans import record_spans

        data, keys, members = path.read_bytes(), [first_key], []
        info = ShardInfo(0, path.name, 1, hashlib.sha256(data).hexdigest(), len(data), first_key, first_key)
        spans = record_spans(path, keys, len(data), members)
        return record_metas(path.parent, [ShardMembers(info, keys, spans, members)])

    cases = []
    for key, members in records:
        for member, data in members.items():
            kind = {"jpg": "image", "png": "image", "npy": "npy", "json": "json"}[member.rsplit(".", 1)[1]]
            others = [(f"{k}.{n}", d) for k, ms in records for n, d in ms.items() if (k, n) != (key, member)]
            at = [(k, n) for k, ms in records for n in ms].index((key, member))
            cases.append(Case(f"shard member {member} ({'region' if key == region_key else 'plain'} record)", kind,
                              data, decode_all, "shard-000000.tar", member=f"{key}.{member}", others=others,
                              container=tar_bytes, position=at, shows=key))  # the record, or key.member
    plain_others = [(f"{first_key}.{n}", d) for n, d in first.items() if n != schema.META]
    cases += [
        Case("build: shard metas", "json", first[schema.META], shard_metas, "shard-000000.tar",
             frozenset(TYPED), member=f"{first_key}.{schema.META}", others=plain_others, container=tar_bytes,
             position=len(plain_others)),  # the labels' values are the index writer's to check
        Case("loader files: record metas", "json", first[schema.META], shard_record_metas, "shard-000000.tar",
             frozenset(TYPED), member=f"{first_key}.{schema.META}", others=plain_others, container=tar_bytes,
             position=len(plain_others)),  # the card reads the values as they are
        Case("export: shard rows", "json", first[schema.META], shard_rows, "shard-000000.tar", frozenset(TYPED),
             member=f"{first_key}.{schema.META}", others=plain_others, container=tar_bytes,
             position=len(plain_others)),
    ]
    out = tmp / "pinned"
    config, keys, inputs = {"record": {"crop_size": 128}}, ["a", "b"], {"mano": {"MANO_RIGHT.pkl": "ab"}}
    store_writer.check_build_file(out, config, keys, inputs)
    spec = {"format": "gsdf", "frames": 3}
    info = ShardInfo(0, "shard-000000.tar", 1, "ab" * 32, 10, "k", "k").to_dict()
    manifest = {"entries": [{"split": "train", "files": []}], "skipped": []}
    cases += [
        Case("build.json (resume)", "json", (out / "build.json").read_bytes(),
             lambda p: store_writer.check_build_file(p.parent, config, keys, inputs), "build.json",
             frozenset({"missing"})),  # none yet: a new store, pinned now
        Case("build.json (the MANO digests the index records)", "json", (out / "build.json").read_bytes(),
             lambda p: store_writer.pinned_mano(p.parent), "build.json", frozenset(TYPED)),  # reads the digests only
        Case("skips file", "json", JSON_NUMBERS({"skipped": [], "records": 1}),
             lambda p: store_writer.read_shard_skips(p.parent, 0), store_writer.extra_name(0)),
        Case("shard sidecar", "json", JSON_NUMBERS(info), lambda p: store.read_sidecar(p.parent, 0),
             "shard-000000.json"),
        Case("export --store build.json", "json", JSON_NUMBERS({"inputs": {"mano": {"MANO_RIGHT.pkl": "ab"}},
                                                               "frames": 2}),
             lambda p: check_store_inputs(p.parent, {"mano": {"MANO_RIGHT.pkl": "ab"}}), "build.json",
             frozenset(TYPED)),
        Case("export.json", "json", JSON_NUMBERS(spec), lambda p: job._check_spec(p.parent, spec), job.SPEC_FILE,
             frozenset({"missing"})),  # none yet: a new export, pinned now
        Case("export chunk manifest", "json", JSON_NUMBERS(manifest), lambda p: job.read_manifest(p.parent, 0),
             chunk_path(Path("."), 0).name, frozenset(TYPED)),
        Case("export: HO-3D list count", "text", b"SEQ/0000\n", handoccnet.listed_frames, "evaluation.txt",
             TEXT_LENIENT),
    ]
    return cases


def data_cases(tmp: Path) -> list[Case]:
    from hoidata import objects
    from hoidata.datasets import dexycb_layout, frame_list, ho3d
    from hoidata.datasets.frame import read_rgb
    from hoidata.objects import ycb
    from hoidata.records.settings import load_build_config
    from hoidata.records.upstream import decode_as_upstream, frame_file
    from hoidata.render.appearance import load_background
    from hoidata.safe_pickle import load_pickle
    from hoidata.sections import pipelines_dir

    meta = (b'serials: ["836212060125"]\nnum_frames: 1\nycb_ids: [1]\nycb_grasp_ind: 0\nmano_sides: [right]\n'
            b"mano_calib: [subject]\n")
    labels = _npz(pose_y=np.zeros((1, 3, 4), np.float32), seg=np.zeros((480, 640), np.uint8),
                  pose_m=np.zeros((1, 51), np.float32), joint_3d=np.zeros((1, 21, 3), np.float32),
                  joint_2d=np.zeros((1, 21, 2), np.float32))
    frame = lambda p: SimpleNamespace(image=None, image_path=p, image_size=(16, 16))  # noqa: E731
    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    return [
        Case("DexYCB meta.yml", "yaml", meta, lambda p: dexycb_layout.read_meta(p.parent), "meta.yml"),
        Case("DexYCB labels", "npz", labels, lambda p: dexycb_layout.read_labels(p, 1), "labels_000000.npz",
             frozenset({"nan_number"})),  # values are the frame reader's to judge (-1 marks an invalid joint)
        Case("dataset image", "image", _image(".jpg"), lambda p: read_rgb(p, (16, 16)), "color_000000.jpg"),
        Case("upstream's image decode", "image", _image(".jpg"), lambda p: decode_as_upstream(frame(p)), "c.jpg"),
        Case("upstream region frame file", "image", _image(".png"), lambda p: frame_file(frame(p)), "c.png",
             frozenset({"truncated"})),  # kept as shipped, decoded by the record's reader
        Case("render background", "image", _image(".png"), lambda p: load_background(p, 8, 8,
                                                                                    np.random.default_rng(0)), "b.png"),
        Case("frame list", "json", JSON_NUMBERS([1, 2, 3]), frame_list.read_frame_list, "ids.json",
             frozenset({"string_number"})),  # digit strings are sample ids by its contract
        Case("frame list digest", "json", JSON_NUMBERS([1, 2]), lambda p: frame_list.frame_list_provenance(p, [1]),
             "ids.json", ALL),
        Case("HO-3D split list", "text", b"SEQ1/0000\nSEQ1/0001\n", lambda p: ho3d.read_list(p.parent, "train"),
             "train.txt", TEXT_LENIENT),
        Case("object mesh", "obj", obj, objects.load_object_mesh, "textured_simple.obj", frozenset({"truncated"})),
        Case("object points", "text", b"0 0 0\n1 1 1\n", objects.load_points, "points.xyz",
             frozenset({"truncated"})),
        Case("simplified mesh cache", "npz", _npz(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]])),
             ycb._read_cached, "m-100-abc.npz", ALL | {"missing", "folder"}),  # an unreadable cache is recomputed
        Case("object mesh digest", "obj", obj, lambda p: ycb.simplify_cache_key(p, 100), "textured_simple.obj",
             ALL),
        Case("pickle", "pickle", pickle.dumps({"a": [1.0, 2.0]}, protocol=2), load_pickle, "meta.pkl"),
        Case("pipeline file", "toml", (pipelines_dir() / "toy.toml").read_bytes(),
             lambda p: load_build_config(str(p)), "toy.toml", frozenset({"empty", "truncated"})),  # defaults
    ]


def training_cases(tmp: Path) -> list[Case]:
    from torchvision.models import resnet18

    from hoisdf.evaluation.visualize import read_curve
    from hoisdf.model.backbone import ResNetUNet
    from hoisdf.training.checkpoint import load_checkpoint
    from hoisdf.training.trainer import trim_keys, trim_log
    from hoisdf.training.upstream import read_snapshot

    curve = b"split,epoch,step,name,value\ntrain,0,1,total,0.5\ntrain,0,2,total,0.4\n"
    net = ResNetUNet(18)
    return [
        Case("checkpoint", "torch", _torch({"model": {"w": torch.zeros(2)}, "config": {}}), load_checkpoint, "last.pt"),
        Case("upstream snapshot", "torch", _torch({"network": {"a.weight": torch.zeros(2)}}), read_snapshot,
             "snapshot.pth.tar"),
        Case("backbone weights", "torch", _torch(resnet18().state_dict()), net.load_backbone, "resnet18.pth"),
        Case("training curve", "csv", curve, read_curve, "metrics.csv", frozenset({"truncated", *TYPED})),
        Case("metrics.csv on resume", "csv", curve, lambda p: trim_log(p, 1), "metrics.csv",
             ALL - {"not_utf8"} | {"missing", "folder"}),  # no log yet: nothing to trim
        Case("keys file on resume", "text", b"k0\nk1\n", lambda p: trim_keys(p, 3, 0), "keys-rank0.txt",
             ALL | {"missing", "folder"}),
    ]


def arctic_cases(tmp: Path) -> list[Case]:
    """ARCTIC's raw sequences, meta, splits and object templates (the toy's, as ARCTIC's loader opens them), and a
    leaderboard submission's torch files in a zip."""
    from hoidata.datasets import arctic_format as af
    from hoidata.objects.arctic import load_arctic_object, read_object_meta
    from hoidata.toy.make import make_toy
    from hoisdf.scoring.arctic_files import Source

    root = tmp / "arctic"
    make_toy(root, "arctic", progress=False)
    seq = sorted((root / "raw_seqs").glob("*/*.mano.npy"))[0]
    subject, name = seq.parent.name, seq.name[: -len(".mano.npy")]
    files = {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*") if p.is_file()
             and (p.parent == seq.parent and p.name.startswith(name) or p.parent.name == "meta")}
    template = root / "meta" / "object_vtemplates" / name.split("_")[0]
    parts = {f"meta/object_vtemplates/{template.name}/{p.name}": p.read_bytes() for p in template.iterdir()}

    def sequence(rel: str, kind: str, accepts=frozenset()):
        return Case(f"ARCTIC {rel.rsplit('/', 1)[1]}", kind, files[rel],
                    lambda p: af.read_sequence(p.parents[2], subject, name), rel, frozenset(accepts),
                    sibling={k: v for k, v in files.items() if k != rel})

    def template_file(rel: str, kind: str, accepts=frozenset()):
        return Case(f"ARCTIC template {rel.rsplit('/', 1)[1]}", kind, parts[rel],
                    lambda p: load_arctic_object(p.parents[2], template.name, {template.name: 0.1}), rel,
                    frozenset(accepts), sibling={k: v for k, v in parts.items() if k != rel})

    rel = f"raw_seqs/{subject}/{name}"
    pt = _torch({"pred.mano.pose.r": torch.zeros(2, 48), "names": ["a", "b"]})
    return [
        sequence(f"{rel}.mano.npy", "pickled_npy"), sequence(f"{rel}.egocam.dist.npy", "pickled_npy"),
        sequence(f"{rel}.object.npy", "npy"),
        Case("ARCTIC meta/misc.json", "json", files["meta/misc.json"], lambda p: af.read_misc(p.parents[1]),
             "meta/misc.json"),
        Case("ARCTIC protocol", "json", (root / "splits_json" / "protocol_p1.json").read_bytes(),
             lambda p: af.read_protocol(p.parents[1], "p1"), "splits_json/protocol_p1.json"),
        Case("ARCTIC object_meta.json", "json", files["meta/object_meta.json"],
             lambda p: read_object_meta(p.parent), "meta/object_meta.json"),
        template_file(f"meta/object_vtemplates/{template.name}/mesh.obj", "obj", {"truncated"}),
        template_file(f"meta/object_vtemplates/{template.name}/parts.json", "json"),
        template_file(f"meta/object_vtemplates/{template.name}/object_params.json", "json"),
        template_file(f"meta/object_vtemplates/{template.name}/top_keypoints_300.json", "json"),
        Case("ARCTIC submission .pt in a zip", "torch", pt, lambda p: Source(p).read("eval/x/pred.pt"), "sub.zip",
             member="eval/x/pred.pt", container=zip_bytes, duplicate_as="{}"),
        Case("ARCTIC submission zip", "zip", zip_bytes([("eval/x/pred.pt", pt)]),
             lambda p: Source(p).read("eval/x/pred.pt"), "sub.zip", frozenset({"not_utf8"})),  # a zip's prefix
    ]
