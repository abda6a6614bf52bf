"""augment.upstream on record.upstream_region records: upstream HOISDF's training augmentation (``data/dexycb.py`` /
``data/ho3d.py`` ``data_aug`` + ``data/dataset_util.py``), checked against golden facts of upstream's own train-mode
``__getitem__`` run on the toy frames with its random draws recorded (tests/golden/upstream_train_aug/README.md)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from hoidata import schema
from hoidata.geometry import upstream_crop as up
from hoisdf.data.upstream_augment import COLOR_OPS, UpstreamDraw, augment_view, draw_upstream, footprint_inside
from hoisdf.data.upstream_samples import frame_inputs, upstream_sample

GOLDEN_DIR = Path(__file__).parent / "golden" / "upstream_train_aug"
GOLDEN = json.loads((GOLDEN_DIR / "train_aug.json").read_text())
TOL = 1e-6  # K and boxes (px), anchor, joints and SDF points (m; SDF points in upstream's x3.1 units)
# upstream keeps boxes and K in float32 after 3x3 products whose last bit follows numpy's BLAS kernel: HO-3D's hand box
# (~111 px) moved 2 float32 ulps (1.5e-5 px) under OPENBLAS_CORETYPE=Haswell / Prescott, more than TOL at that size
FLOAT32_RTOL = 4 * float(np.finfo(np.float32).eps)
SDF_SCALE = 3.1
SMALL = ["record.sdf_samples_hand=64", "record.sdf_samples_object=32", 'record.upstream_region=["train"]', 'dataset.splits=["train"]']
GROUPS = {"dexycb_right": ("dexycb_s0", "toy", SMALL), "dexycb_left": ("dexycb_s0", "toy", SMALL),
          "ho3d": ("ho3d_small", "ho3d", SMALL)}


def golden_draw(entry: dict) -> UpstreamDraw:
    d = entry["draw"]
    return UpstreamDraw(tuple(d["jitter"]), d["scale"], d["rotation"], d["blur"], d["brightness"], d["contrast"],
                        d["saturation"], d["hue"], tuple(d["order"]))


def close(got, want, what: str) -> None:
    np.testing.assert_allclose(np.asarray(got, np.float64), np.asarray(want, np.float64), rtol=FLOAT32_RTOL, atol=TOL,
                               err_msg=what)


@pytest.fixture(scope="module")
def region_stores(request, tmp_path_factory):
    """{toy fixture name: store folder} built with record.upstream_region (its train split)."""
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    out = {}
    for fixture, pipeline, overrides in sorted({(f, p, tuple(o)) for f, p, o in GROUPS.values()}):
        root = request.getfixturevalue(fixture)
        out[fixture] = tmp_path_factory.mktemp("region") / "store"
        build_store(load_build_config(pipeline, list(overrides)), root, root / "mano", root / "models", out[fixture],
                    progress=False)
    return out


@pytest.fixture(scope="module")
def region_records(region_stores):
    """{key: decoded record} of every record of the region stores."""
    from hoidata.store import iter_records

    return {rec[schema.META]["key"]: rec for store in region_stores.values() for rec in iter_records(store)}


@pytest.mark.slow
@pytest.mark.parametrize("group", sorted(GOLDEN))
def test_region_records_augment_as_upstream(region_records, group):
    """Upstream's draw replayed on the record: 0 differing pixels before colour, at most 1 level after (the frames
    with a stored image); K, grid boxes, anchor, 2D and 3D joints within 1e-6."""
    from PIL import Image

    for key, want in GOLDEN[group].items():
        rec = region_records[key]
        meta, region = rec[schema.META], rec[schema.IMG]
        K, joints_uv, box21_uv = frame_inputs(meta)
        origin, size = meta["region_origin"].astype(int), meta["frame_size"].astype(int)
        view = augment_view(region, origin, size, K, joints_uv, box21_uv, np.asarray(meta["joints_3d"], np.float32),
                            meta["dataset"], golden_draw(want))
        plain = np.ascontiguousarray(np.asarray(view.plain), np.uint8)
        assert hashlib.sha256(plain.tobytes()).hexdigest() == want["plain_sha256"], key
        if want["final_png"]:
            final = np.asarray(Image.open(GOLDEN_DIR / want["final_png"]).convert("RGB"), np.int16)
            assert np.abs(np.asarray(view.image, np.int16) - final).max() <= 1, key
        close(view.K.astype(np.float32), want["K"], f"{key} K")
        close(view.hand_box, want["bbox_hand"], f"{key} hand box")
        close(view.object_box, want["bbox_obj"], f"{key} object box")
        close(view.anchor, want["obj_center_cam"], f"{key} anchor")
        close((view.joints_uv / 256 * 128).astype(np.float32), want["joint_coord"], f"{key} 2D joints")
        close((view.joints_3d - view.joints_3d[0]) * 1000 / 1000, np.asarray(want["joint_cam_no_trans"]) / 1000, key)
        close(view.joints_3d[0], want["mano_root"], f"{key} hand root")


@pytest.mark.slow
@pytest.mark.parametrize("group", sorted(GOLDEN))
def test_loader_sample_labels_as_upstream(region_records, group):
    """The loader's per-sample step (upstream_sample) on the record: its K, boxes, anchor, hand root, object pose
    (axis-angle and anchor-relative translation) and MANO global rotation against upstream's."""
    import cv2

    for key, want in GOLDEN[group].items():
        rec = region_records[key]
        meta = rec[schema.META]
        sample = {"seg_bits": rec[schema.SEG], "hand_root": np.asarray(meta["joints_3d"][0], np.float32),
                  "mano_pose": np.asarray(meta["mano_pose"], np.float32),
                  "hand_points": np.zeros((4, 3), np.float32)}
        out = upstream_sample(rec[schema.IMG], meta, sample, golden_draw(want), key)
        assert out["img"].shape == (256, 256, 3) and out["seg_bits"].shape == (128, 128) and out["upstream_aug"]
        close(out["K"], want["K"], f"{key} K")
        close(out["grid_hand_box"], want["bbox_hand"], f"{key} hand box")
        close(out["object_box"], want["bbox_obj"], f"{key} object box")
        close(out["object_anchor"], want["obj_center_cam"], f"{key} anchor")
        close(out["hand_root"], want["mano_root"], f"{key} hand root")
        pose = out["object_pose"].astype(np.float64)
        close(cv2.Rodrigues(pose[:3, :3])[0][:, 0], want["obj_rot"], f"{key} object rotation")
        close(pose[:3, 3] - out["object_anchor"], want["rel_obj_trans"], f"{key} object translation")
        close(out["mano_pose"][:3], want["mano_global"], f"{key} MANO global rotation")


