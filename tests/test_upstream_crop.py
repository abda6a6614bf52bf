"""record.crop = "upstream": records equal to upstream HOISDF's test loader (``data/dexycb.py`` / ``data/ho3d.py``
``__getitem__`` -> ``data_crop`` + ``data/dataset_util.py``), checked against golden facts of upstream's own code
run on the toy frames (tests/golden/upstream_crops/README.md says how they were made), and evaluation using them."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hoidata import schema, store
from hoidata.errors import DataError
from hoidata.geometry.upstream_crop import box21_upstream, pixel_affine, scale_translate
from hoidata.objects import load_points, object_points_path
from hoidata.build_sdf import build_store, read_frames
from hoidata.records.settings import load_build_config
from hoidata.records.upstream import upstream_view

GOLDEN = json.loads((Path(__file__).parent / "golden" / "upstream_crops" / "crops.json").read_text())
SMALL = ["record.sdf_samples_hand=64", "record.sdf_samples_object=32", 'record.crop="upstream"']
ANCHOR_M = 1e-6  # the object anchor's tolerance against upstream's (metres)
LEFT = ['dataset.splits=["train"]', 'dataset.sides=["left"]', "dataset.frame_stride=3", 'record.crop_splits=["train"]']


def sha(img: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(img, np.uint8).tobytes()).hexdigest()


def assert_as_upstream(key: str, img, K, hand_box, object_box, anchor, golden: dict) -> None:
    """0 differing pixels, K and boxes within 1e-3 px, the anchor within 1e-6 m (a computed float: compared by
    value, docs/development.md, "Floating-point goldens"). The crop is uint8 pixels picked by a nearest-neighbour
    warp, no arithmetic on their values: its bytes are the contract, pinned by their sha256."""
    want = golden[key]
    assert sha(img) == want["sha256"], key
    np.testing.assert_allclose(np.asarray(K, np.float64), want["K"], rtol=0, atol=1e-3)
    np.testing.assert_allclose(np.asarray(hand_box, np.float64), want["grid_hand_box"], rtol=0, atol=1e-3)
    np.testing.assert_allclose(np.asarray(object_box, np.float64), want["grid_object_box"], rtol=0, atol=1e-3)
    np.testing.assert_allclose(np.asarray(anchor, np.float64), want["object_anchor"], rtol=0, atol=ANCHOR_M,
                               err_msg=key)


def _frames(root: Path, pipeline: str, overrides) -> dict:
    frames, _ = read_frames(load_build_config(pipeline, overrides), root, root / "mano")
    return {schema.record_key(f.dataset, f.split, f.frame_id): f for f in frames}


@pytest.mark.slow
@pytest.mark.parametrize("fixture, pipeline, overrides", [
    ("dexycb_s0", "toy", ['dataset.splits=["test"]']),
    ("dexycb_s0", "toy", LEFT),
    ("ho3d_small", "ho3d_eval", []),
])
def test_views_equal_upstream_data_crop(request, fixture, pipeline, overrides):
    """The geometry alone (no store): every golden frame of the split, right, left (flipped) and HO-3D's."""
    root, golden = request.getfixturevalue(fixture), GOLDEN[fixture]
    frames = {k: f for k, f in _frames(root, pipeline, overrides).items() if k in golden}
    assert frames and all(f.mirror == golden[k]["mirrored"] for k, f in frames.items())
    for key, frame in frames.items():
        view = upstream_view(frame, box21_upstream(load_points(object_points_path(root / "models", frame.object_name))))
        assert_as_upstream(key, view.image, view.K, view.grid_hand_box, view.grid_object_box, view.anchor, golden)


