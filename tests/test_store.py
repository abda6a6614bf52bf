"""The store: record encoding, deterministic atomic shards, the zarr index, verification and resume."""

from __future__ import annotations

import hashlib
import io
import json
import os
import socket
import tarfile
import warnings

import cv2
import numpy as np
import pytest

from hoidata.datasets.frame import Skip
from hoidata.errors import DataError
from hoidata.schema import (
    HEATMAP,
    IMG,
    MEMBERS,
    META,
    META_FIELDS,
    SCHEMA_VERSION,
    SDF,
    SEG,
)
from hoidata.store import (
    INDEX_NAME,
    KEY,
    ShardInfo,
    ShardWriter,
    completed_shards,
    decode_record,
    encode_record,
    index_labels,
    iter_records,
    read_index,
    read_shard_members,
    shard_name,
    verify_store,
    write_index,
    write_shard,
)

CROP = 32  # small crops keep the whole file well under a few seconds
SCALARS = {"schema_version": SCHEMA_VERSION, "kind": "full", "dataset": "toy", "split": "train", "side": "right",
           "mirrored": False, "tip_convention": "manopth", "object_name": "002_master_chef_can", "object_id": 1, "sample_index": -1,
           "source": {"path": "seq0/labels_000.npz", "index": 0}}


def make_record(i: int, n_sdf: int = 40):
    """Arrays and a complete meta dict for record i: smooth image (JPEG-friendly), random masks and SDF."""
    rng = np.random.default_rng(i)
    key = f"toy-train-f{i:04d}"
    yy, xx = np.mgrid[:CROP, :CROP]
    img = np.stack([xx * 6, yy * 6, (xx + yy) * 3 + i], axis=-1).astype(np.uint8)
    seg = rng.integers(0, 16, (CROP // 2, CROP // 2), dtype=np.uint8)
    hm = rng.integers(0, 256, (CROP // 2, CROP // 2), dtype=np.uint8)
    sdf = rng.integers(-3000, 3000, (n_sdf, 6)).astype(np.int16)
    sdf[:, 5] = rng.integers(-1, 16, n_sdf)
    meta = {**SCALARS, "key": key, "frame_id": f"f{i:04d}"}
    for name, (shape, _) in META_FIELDS.items():
        if shape is not None:
            meta[name] = rng.normal(size=shape).astype(np.float32)
    meta["sdf_counts"] = np.array([n_sdf - 10, 6, 4])
    return key, img, seg, hm, sdf, meta


def encoded(n: int) -> list[tuple[str, dict[str, bytes]]]:
    return [(make_record(i)[0], encode_record(*make_record(i))) for i in range(n)]


def build_store(store, n=7, per_shard=3):
    """A complete store: shards through ShardWriter, then the index."""
    records = encoded(n)
    with ShardWriter(store, per_shard) as writer:
        for key, members in records:
            writer.add(key, members)
    metas = [make_record(i)[5] for i in range(n)]
    meshes = {"002_master_chef_can": (np.random.default_rng(0).normal(size=(8, 3)), np.array([[0, 1, 2], [2, 3, 7]]))}
    write_index(store, writer.shards, index_labels(metas), meshes,
                [Skip("f9999", "hand not visible", "seq0/f9999.jpg"), ("f9998", "no object", "")],
                {"crop_size": CROP, "root": store}, {"git_commit": "0123abc"})
    return records, writer.shards


def test_round_trip_is_exact_except_jpeg():
    key, img, seg, hm, sdf, meta = make_record(3)
    members = encode_record(key, img, seg, hm, sdf, meta)
    assert list(members) == list(MEMBERS)
    assert members == encode_record(key, img, seg, hm, sdf, meta)  # deterministic bytes
    out = decode_record({KEY: key, **members}, "test.tar")
    assert out[KEY] == key
    assert np.abs(out[IMG].astype(int) - img).mean() < 2.0  # quality 95 on a smooth image
    np.testing.assert_array_equal(out[SEG], seg)
    np.testing.assert_array_equal(out[HEATMAP], hm)
    np.testing.assert_array_equal(out[SDF], sdf)
    assert out[SDF].dtype == np.int16
    for name, value in meta.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(out[META][name], value)
        else:
            assert out[META][name] == value
    assert json.loads(members[META]) == json.loads(json.dumps(json.loads(members[META]), sort_keys=True))


def test_encode_refuses_bad_arrays():
    key, img, seg, hm, sdf, meta = make_record(0)
    with pytest.raises(DataError, match="seg.png"):
        encode_record(key, img, seg[:-1], hm, sdf, meta)
    with pytest.raises(DataError, match="sdf.npy"):
        encode_record(key, img, seg, hm, sdf.astype(np.float32), meta)
    with pytest.raises(DataError, match="'joints_3d'"):
        encode_record(key, img, seg, hm, sdf, {**meta, "joints_3d": np.zeros((20, 3))})
    with pytest.raises(DataError, match="keys may only"):
        encode_record("toy.train.0", img, seg, hm, sdf, meta)


@pytest.mark.parametrize("damage, match", [
    (lambda m: {**m, "img.png": m.pop(IMG)}, "expected exactly"),
    (lambda m: {**m, "extra.txt": b"x"}, "expected exactly"),
    (lambda m: {**m, SDF: _npy(np.zeros((4, 6), np.int32))}, "sdf.npy"),
    (lambda m: {**m, SDF: _npy(np.zeros((4, 5), np.int16))}, "sdf.npy"),
    (lambda m: {**m, META: _meta_without(m[META], "hand_root")}, "missing fields \\['hand_root'\\]"),
    (lambda m: {**m, META: _meta_with(m[META], schema_version=SCHEMA_VERSION + 1)}, "schema_version"),
    (lambda m: {**m, META: _meta_with(m[META], key="toy-train-other")}, "differs from the record key"),
    (lambda m: {**m, SEG: m[HEATMAP][:40]}, "hm.png|seg.png"),
    (lambda m: {**m, IMG: m[SEG]}, "img.jpg"),
])
def test_decode_rejects(damage, match):
    key, *arrays = make_record(1)
    members = damage(dict(encode_record(key, *arrays)))
    with pytest.raises(DataError, match=match) as err:
        decode_record({KEY: key, **members}, "shard-000042.tar")
    assert str(err.value).startswith("shard-000042.tar: ")
    assert key in str(err.value)


def _npy(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def _meta_without(data: bytes, name: str) -> bytes:
    meta = json.loads(data)
    del meta[name]
    return json.dumps(meta).encode()


def _meta_with(data: bytes, **changes) -> bytes:
    return json.dumps({**json.loads(data), **changes}).encode()


def test_shards_are_deterministic(tmp_path):
    infos = []
    for name in ("a", "b"):
        with ShardWriter(tmp_path / name, 3) as writer:
            for key, members in encoded(7):
                writer.add(key, {m: members[m] for m in reversed(MEMBERS)})  # dict order must not matter
        infos.append(writer.shards)
    assert infos[0] == infos[1]
    assert [(s.name, s.count, s.first_key, s.last_key) for s in infos[0]] == [
        ("shard-000000.tar", 3, "toy-train-f0000", "toy-train-f0002"),
        ("shard-000001.tar", 3, "toy-train-f0003", "toy-train-f0005"),
        ("shard-000002.tar", 1, "toy-train-f0006", "toy-train-f0006")]
    for info in infos[0]:
        data = (tmp_path / "a" / info.name).read_bytes()
        assert data == (tmp_path / "b" / info.name).read_bytes()
        assert (len(data), hashlib.sha256(data).hexdigest()) == (info.size, info.sha256)
    with tarfile.open(tmp_path / "a" / "shard-000000.tar") as tar:
        first = tar.getmembers()[:5]
    assert [m.name for m in first] == [f"toy-train-f0000.{m}" for m in MEMBERS]
    assert {(m.mtime, m.uid, m.gid, m.uname, m.gname, m.mode) for m in first} == {(0, 0, 0, "", "", 0o644)}


def test_shards_appear_atomically(tmp_path):
    records = encoded(5)
    writer = ShardWriter(tmp_path, 3)
    for key, members in records[:2]:
        assert writer.add(key, members) is None
    assert not list(tmp_path.glob("shard-*.tar")) and list(tmp_path.glob("shard-000000.tar.*.tmp"))  # per writer
    assert writer.add(*records[2]).name == "shard-000000.tar"
    assert [p.name for p in tmp_path.iterdir()] and not list(tmp_path.glob("*.tmp"))
    writer.add(*records[3])
    assert not (tmp_path / "shard-000001.tar").exists()
    writer.close()
    assert (tmp_path / "shard-000001.tar").exists() and not list(tmp_path.glob("*.tmp"))
    assert sorted(p.name for p in tmp_path.glob("shard-*.json")) == ["shard-000000.json", "shard-000001.json"]
    # an exception inside the context drops the unfinished shard instead of completing it
    with pytest.raises(RuntimeError), ShardWriter(tmp_path / "broken", 3) as broken:
        broken.add(*records[0])
        raise RuntimeError("interrupted")
    assert list((tmp_path / "broken").iterdir()) == []


def test_index_round_trip(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no UnstableSpecificationWarning: only spec'd zarr v3 data types
        records, shards = build_store(tmp_path)
        index = read_index(tmp_path)
    assert index.keys == [key for key, _ in records]
    assert index.shards == shards
    np.testing.assert_array_equal(index.labels["shard"], [0, 0, 0, 1, 1, 1, 2])
    assert index.labels["joints_3d"].shape == (7, 21, 3) and index.labels["joints_3d"].dtype == np.float32
    assert index.labels["object_id"].dtype == np.int16
    np.testing.assert_array_equal(index.labels["K"][4], make_record(4)[5]["K"])
    assert index.labels["frame_id"].tolist()[:2] == ["f0000", "f0001"]
    vertices, faces = index.objects["002_master_chef_can"]
    assert vertices.shape == (8, 3) and faces.dtype == np.int32
    assert index.skipped[0] == {"frame_id": "f9999", "reason": "hand not visible", "path": "seq0/f9999.jpg"}
    assert index.config == {"crop_size": CROP, "root": str(tmp_path)}
    assert index.provenance["git_commit"] == "0123abc" and index.provenance["hoidata_version"]
    assert index.shard_rows(1) == slice(3, 6)
    # writing again replaces the index whole, leaving no temporary folder behind
    write_index(tmp_path, shards, index_labels([make_record(i)[5] for i in range(7)]), {}, [], {}, {})
    assert read_index(tmp_path).objects == {} and not list(tmp_path.glob(f"{INDEX_NAME}.*"))


def test_index_refuses_inconsistent_input_and_damage(tmp_path):
    _, shards = build_store(tmp_path)
    labels = index_labels([make_record(i)[5] for i in range(7)])
    with pytest.raises(DataError, match="expected 7 rows|shape"):
        write_index(tmp_path, shards, {**labels, "joints_3d": labels["joints_3d"][:6]}, {}, [], {}, {})
    with pytest.raises(DataError, match="first/last key"):
        write_index(tmp_path, shards, {**labels, "key": labels["key"][::-1]}, {}, [], {}, {})
    with pytest.raises(DataError, match="missing"):
        read_index(tmp_path / "nowhere")
    (tmp_path / INDEX_NAME / "labels" / "joints_3d" / "zarr.json").write_text("{not json")
    with pytest.raises(DataError, match="labels/joints_3d"):
        read_index(tmp_path)


def test_iter_records_and_verify(tmp_path):
    records, _ = build_store(tmp_path)
    assert [r[KEY] for r in iter_records(tmp_path)] == [key for key, _ in records]
    report = verify_store(tmp_path)
    assert report.ok, str(report)
    assert (report.shards, report.records) == (3, 7)


def test_verify_catches_truncation(tmp_path):
    build_store(tmp_path)
    shard = tmp_path / "shard-000001.tar"
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])
    report = verify_store(tmp_path)
    assert not report.ok
    assert all("shard-000001.tar" in p for p in report.problems), report.problems
    assert any("bytes" in p for p in report.problems) and any("truncated" in p for p in report.problems)


@pytest.mark.parametrize("where", ["data", "header"])
def test_verify_catches_a_flipped_byte(tmp_path, where):
    build_store(tmp_path)
    shard = tmp_path / "shard-000002.tar"
    with tarfile.open(shard) as tar:
        member = tar.getmembers()[3]  # the record's sdf.npy
    offset = member.offset_data + 100 if where == "data" else member.offset + 10
    data = bytearray(shard.read_bytes())
    data[offset] ^= 0x55
    shard.write_bytes(bytes(data))
    report = verify_store(tmp_path)
    assert not report.ok
    assert any("shard-000002.tar" in p and "sha256" in p for p in report.problems)
    assert all("shard-000002.tar" in p for p in report.problems)
    if where == "header":  # tarfile alone would just stop early here
        with pytest.raises(DataError, match="shard-000002.tar"):
            list(read_shard_members(shard))


def test_completed_shards_checks_bytes_against_sidecars(tmp_path):
    records, shards = build_store(tmp_path, n=7, per_shard=3)
    plan = [ShardInfo(s.number, shard_name(s.number), s.count, first_key=s.first_key, last_key=s.last_key)
            for s in shards]
    host = socket.gethostname()
    (tmp_path / "shard-000002.tar.tmp").write_bytes(b"partial")  # a planned shard's leftover: removed
    (tmp_path / f"shard-000001.tar.{host}-999999.tmp").write_bytes(b"partial")  # of a dead writer here: removed
    alive = [f"shard-000001.tar.{host}-{os.getppid()}.tmp",  # a writer still running on this host
             "shard-000001.tar.other-node-42.tmp",  # one on another node of a shared filesystem
             "shard-000003.tar.tmp"]  # another --part job's shard
    for name in alive:
        (tmp_path / name).write_bytes(b"partial")  # all left alone
    assert completed_shards(tmp_path, plan) == {0, 1, 2}
    assert sorted(p.name for p in tmp_path.glob("*.tmp")) == sorted(alive)
    assert completed_shards(tmp_path, plan[2:], clean=False) == {2}
    data = bytearray((tmp_path / "shard-000001.tar").read_bytes())
    data[700] ^= 1
    (tmp_path / "shard-000001.tar").write_bytes(bytes(data))
    (tmp_path / "shard-000002.json").unlink()
    assert completed_shards(tmp_path, plan) == {0}
    changed = [ShardInfo(0, shard_name(0), 2, first_key=shards[0].first_key)]  # the plan changed: rebuild
    assert completed_shards(tmp_path, changed) == set()
    # rewriting a shard on its own gives the very same bytes, so a resumed build equals a straight one
    assert write_shard(tmp_path, 1, records[3:6]) == shards[1]
    assert completed_shards(tmp_path, plan) == {0, 1}


def test_webdataset_reads_the_same_records(tmp_path):
    import webdataset as wds

    records, shards = build_store(tmp_path)
    urls = [str(tmp_path / s.name) for s in shards]
    samples = list(wds.WebDataset(urls, shardshuffle=False))
    assert [s["__key__"] for s in samples] == [key for key, _ in records]
    for sample, (_, members) in zip(samples, records):
        assert {m: sample[m] for m in MEMBERS} == members
    decoded = decode_record(samples[0], samples[0]["__url__"])  # the trainer can decode WebDataset samples directly
    assert decoded[KEY] == records[0][0]


def test_to_jsonable_numbers_and_non_finite_values():
    """Numeric arrays take a fast path (tolist at once); the values are those of the element-wise path, and a
    NaN or infinity anywhere in them is still refused with the field's name."""
    from hoidata.store.index import to_jsonable

    value = {"K": np.array([[1.5, 0.0], [2.0, -3.25]]), "f32": np.float32([0.1, 2.0]),
             "ids": np.arange(3, dtype=np.int16), "flags": np.array([True, False]), "names": np.array(["a", "b"]), "nested": [np.array([1.0]), (2, "x")]}
    out = to_jsonable(value, "w", "meta")
    assert out == {"K": [[1.5, 0.0], [2.0, -3.25]], "f32": [float(np.float32(0.1)), 2.0], "ids": [0, 1, 2],
                   "flags": [True, False], "names": ["a", "b"], "nested": [[1.0], [2, "x"]]}
    assert type(out["ids"][0]) is int and type(out["flags"][0]) is bool and type(out["f32"][0]) is float
    for bad in (np.array([[0.0, np.nan]]), np.float32([1.0, -np.inf])):
        with pytest.raises(DataError, match=r"'meta\.K': non-finite number (nan|-inf)"):
            to_jsonable({"K": bad}, "w", "meta")


def test_decode_leaves_undecoded_members_out_but_checks_them():
    """decode_record(undecoded=(HEATMAP,)) (what the training loader calls) does not return the heatmap, and still
    refuses one that is cut short, of the wrong size, not a PNG, over the size limit or missing."""
    from hoidata.store.codec import MAX_MEMBER_BYTES

    key, img, seg, hm, sdf, meta = make_record(2)
    members = {KEY: key, **encode_record(key, img, seg, hm, sdf, meta)}
    out = decode_record(members, "shard.tar", undecoded=(HEATMAP,))
    assert HEATMAP not in out and set(out) == {KEY, IMG, SEG, SDF, META}
    np.testing.assert_array_equal(out[SEG], seg)
    _, wrong_size = cv2.imencode(".png", np.zeros((CROP, CROP), np.uint8))
    _, colour = cv2.imencode(".png", np.zeros((CROP // 2, CROP // 2, 3), np.uint8))
    for bad, match in ((members[HEATMAP][:-20], "truncated PNG"), (wrong_size.tobytes(), r"expected \(16, 16\)"),
                       (members[IMG], "not an 8-bit grey PNG"), (colour.tobytes(), "not an 8-bit grey PNG"),
                       (b"\0" * (MAX_MEMBER_BYTES + 1), "at most")):
        with pytest.raises(DataError, match=match):
            decode_record({**members, HEATMAP: bad}, "shard.tar", undecoded=(HEATMAP,))
    with pytest.raises(DataError, match="expected exactly"):
        decode_record({k: v for k, v in members.items() if k != HEATMAP}, "shard.tar", undecoded=(HEATMAP,))