@pytest.mark.parametrize("group", sorted(GOLDEN))
def test_sdf_points_turn_as_upstream(group):
    """The loader's points (relative to the hand root) turned by the draw's rotation, then put in upstream's frames
    (hand: the turned root; object: upstream's anchor) x3.1: upstream's values for the same rows (a left hand's rows
    mirrored in x first, as upstream and the project's build both mirror them)."""
    from hoidata.geometry.upstream_crop import rotated_crop_affines as affine_transform

    for key, want in GOLDEN[group].items():
        _, _, rot = affine_transform(np.zeros(2), 100.0, golden_draw(want).rotation, np.eye(3))
        root_turned, anchor = np.asarray(want["mano_root"]), np.asarray(want["obj_center_cam"])
        root = root_turned @ rot.astype(np.float64)  # turned back: rot is orthonormal to float32 precision
        for block, entry in want["sdf"].items():
            xyz = np.asarray(entry["input_xyz"]) * ([-1, 1, 1] if group == "dexycb_left" else 1)  # upstream's flip
            rel = (xyz - root).astype(np.float32)
            turned = rel.dot(rot.T).astype(np.float64)
            ours = turned if block.startswith("hand") else turned + root_turned - anchor
            close(ours * SDF_SCALE, entry["output"], f"{key} {block}")


