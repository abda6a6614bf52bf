"""render-synthetic: views and perturbations, determinism, physical checks, labels vs pixels, errors."""

from __future__ import annotations

import igl
import numpy as np
import pytest
import torch

from hoidata import schema, store
from hoidata.errors import DataError
from hoidata.records.records import RecordSettings
from hoidata.synth import views
from hoidata.render_synthetic import render_synthetic
from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d
from hoidata.toy.make import write_assets

pytestmark = pytest.mark.slow  # renders and builds synthetic stores

RECORD = RecordSettings(crop_size=128, sdf_samples_hand=256, sdf_samples_object=128)


@pytest.fixture(scope="session")
def ho3d_source(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_source")
    mano_dir, models_dir = write_assets(root)
    write_toy_ho3d(root, mano_dir, models_dir, ToyHO3DSize(train_sequences=2, eval_sequences=0, frames=2), progress=False)
    return root


def _render(source, out, workers=1, seed=0, count=6, **kw):
    return render_synthetic(source, out, count, source / "mano", source / "models", seed=seed, workers=workers,
                            record=RECORD, records_per_shard=3, progress=False, **kw)


@pytest.fixture(scope="session")
def synth_store(ho3d_source, tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "store"
    summary = _render(ho3d_source, out)
    return out, summary


def test_views_and_perturbations():
    rng = np.random.default_rng(0)
    rots = np.array([views.sample_view_rotation(rng) for _ in range(2000)])
    np.testing.assert_allclose(rots @ rots.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rots.shape), atol=1e-12)
    assert np.allclose(np.linalg.det(rots), 1.0)
    view_dirs = -rots[:, 2, :]  # object-frame direction from the object to the camera
    assert np.abs(view_dirs.mean(0)).max() < 0.05  # uniform over the sphere
    centre = np.array([0.01, -0.02, 0.03])
    t = views.place_on_axis(rots[0], centre, 0.5)
    np.testing.assert_allclose(rots[0] @ centre + t, [0, 0, 0.5], atol=1e-12)
    pose = np.zeros(48)
    pose[:3], pose[3:] = [0.1, 0.2, 0.3], 0.3
    noisy = np.array([views.perturb_pose(pose, rng, 0.1) for _ in range(500)])
    assert np.array_equal(noisy[:, :3], np.broadcast_to(pose[:3], (500, 3)))  # the view sets the global rotation
    angle_change = np.linalg.norm(noisy[:, 3:].reshape(500, 15, 3), axis=2) - np.linalg.norm(pose[3:6])
    assert abs(angle_change.std() - 0.1) < 0.01 and abs(angle_change.mean()) < 0.01


def test_same_seed_same_store_whatever_the_workers(synth_store, ho3d_source, tmp_path):
    out, summary = synth_store
    assert summary.finished and summary.written == 6
    _render(ho3d_source, tmp_path / "two", workers=2)
    shards = sorted(p.name for p in out.glob("shard-*.tar"))
    assert shards == sorted(p.name for p in (tmp_path / "two").glob("shard-*.tar")) and len(shards) == 2
    for name in shards:
        assert (out / name).read_bytes() == (tmp_path / "two" / name).read_bytes()
    _render(ho3d_source, tmp_path / "other", seed=1, count=3)
    assert (tmp_path / "other" / shards[0]).read_bytes() != (out / shards[0]).read_bytes()


def test_records_are_physically_valid_and_flagged(synth_store, ho3d_source):
    from hoidata.hand import load_mano
    from hoidata.objects import load_object_mesh, object_mesh_path, repair_mesh

    out, _ = synth_store
    mano = load_mano(ho3d_source / "mano", dtype=torch.float64)
    index = store.read_index(out)
    stats = index.provenance["synthetic"]
    assert stats["accepted"] == 6 and 0.0 <= stats["rejection_rate"] < 1.0
    for rec in store.iter_records(out):
        meta = rec[schema.META]
        assert meta["dataset"] == "synthetic" and meta["source"]["synthetic"] and meta["source"]["source_grasp"]
        assert meta["tip_convention"] == "ho3d"
        verts = mano(torch.as_tensor(meta["mano_pose"])[None], torch.as_tensor(meta["mano_betas"])[None],
                     torch.as_tensor(meta["mano_transl"])[None]).vertices[0].numpy()
        geo, _ = repair_mesh(load_object_mesh(object_mesh_path(ho3d_source / "models", meta["object_name"])))
        pose = np.asarray(meta["object_pose"])
        local = (verts - pose[:3, 3]) @ pose[:3, :3]  # hand in the object's frame
        v, f = np.asarray(geo.vertices), np.asarray(geo.faces)
        dist = np.sqrt(igl.point_mesh_squared_distance(local, v, f)[0])
        inside = igl.winding_number(v, f, local) > 0.5
        assert (dist[inside] <= 0.002).all()  # penetration within 2 mm
        assert dist.min() <= 0.005  # still touching
        box_centre = pose[:3, :3] @ (0.5 * (v.min(0) + v.max(0))) + pose[:3, 3]
        centre = 0.5 * (box_centre + np.asarray(meta["joints_3d"])[9])  # object centre and middle knuckle
        np.testing.assert_allclose(centre[:2], 0.0, atol=1e-6)  # on the optical axis
        assert 0.45 <= centre[2] <= 0.55


def test_masks_and_joints_agree_with_the_render(synth_store):
    out, _ = synth_store
    for rec in store.iter_records(out):
        meta, seg = rec[schema.META], rec[schema.SEG]
        assert min(meta["seg_iou"]) > 0.85  # crop masks vs the label map of the render that made the pixels
        uv = (np.asarray(meta["joints_2d"]) + 0.5) / 2 - 0.5
        px = np.clip(np.round(uv).astype(int), 0, seg.shape[0] - 1)
        hand = (seg & schema.SEG_HAND_AMODAL) > 0
        hand = np.pad(hand, 1)[:-2, 1:-1] | np.pad(hand, 1)[2:, 1:-1] | np.pad(hand, 1)[1:-1, :-2] | np.pad(hand, 1)[1:-1, 2:] | hand
        assert hand[px[:, 1], px[:, 0]].mean() >= 0.95


def test_inspect_a_synthetic_store(synth_store, tmp_path):
    from hoidata.store.inspect import inspect_store

    out, _ = synth_store
    png = inspect_store(out, n=4, out=tmp_path / "grid.png")
    assert png.stat().st_size > 10_000


def test_bad_input(ho3d_source, tmp_path):
    with pytest.raises(DataError, match="not a store"):
        render_synthetic(tmp_path, tmp_path / "o1", 2, ho3d_source / "mano", ho3d_source / "models")
    (tmp_path / "bg").mkdir()
    with pytest.raises(DataError, match="no images"):
        _render(ho3d_source, tmp_path / "o2", backgrounds=tmp_path / "bg")
    with pytest.raises(ValueError, match="--count"):
        _render(ho3d_source, tmp_path / "o3", count=0)