@pytest.mark.slow
def test_left_hand_is_flipped_as_upstream_flips_it(dexycb_s0):
    """Without the flip the crop is another one: the golden left-hand facts pin upstream's cx' = W - cx - 1."""
    from dataclasses import replace

    golden = GOLDEN["dexycb_s0"]
    key, frame = next((k, f) for k, f in _frames(dexycb_s0, "toy", LEFT).items() if golden.get(k, {}).get("mirrored"))
    box3d = box21_upstream(load_points(object_points_path(dexycb_s0 / "models", frame.object_name)))
    flipped, unflipped = upstream_view(frame, box3d), upstream_view(replace(frame, mirror=False), box3d)
    assert sha(flipped.image) == golden[key]["sha256"] != sha(unflipped.image)
    assert np.array_equal(flipped.image, np.asarray(upstream_view(frame, box3d).image))  # deterministic


def test_pil_pixels_follow_the_shifted_affine():
    """PIL's nearest warp samples A^-1 (x + 1/2): in the project's convention the pixels follow pixel_affine(A),
    0.5 (1 - a) px off the K upstream returns (which the released weights were trained with)."""
    from PIL import Image

    src = np.arange(640 * 480 * 3, dtype=np.uint32).reshape(480, 640, 3) % 251
    affine = scale_translate(np.array([300, 200]), np.float32(173.0), 256).astype(np.float32)
    from hoidata.geometry.upstream_crop import warp_nearest

    out = warp_nearest(Image.fromarray(src.astype(np.uint8)), affine, 256)
    inv = np.linalg.inv(pixel_affine(affine))
    for x, y in [(0, 0), (17, 99), (255, 255), (128, 3)]:
        u, v = inv[:2, :2] @ [x, y] + inv[:2, 2]
        assert np.array_equal(out[y, x], src[int(np.floor(v + 0.5)), int(np.floor(u + 0.5))].astype(np.uint8))


@pytest.fixture(scope="module")
def upstream_test_store(dexycb_s0, tmp_path_factory):
    out = tmp_path_factory.mktemp("upstream_test") / "store"
    build_store(load_build_config("toy", ['dataset.splits=["test"]', *SMALL]), dexycb_s0, dexycb_s0 / "mano",
                dexycb_s0 / "models", out, progress=False)
    return out


def _check_store(path: Path, golden: dict, n: int) -> None:
    assert store.verify_store(path).ok
    names = [m.name for m in __import__("tarfile").open(next(path.glob("shard-*.tar")))]
    assert names and not any(name.endswith(".img.jpg") for name in names)  # lossless img.png only
    seen = 0
    for rec in store.iter_records(sorted(path.glob("shard-*.tar"))):
        meta = rec[schema.META]
        assert meta["crop"] == schema.UPSTREAM_CROP and rec[schema.IMG].shape == (256, 256, 3)
        if rec[store.KEY] in golden:
            seen += 1
            assert meta["mirrored"] == golden[rec[store.KEY]]["mirrored"]
            assert_as_upstream(rec[store.KEY], rec[schema.IMG], meta["K"], meta["grid_hand_box"],
                               meta["grid_object_box"], meta["object_anchor"], golden)
    assert seen == n


@pytest.mark.slow
def test_dexycb_test_records_equal_upstream(upstream_test_store):
    _check_store(upstream_test_store, GOLDEN["dexycb_s0"], 6)


@pytest.mark.slow
def test_left_hand_records_equal_upstream(dexycb_s0, tmp_path):
    build_store(load_build_config("toy", [*LEFT, *SMALL]), dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models",
                tmp_path / "store", progress=False)
    _check_store(tmp_path / "store", GOLDEN["dexycb_s0"], 8)  # frames 0 and 3 of 4 left sequences


@pytest.mark.slow
def test_ho3d_evaluation_records_equal_upstream(ho3d_small, tmp_path):
    build_store(load_build_config("ho3d_eval", ['record.crop="upstream"']), ho3d_small, ho3d_small / "mano",
                ho3d_small / "models", tmp_path / "store", progress=False)
    _check_store(tmp_path / "store", GOLDEN["ho3d_small"], 3)
    rec = next(store.iter_records(sorted((tmp_path / "store").glob("shard-*.tar"))))
    assert rec[schema.META]["kind"] == schema.EVAL and np.isclose(rec[schema.META]["object_anchor"][2], 0.5244322)