@pytest.mark.slow  # imports torchvision (seconds)
def test_draw_replays_every_field():
    """A draw given explicitly is what the augmentation uses: two draws differing in one colour factor differ in
    pixels after colour, not before."""
    region = np.random.default_rng(0).integers(0, 256, (300, 300, 3), dtype=np.uint8)
    K = np.array([[600.0, 0, 150], [0, 600, 150], [0, 0, 1]])
    uv = np.array([[120, 120], [180, 170]], np.float32)
    box = np.array([[140, 130], [170, 160]], np.float64)
    joints = np.tile(np.array([0.0, 0.0, 0.5], np.float32), (21, 1))
    a = augment_view(region, (0, 0), (300, 300), K, uv, box, joints, "dexycb", UpstreamDraw(brightness=1.2))
    b = augment_view(region, (0, 0), (300, 300), K, uv, box, joints, "dexycb", UpstreamDraw(brightness=0.8))
    assert np.array_equal(np.asarray(a.plain), np.asarray(b.plain))
    assert not np.array_equal(np.asarray(a.image), np.asarray(b.image))
    with pytest.raises(ValueError, match="permutation"):
        UpstreamDraw(order=("hue", "hue", "contrast", "brightness"))


@pytest.mark.parametrize("rotation", ["dexycb", "uniform"])
def test_region_holds_every_pixel_the_warp_samples(rotation):
    """train_region is large enough: the farthest draws (jitter +-1, scale 1.2, 45 degrees and the draws of a seeded
    stream) sample only inside the square or outside the frame; a square 3 px smaller does not hold them all."""
    hand = np.array([[300, 200], [360, 270]], np.float32)
    obj = np.array([[320, 180], [400, 260]], np.float64)
    centre, side = up.base_square(hand, obj, (640, 480))
    x0, y0, n = up.train_region(centre, side)
    draws = [UpstreamDraw((sx, sy), 1.2, np.pi / 4) for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)]
    rng = np.random.default_rng(5)
    draws += [draw_upstream(rng, rotation) for _ in range(200)]
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])

    def holds(x0, y0, n):
        from hoidata.geometry.upstream_crop import rotated_crop_affines as affine_transform

        for d in draws:
            c = centre + up.CENTER_JITTER * side * np.asarray(d.jitter)
            affine, _, _ = affine_transform(c, side * np.float64(d.scale), d.rotation, K)
            if not footprint_inside(affine, (x0, y0), n, (10 ** 4, 10 ** 4)):
                return False
        return True

    assert holds(x0, y0, n)
    assert not holds(x0 + 3, y0 + 3, n - 6)


def test_color_order_is_a_permutation_per_sample():
    """Each draw carries its own order (upstream shuffles per sample): 24 orders appear over 2000 draws."""
    rng = np.random.default_rng(1)
    orders = {draw_upstream(rng, "dexycb").order for _ in range(2000)}
    assert len(orders) == 24 and all(sorted(o) == sorted(COLOR_OPS) for o in orders)


@pytest.mark.slow
def test_loader_batches_are_upstream_augmented(region_stores):
    """build_dataset(upstream=True) yields 256 px samples marked upstream_aug, seeded per (seed, epoch, key); the
    batch passes augment_batch unchanged except the heatmap, masks and anchor it adds."""
    import torch

    from hoisdf.data.augment import AugmentSettings, augment_batch
    from hoisdf.data.loader import StoreSpec, build_dataset

    def first(epoch):
        data = build_dataset([StoreSpec(region_stores["dexycb_s0"])], 4, None, 0, 8, 8, training=True,
                             shuffle_buffer=0, upstream=True)
        data.set_epoch(epoch)
        return next(iter(data))

    batch, again, other = first(0), first(0), first(1)
    assert batch["img"].shape == (4, 3, 256, 256) and batch["img"].dtype == torch.uint8
    assert bool(batch["upstream_aug"].all()) and batch["key"] == again["key"]
    assert torch.equal(batch["img"], again["img"]) and not torch.equal(batch["img"], other["img"])
    out = augment_batch(batch, AugmentSettings(input_size=256, upstream=True), None, train=True)
    assert out["img"].shape == (4, 3, 256, 256) and out["seg"].shape == (4, 4, 128, 128)
    assert out["heatmap"].shape == (4, 1, 128, 128) and torch.equal(out["obj_center"], batch["object_anchor"])
    assert torch.equal(out["K"], batch["K"]) and torch.equal(out["hand_box"], batch["hand_box"])


