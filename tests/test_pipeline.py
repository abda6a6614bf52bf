"""build-sdf end to end on a tiny toy DexYCB: determinism, resume, skips, verify, record contents."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from hoidata import schema, store
from hoidata.cli import main
from hoidata.geometry.sdf import brute_force_signed_distance
from hoidata.build_sdf import build_store
from hoidata.records.settings import load_build_config
from hoidata.toy.make import write_assets

pytestmark = pytest.mark.slow  # build-sdf end to end on the tiny toy DexYCB

SMALL = ["dataset.splits=[\"train\"]", "record.crop_size=128", "record.sdf_samples_hand=384", "record.sdf_samples_object=256",
         "store.records_per_shard=5"]


@pytest.fixture(scope="session")
def tiny_root(tiny_dexycb):
    return tiny_dexycb


def _build(root, out, workers=1, part=(0, 1), extra=()):
    cfg = load_build_config("toy", SMALL + list(extra))
    return build_store(cfg, root, root / "mano", root / "models", out, workers=workers, part=part, progress=False)


@pytest.fixture(scope="session")
def built(tiny_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("store") / "one"
    summary = _build(tiny_root, out)
    return out, summary


def _shard_bytes(out):
    return {p.name: p.read_bytes() for p in sorted(out.glob("shard-*.tar"))}


def test_build_writes_a_verified_store(built):
    out, summary = built
    assert summary.finished and summary.written == 16 and summary.items == 16
    assert len(list(out.glob("shard-*.tar"))) == 4
    report = store.verify_store(out)
    assert report.ok, str(report)
    index = store.read_index(out)
    assert len(index.keys) == 16 and index.config["record"]["crop_size"] == 128
    assert index.provenance["hoidata_version"] and "git_commit" in index.provenance
    assert set(index.objects) == set(index.labels["object_name"].tolist())
    assert all(len(v) == 1000 for v, _ in index.objects.values())


def test_two_workers_give_byte_identical_shards(built, tiny_root, tmp_path):
    out, _ = built
    _build(tiny_root, tmp_path / "two", workers=2)
    assert _shard_bytes(tmp_path / "two") == _shard_bytes(out)


def test_interrupted_build_resumes_to_the_same_store(built, tiny_root, tmp_path):
    out, _ = built
    resumed = tmp_path / "resumed"
    first = _build(tiny_root, resumed, part=(0, 2))  # as if killed after some shards
    assert not first.finished and first.units_written == 2
    (resumed / "shard-000001.tar.tmp").write_bytes(b"half a shard")  # a shard being written when killed
    kept = resumed / "shard-000002.tar"
    kept.write_bytes(kept.read_bytes()[:1000])  # and one whose file got damaged
    second = _build(tiny_root, resumed)
    assert second.finished and second.units_kept == 1 and second.units_written == 3
    assert _shard_bytes(resumed) == _shard_bytes(out)
    assert not list(resumed.glob("*.tmp"))


def test_resume_refuses_a_store_built_with_other_settings(built, tiny_root):
    out, _ = built
    with pytest.raises(Exception, match="record.sdf_samples_hand differs"):
        _build(tiny_root, out, extra=["record.sdf_samples_hand=100"])


def test_a_corrupt_frame_is_skipped_and_the_build_goes_on(tiny_root, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(tiny_root, root)
    image = sorted(root.glob("*/*/836212060125/color_000002.jpg"))[0]
    image.write_bytes(b"not a jpeg")
    summary = _build(root, tmp_path / "store")
    assert summary.written == 15 and summary.finished
    index = store.read_index(tmp_path / "store")
    reasons = [s["reason"] for s in index.skipped if s["frame_id"].endswith("_000002")]
    assert any("cannot decode the image file" in r for r in reasons)


def test_records_hold_exact_sdf_and_consistent_masks(built, tiny_root):
    import torch

    from hoidata.hand import load_mano
    from hoidata.objects import load_object_mesh, object_mesh_path, repair_mesh

    out, _ = built
    from hoidata.geometry.mirror import mirror_axis_angle, mirror_mesh, mirror_points

    right = load_mano(tiny_root / "mano", dtype=torch.float64)
    left = load_mano(tiny_root / "mano", side="left", fix_left_shapedirs=False, dtype=torch.float64)
    records = list(store.iter_records(out))
    assert any(r[schema.META]["mirrored"] for r in records[::3]) and not all(r[schema.META]["mirrored"] for r in records[::3])
    for rec in records[::3]:
        meta = rec[schema.META]
        xyz, sdf_h, sdf_o, _ = schema.dequantize_sdf(rec[schema.SDF])
        points = xyz.astype(np.float64) + meta["hand_root"]
        pose, transl = np.asarray(meta["mano_pose"]), np.asarray(meta["mano_transl"])
        if meta["mirrored"]:  # the left hand as DexYCB annotated it (MANO_LEFT unfixed), reflected
            posed = left(torch.as_tensor(mirror_axis_angle(pose))[None], torch.as_tensor(meta["mano_betas"])[None],
                         torch.as_tensor(mirror_points(transl))[None])
            hand, faces = mirror_mesh(left.close(posed.vertices)[0].numpy(), np.asarray(left.closed_faces))
        else:
            posed = right(torch.as_tensor(pose)[None], torch.as_tensor(meta["mano_betas"])[None],
                          torch.as_tensor(transl)[None])
            hand, faces = right.close(posed.vertices)[0].numpy(), right.closed_faces
        ref_h = brute_force_signed_distance(points[::8], hand, faces)[0]
        assert np.abs(ref_h - sdf_h[::8]).max() < 5e-5  # stored distances exact to 0.05 mm
        geo, _ = repair_mesh(load_object_mesh(object_mesh_path(tiny_root / "models", meta["object_name"])))
        pose = np.asarray(meta["object_pose"])
        model, model_faces = np.asarray(geo.vertices), np.asarray(geo.faces)
        if meta["mirrored"]:  # the pose of a mirrored record poses the x-mirrored model (the flipped image's)
            model, model_faces = mirror_mesh(model, model_faces)
        obj = model @ pose[:3, :3].T + pose[:3, 3]
        ref_o = brute_force_signed_distance(points[::8], obj, model_faces)[0]
        assert np.abs(ref_o - sdf_o[::8]).max() < 5e-5
        seg = rec[schema.SEG]
        for visible, amodal in ((schema.SEG_HAND_VISIBLE, schema.SEG_HAND_AMODAL),
                                (schema.SEG_OBJECT_VISIBLE, schema.SEG_OBJECT_AMODAL)):
            assert ((seg & visible) > 0).any() and not (((seg & visible) > 0) & ((seg & amodal) == 0)).any()
        uv = (np.asarray(meta["joints_2d"]) + 0.5) / 2 - 0.5  # crop pixels -> mask pixels
        hand_mask = cv2.dilate(((seg & schema.SEG_HAND_AMODAL) > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
        px = np.clip(np.round(uv).astype(int), 0, seg.shape[0] - 1)
        assert hand_mask[px[:, 1], px[:, 0]].mean() >= 0.95
        assert rec[schema.IMG].shape == (128, 128, 3) and rec[schema.HEATMAP].max() > 200
        # our masks and the dataset's own (rendered by make-toy at full resolution) agree
        assert meta["seg_iou"][0] > 0.8 and (meta["seg_iou"][1] > 0.8 or ((seg & schema.SEG_OBJECT_VISIBLE) > 0).sum() < 20)


def test_cli_verify_names_a_truncated_shard(built, tmp_path, capsys):
    out, _ = built
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    shard = copy / "shard-000001.tar"
    shard.write_bytes(shard.read_bytes()[:-2000])
    assert main(["verify", str(copy)]) == 1
    assert "shard-000001.tar" in capsys.readouterr().out
    assert main(["verify", str(out)]) == 0


def test_ho3d_build_converts_and_records_quality(tmp_path):
    from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d

    root = tmp_path / "ho3d"
    mano_dir, models_dir = write_assets(root)
    write_toy_ho3d(root, mano_dir, models_dir, ToyHO3DSize(train_sequences=1, eval_sequences=1, frames=3), progress=False)
    cfg = load_build_config("ho3d", ["record.crop_size=128", "record.sdf_samples_hand=256", "record.sdf_samples_object=128"])
    summary = build_store(cfg, root, mano_dir, models_dir, tmp_path / "store", progress=False)
    assert summary.written == 3 and summary.finished
    index = store.read_index(tmp_path / "store")
    assert set(index.labels["tip_convention"].tolist()) == {"ho3d"}
    assert (index.labels["hand_root"][:, 2] > 0).all()  # OpenGL annotations arrive in the OpenCV frame
    assert (index.labels["seg_iou"][:, 0] > 0.5).all()  # against HO-3D's quarter-resolution JPEG masks


def test_estimate_writes_nothing_and_reports_time_and_disk(tiny_root, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["build-sdf", "--dataset", "toy", "--root", str(tiny_root), "--out", str(out), "--estimate", *SMALL]) == 0
    text = capsys.readouterr().out
    assert not out.exists()
    assert "frames: 16" in text and "bytes_per_frame" in text and "estimated_minutes" in text