def _tiny_run(path: Path, mano_dir: Path) -> Path:
    """An untrained tiny HOISDF that takes 256 px inputs: upstream crops reach it as stored."""
    from hoidata.hand import load_mano
    from hoisdf.config import load_train_config
    from hoisdf.model import build_model
    from hoisdf.training.checkpoint import save_checkpoint

    cfg = load_train_config(None, ["model.depth=18", "model.image_size=256", "model.hand_queries=32", "model.object_queries=16",
                                   "model.grid_resolution=16", "model.hand_layers=1", "model.decoder_layers=1",
                                   "model.object_layers=1"])
    torch.manual_seed(0)
    model = build_model(cfg.model, load_mano(mano_dir))
    payload = {"model": model.state_dict(), "config": cfg.as_dict(), "progress": {}}
    save_checkpoint(path / "checkpoints" / "last.pt", payload)
    return path


@pytest.mark.slow
def test_network_receives_upstream_inputs(upstream_test_store, dexycb_s0, tmp_path):
    """The batch the model gets in evaluation: the stored crop as is in [0, 1], upstream's K, boxes and anchor."""
    from hoidata.hand import load_mano
    from hoisdf.evaluation.inference import infer, load_for_eval

    mano = load_mano(dexycb_s0 / "mano", side="right")
    model, config, _ = load_for_eval(_tiny_run(tmp_path / "run", dexycb_s0 / "mano"), mano, torch.device("cpu"))
    seen, forward = [], model.forward

    def spy(batch, **kw):
        seen.append(batch)
        return forward(batch, **kw)

    model.forward = spy
    col = infer(model, mano, config, [upstream_test_store], 4, torch.device("cpu"), progress=False)
    records = {r[store.KEY]: r for r in store.iter_records(sorted(upstream_test_store.glob("shard-*.tar")))}
    golden = GOLDEN["dexycb_s0"]
    for batch in seen:
        for i, key in enumerate(batch["key"]):
            img = batch["img"][i]
            assert torch.equal(img, torch.from_numpy(records[key][schema.IMG]).permute(2, 0, 1).float() / 255)
            assert_as_upstream(key, records[key][schema.IMG], batch["K"][i], batch["hand_box"][i],
                               batch["object_box"][i], batch["obj_center"][i], golden)
    anchors = np.asarray([golden[k]["object_anchor"] for k in col.keys], np.float64)
    assert len(col.keys) == 6
    np.testing.assert_allclose(col.get("obj_center").astype(np.float64), anchors, rtol=0, atol=ANCHOR_M)