@pytest.mark.slow
def test_each_augmentation_refuses_the_other_records(region_stores, tiny_store):
    """A region record under the project's augmentation, a project record under augment.upstream: one DataError
    naming the record."""
    from hoidata.errors import DataError
    from hoisdf.data.loader import StoreSpec, build_dataset

    for store, upstream, words in ((region_stores["dexycb_s0"], False, "upstream_region"),
                                   (tiny_store, True, "record.upstream_region")):
        data = build_dataset([StoreSpec(store)], 2, None, 0, 8, 8, training=True, upstream=upstream)
        data.set_epoch(0)
        with pytest.raises(DataError, match=words):
            next(iter(data))


@pytest.mark.slow
def test_region_codec_rules(region_records):
    """A region record reads back as it was written; its fields come all together, with img.png only."""
    from hoidata.errors import DataError
    from hoidata.store import decode_record, encode_record

    rec = next(r for r in region_records.values() if r[schema.META]["kind"] == schema.FULL)
    meta = dict(rec[schema.META])
    members = encode_record(meta["key"], rec[schema.IMG], rec[schema.SEG], rec[schema.HEATMAP], rec[schema.SDF], meta)
    assert schema.IMG_LOSSLESS in members and schema.IMG not in members
    back = decode_record(members, "<test>")
    assert np.array_equal(back[schema.IMG], rec[schema.IMG]) and back[schema.META]["region"] == schema.UPSTREAM_REGION
    for broken in ({k: v for k, v in meta.items() if k != "frame_size"}, {**meta, "region": "other"}):
        with pytest.raises(DataError, match="region"):
            encode_record(meta["key"], rec[schema.IMG], rec[schema.SEG], rec[schema.HEATMAP], rec[schema.SDF], broken)


DRAWS = json.loads((GOLDEN_DIR / "draws.json").read_text())
ECDF_TOL = 0.03  # KS two-sample critical value for 10^4 + 10^4 draws at alpha 1e-3 is 0.0276; seeds fixed
ORDER_TOL = 0.015  # per order frequency (1/24 each; the difference of two 10^4-draw estimates has SD 0.003)


def draw_columns(draws: list[UpstreamDraw]) -> dict[str, np.ndarray]:
    return {"jitter_x": np.array([d.jitter[0] for d in draws]), "jitter_y": np.array([d.jitter[1] for d in draws]),
            **{k: np.array([getattr(d, k) for d in draws]) for k in ("scale", "blur", "brightness", "contrast",
                                                                     "saturation", "hue", "rotation")}}


@pytest.mark.parametrize("dataset, rule", [("dexycb", "dexycb"), ("ho3d", "uniform")])
def test_draws_follow_upstreams(dataset, rule):
    """10^4 draws of draw_upstream (fixed seed) against 10^4 recorded from upstream's own data_aug: the largest gap
    between the two empirical CDFs on a 101-point grid of each quantity (the two-sample KS statistic there; the
    grid holds DexYCB's atom at rotation 0 and the scale clip's atoms at 0.8 and 1.2) below ECDF_TOL, and the 24
    colour orders' frequencies within ORDER_TOL."""
    want = DRAWS["datasets"][dataset]
    rng = np.random.default_rng(2026)
    draws = [draw_upstream(rng, rule) for _ in range(DRAWS["draws"])]
    for name, values in draw_columns(draws).items():
        grid = np.linspace(*want["ecdf"][name]["range"], DRAWS["grid_points"])
        ours = np.searchsorted(np.sort(values), grid, side="right") / len(values)
        gap = np.abs(ours - np.asarray(want["ecdf"][name]["cdf"])).max()
        assert gap < ECDF_TOL, (dataset, name, gap)
    orders = [" ".join(d.order) for d in draws]
    for order, freq in zip(want["orders"], want["order_freq"]):
        assert abs(orders.count(order) / len(orders) - freq) < ORDER_TOL, (dataset, order)