@pytest.mark.slow
def test_evaluate_cli_on_an_upstream_crop_store(upstream_test_store, dexycb_s0, tmp_path):
    run, out = _tiny_run(tmp_path / "run", dexycb_s0 / "mano"), tmp_path / "eval"
    proc = subprocess.run([sys.executable, "-m", "hoisdf.evaluate", "--ckpt", str(run), "--shards",
                           str(upstream_test_store), "--mano", str(dexycb_s0 / "mano"), "--out", str(out),
                           "--workers", "0", "--no-progress", "--plausibility", "0"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "MJE" in proc.stdout and "note:" not in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["samples"] == 6 and metrics["upstream_crop_records"] == 6 and metrics["notes"] == []
    assert (out / "per_object.csv").is_file() and all(Path(p).is_file() for p in metrics["files"].values())
    assert "wrote" in proc.stdout and "metrics.json" in proc.stdout


def test_crop_note_names_the_mismatch():
    from types import SimpleNamespace

    from hoisdf.evaluate import crop_note

    upstream = SimpleNamespace(pixel_convention="upstream")
    assert crop_note(upstream, np.array([1.0, 0.0, 1.0]), 3).startswith("note: ") and "1 of 3" in crop_note(
        upstream, np.array([1.0, 0.0, 1.0]), 3)
    assert "2 of 2" in crop_note({"pixel_convention": "upstream"}, None, 2)
    assert crop_note(upstream, np.ones(3), 3) is None
    assert crop_note(SimpleNamespace(), np.zeros(3), 3) is None  # a run from before the setting: no note
    assert crop_note(SimpleNamespace(pixel_convention="project"), np.zeros(3), 3) is None


@pytest.mark.slow
def test_training_refuses_upstream_crop_records(upstream_test_store):
    from hoisdf.data import StoreSpec, build_dataset

    data = build_dataset([StoreSpec(upstream_test_store)], 2, n_hand=8, n_object=8, training=True, epoch_samples=2)
    with pytest.raises(DataError, match="upstream-crop record"):
        next(iter(data))


@pytest.mark.parametrize("overrides, field", [
    (['record.crop="pil"'], "record.crop"),
])
def test_bad_crop_settings_are_one_line(overrides, field):
    with pytest.raises(DataError, match=field):
        load_build_config("toy", overrides)


def test_ho3d_upstream_crop_is_for_the_evaluation_split():
    with pytest.raises(DataError, match="record.crop_splits"):
        load_build_config("ho3d", ['record.crop="upstream"', 'record.crop_splits=["train"]'])


def test_upstream_crop_codec_rules(tmp_path):
    """img.png exactly when meta holds the crop fields (all or none); bit-exact round trip; the tar holds img.png."""
    from test_store import make_record

    from hoidata.store import ShardWriter, decode_record, encode_record

    key, img, seg, hm, sdf, meta = make_record(0)
    img = np.random.default_rng(1).integers(0, 256, img.shape, dtype=np.uint8)  # noise: JPEG would change it
    crop = {"crop": "upstream", "grid_hand_box": np.arange(4.0), "grid_object_box": np.arange(4.0) + 1,
            "object_anchor": np.array([0.01, -0.02, 0.5], np.float32)}
    members = encode_record(key, img, seg, hm, sdf, {**meta, **crop})
    assert schema.IMG_LOSSLESS in members and schema.IMG not in members
    out = decode_record(members, "here")
    assert np.array_equal(out[schema.IMG], img) and out[schema.META]["crop"] == "upstream"
    assert np.array_equal(out[schema.META]["object_anchor"].astype(np.float32), crop["object_anchor"])
    with ShardWriter(tmp_path, 4) as writer:
        writer.add(key, members)
    assert np.array_equal(next(store.iter_records([tmp_path / store.shard_name(0)]))[schema.IMG], img)
    plain = encode_record(key, img, seg, hm, sdf, meta)
    bad = [({**plain, schema.IMG_LOSSLESS: plain[schema.IMG]}, "expected exactly"),  # both images
           ({**members, schema.META: plain[schema.META]}, "stores its image as img.png"),  # PNG, no crop fields
           ({**plain, schema.META: members[schema.META]}, "stores its image as img.png")]  # crop fields, JPEG
    for case, message in bad:
        with pytest.raises(DataError, match=message):
            decode_record(case, "here")
    with pytest.raises(DataError, match="come together"):
        encode_record(key, img, seg, hm, sdf, {**meta, "crop": "upstream"})
    with pytest.raises(DataError, match="'crop'"):
        encode_record(key, img, seg, hm, sdf, {**meta, **crop, "crop": "project"})


def test_an_empty_crop_box_is_a_reason_not_a_crash():
    from PIL import Image

    from hoidata.geometry.upstream_crop import upstream_crop

    outside = np.array([[700.0, 500.0], [720.0, 530.0]], np.float32)  # hand and object both beyond 640 x 480
    with pytest.raises(ValueError, match="empty"):
        upstream_crop(Image.new("RGB", (640, 480)), np.eye(3), outside, outside + 5, 1.1, np.float32(0.5), True)