def test_build_refuses_a_region_it_cannot_make():
    """record.upstream_region on a dataset upstream never trained on, or on splits that are upstream test crops:
    one DataError naming the key, before any frame is read."""
    from hoidata.errors import DataError
    from hoidata.records.settings import load_build_config

    assert load_build_config("toy", ['record.upstream_region=["train"]']).record.upstream_region == ("train",)
    for overrides in (['dataset.name="hot3d_clips"', 'record.upstream_region=["train"]'],
                      ['record.crop="upstream"', 'record.crop_splits=["train"]', 'record.upstream_region=["train"]']):
        with pytest.raises(DataError, match="record.upstream_region"):
            load_build_config("toy", overrides)


@pytest.mark.slow
def test_the_dexycb_preset_trains_in_full_on_a_region_store(region_stores, mano_dir, tmp_path):
    """``python -m hoisdf.train --config dexycb`` on a record.upstream_region store: the upstream recipe in full
    (upstream's augmentation in the loader, its heatmap target, raw 6D, fp32) runs its steps; only the network's
    widths are made small."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    small = ["model.depth=18", "model.d_model=64", "model.ff=128", "model.hand_layers=1", "model.decoder_layers=1",
             "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96", "model.token_hidden=[48]",
             "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=12", "model.chunk=1000", 'model.weights=""',
             "train.batch_size=2", "train.workers=0", "train.max_steps=2"]
    argv = [sys.executable, "-m", "hoisdf.train", "--config", "dexycb", "--shards", str(region_stores["dexycb_s0"]),
            "--mano", str(mano_dir), "--out", str(tmp_path / "run"), "--no-progress", *small]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=600, cwd=root,
                          env={**os.environ, "PYTHONPATH": str(root), "PYOPENGL_PLATFORM": "egl"})
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    for key in ("augment.upstream = true", 'augment.heatmap_target = "upstream"', 'model.rot6d = "raw"',
                "train.bf16 = false"):
        assert any(key in line and "recipe upstream" in line for line in lines), key
    assert "done: epoch 0, 2 steps" in done.stdout and (tmp_path / "run" / "checkpoints" / "last.pt").exists()


def _frame_members(store: Path) -> dict:
    """{key: (member name, bytes)} of the image member of each record of ``store``."""
    from hoidata.store import read_shard_members

    out = {}
    for shard in sorted(store.glob("shard-*.tar")):
        for members in read_shard_members(shard):
            name = schema.image_member([m for m in members if not m.startswith("__")])
            out[members["__key__"]] = (name, bytes(members[name]))
    return out


@pytest.mark.slow
def test_region_records_keep_the_frame_file_as_shipped(request, region_stores, region_records):
    """A region record stores the original frame's file byte for byte (frame.jpg for DexYCB's JPEG, frame.png for
    the toy HO-3D's PNG: never re-encoded); it reads back as Pillow reads that file, flipped for a left hand, and its
    img is that frame's square at region_origin (what the masks sit on)."""
    import io

    from PIL import Image

    from hoidata.store import FRAME_IMAGE

    for fixture, store in region_stores.items():
        root = request.getfixturevalue(fixture)
        shipped = {p.read_bytes() for p in root.rglob("*") if p.suffix in (".jpg", ".png") and
                   (p.name.startswith("color_") or p.parent.name == "rgb")}
        for key, (name, data) in _frame_members(store).items():
            rec = region_records[key]
            meta = rec[schema.META]
            assert name == (schema.FRAME_JPG if meta["dataset"] == "dexycb" else schema.FRAME_PNG) and data in shipped
            want = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
            assert np.array_equal(rec[FRAME_IMAGE], want[:, ::-1] if meta["mirrored"] else want), key
            x0, y0 = meta["region_origin"].astype(int)
            assert np.array_equal(rec[schema.IMG], up.cut_region(rec[FRAME_IMAGE], x0, y0, rec[schema.IMG].shape[0]))


@pytest.mark.slow
@pytest.mark.parametrize("group", sorted(GOLDEN))
def test_the_loader_warps_the_stored_frame_as_upstream(region_records, group):
    """The loader's path (the whole stored frame warped, no rebuilt frame) against upstream's golden pixels, and
    equal value for value to the sample of the same record stored the older way (its square as img.png)."""
    from hoidata.store import FRAME_IMAGE, decode_record, encode_record

    for key, want in GOLDEN[group].items():
        rec = region_records[key]
        meta, draw = rec[schema.META], golden_draw(want)
        K, joints_uv, box21_uv = frame_inputs(meta)
        view = augment_view(rec[FRAME_IMAGE], (0, 0), meta["frame_size"].astype(int), K, joints_uv, box21_uv,
                            np.asarray(meta["joints_3d"], np.float32), meta["dataset"], draw)
        assert hashlib.sha256(np.asarray(view.plain).tobytes()).hexdigest() == want["plain_sha256"], key
        old = decode_record(encode_record(key, rec[schema.IMG], rec[schema.SEG], rec[schema.HEATMAP], rec[schema.SDF],
                                          dict(meta)), "<old store>")
        assert FRAME_IMAGE not in old
        sample = {"seg_bits": rec[schema.SEG], "hand_root": np.asarray(meta["joints_3d"][0], np.float32),
                  "mano_pose": np.asarray(meta["mano_pose"], np.float32), "hand_points": np.ones((4, 3), np.float32)}
        new_way = upstream_sample(rec[schema.IMG], meta, sample, draw, key, rec[FRAME_IMAGE])
        old_way = upstream_sample(old[schema.IMG], old[schema.META], sample, draw, key)
        assert new_way.keys() == old_way.keys()
        for name, value in new_way.items():
            assert np.array_equal(value, old_way[name]), (key, name)


@pytest.mark.slow
def test_frame_member_codec_rules(region_records):
    """A frame member whose header disagrees with frame_size, one cut short, one on a record without the region
    fields, or one beside img.png: one DataError naming the record (or its members)."""
    import cv2

    from hoidata.errors import DataError
    from hoidata.store import decode_record, encode_record

    rec = next(r for r in region_records.values() if r[schema.META]["dataset"] == "dexycb")
    meta, key = dict(rec[schema.META]), rec[schema.META]["key"]
    arrays = (rec[schema.IMG], rec[schema.SEG], rec[schema.HEATMAP], rec[schema.SDF])
    jpeg = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    members = encode_record(key, *arrays, meta, jpeg)
    assert schema.FRAME_JPG in members and members[schema.FRAME_JPG] == jpeg and schema.IMG_LOSSLESS not in members
    small = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes()
    for frame, words in ((small, "frame_size"), (jpeg[:-40], "truncated")):
        with pytest.raises(DataError, match=words):
            encode_record(key, *arrays, meta, frame)
        with pytest.raises(DataError, match=f"{key}.frame.jpg"):
            decode_record({"__key__": key, **members, schema.FRAME_JPG: frame}, "<test>")
    plain = {k: v for k, v in meta.items() if k not in schema.REGION_FIELDS}
    with pytest.raises(DataError, match="upstream-region record"):
        encode_record(key, *arrays, plain, jpeg)
    with pytest.raises(DataError, match="expected exactly"):
        decode_record({**members, schema.IMG_LOSSLESS: encode_record(key, *arrays, meta)[schema.IMG_LOSSLESS]}, "<t>")
