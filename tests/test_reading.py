"""Issue 44, part 2: the guarded door (hoidata.reading, reading_media, shapes). No file is read outside it (a scan
of the source); its bounds and messages; the issue's examples, each through the command a user runs. The corpus
walk over every reader is tests/test_reading_corpus.py."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from door_walk import door_readers, raw_reads

from hoidata.errors import DataError
from hoidata.reading import list_tar, parse_json, read_json, read_zip_member, too_deep
from hoidata.shapes import Integer, ListOf, Numbers, Record, check, numbers
from hoisdf.scoring.cli import main as score

# the reads that stay outside the door, each for its reason
OUTSIDE = {
    ("hoidata.atomic", "_umask"): "the process's own /proc/self/status, not a user's file",
    ("hoidata.sections", "apply_overrides"): "TOML of a command-line value, not a file",
    ("hoidata.store.shards", "_members"): "the store's tar stream reader: sizes against the index, member sizes "
                                          "before reading (docs/reliability.md, 3.); each member decoded by the door",
    ("hoidata.store.shards", "read_shard_members"): "the same reader, a local shard",
    ("hoidata.store.shards", "read_record"): "the same reader, one record at its span",
    ("hoidata.store.spans", "record_spans"): "the same reader: the spans of a shard's records",
    ("hoisdf.training.checkpoint", "copy_checkpoint"): "a byte copy of a checkpoint this run wrote",
}


def test_no_file_is_read_outside_the_door():
    found = {}
    for module, function, line, what in raw_reads():
        found.setdefault((module, function), []).append(f"{what} (line {line})")
    bypass = {k: v for k, v in found.items() if k not in OUTSIDE}
    assert not bypass, f"file reads outside hoidata.reading (route them through it): {bypass}"
    assert set(OUTSIDE) <= set(found), f"stale entries: {sorted(set(OUTSIDE) - set(found))}"


def test_the_scan_finds_each_kind_of_raw_read(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("import json\nimport numpy as np\nfrom pathlib import Path\nfrom PIL import Image\n"
                   "def a(p):\n    return json.loads(Path(p).read_text())\n"
                   "def b(p):\n    with open(p) as f:\n        return f.read()\n"
                   "def c(p):\n    return np.load(p), Image.open(p)\n"
                   "def d(p, x):\n    with open(p, 'w') as f:\n        f.write(json.loads(json.dumps(x)))\n"
                   "def e(p):\n    return [json.loads(q) for q in p]\n")
    found = sorted((f, w) for _, f, _, w in raw_reads([("m", src)]))
    assert found == [("a", ".read_text"), ("a", "json.loads"), ("b", "open"), ("c", "PIL.Image.open"),
                     ("c", "numpy.load"), ("e", "json.loads")]
    door = tmp_path / "n.py"
    door.write_text("from hoidata.reading import read_json\nclass K:\n    def f(self, p):\n"
                    "        return [read_json(q) for q in p]\ndef g():\n    return 1\n")
    assert door_readers([("n", door)]) == {("n", "K.f")}


def test_json_nesting_is_bounded_before_the_parser():
    assert not too_deep(b"[" * 64 + b"]" * 64) and too_deep(b"[" * 65 + b"]" * 65)
    assert not too_deep(b'["' + b"[" * 500 + b'"]')  # brackets inside a string are text
    assert too_deep(b'{"a": ' * 70 + b"1" + b"}" * 70)
    with pytest.raises(DataError, match=r"f.json: not JSON this reader takes: arrays and objects nested more than 64"):
        parse_json(b"[" * 200_000 + b"]" * 200_000, "f.json")
    with pytest.raises(DataError, match=r"f.json: 'm': not UTF-8 JSON: byte 0x80 at offset 2 \(line 1\)"):
        parse_json(b"[[\x80\x81]]", "f.json", "m")


def test_size_and_kind_of_a_file_are_checked_before_it_is_read(tmp_path):
    (tmp_path / "big.json").write_bytes(b"[" + b"1," * 50 + b"1]")
    with pytest.raises(DataError, match=r"big.json: 103 bytes, more than a list may hold \(100\)"):
        read_json(tmp_path / "big.json", "list", max_bytes=100)
    with pytest.raises(DataError, match=r"a folder, not a list"):
        read_json(tmp_path, "list")
    with pytest.raises(DataError, match=r"nope.json: list not found; give another"):
        read_json(tmp_path / "nope.json", "list", "give another")


@pytest.mark.parametrize("value, shape, words", [
    ([float("nan")] * 15, (15,), "expected 15 finite numbers, got 15 numbers, 15 of them NaN"),
    ([1.0, float("inf"), float("nan")], (3,), "expected 3 finite numbers, got 3 numbers, 1 NaN and 1 infinite"),
    ([[1, 2, "3"]], (1, 3), "expected numbers, got a string ('3') at [0][2]"),
    ([[True, False, True]], (1, 3), "expected numbers, got a boolean (true) at [0][0]"),
    ([1.0, None], (2,), "expected numbers, got null at [1]"),
    ([[1.0, 2.0], [3.0]], (2, 2), "expected (2, 2) numbers, got a ragged list"),
    ([1.0] * 14, (15,), "expected 15 numbers, got shape (14,)"),
    (np.array(["1", "2"]), (2,), "expected numbers, got an array of <U1 values"),
])
def test_numbers_say_what_is_wrong(value, shape, words):
    with pytest.raises(DataError) as caught:
        numbers(value, "f.json", "x", shape)
    assert str(caught.value) == f"f.json: 'x': {words}"
    assert numbers([[1, 2.5]], "f", None, (None, 2)).dtype == np.float64


def test_declared_shapes_name_the_field_path():
    shape = ListOf(Record({"frame_id": Integer(), "xyz": Numbers((3,))}), label="entry {}")
    good = check([{"frame_id": 1, "xyz": [0, 0, 1]}], shape, "r.json")
    assert good[0]["xyz"].dtype == np.float64
    for value, words in (([{"frame_id": "1", "xyz": [0, 0, 1]}], "'entry 0: frame_id': expected a whole number, "
                                                                   "got a string ('1')"),
                         ([{"frame_id": 1}], "'entry 0: xyz': missing"), ({"a": 1}, "expected a list, got an object"),
                         ([{"frame_id": 1.5, "xyz": [0, 0, 1]}], "expected a whole number, got the number 1.5")):
        with pytest.raises(DataError, match=__import__("re").escape(words)):
            check(value, shape, "r.json")


def test_zip_and_tar_members_are_named_and_duplicates_refused(tmp_path):
    import warnings

    from reading_corpus import tar_bytes

    path = tmp_path / "a.zip"
    with warnings.catch_warnings(), zipfile.ZipFile(path, "w") as zf:
        warnings.simplefilter("ignore")
        zf.writestr("pred.json", b"[1]")
        zf.writestr("pred.json", b"[2]")
    with pytest.raises(DataError, match=r"a.zip: 'pred.json': two members of the archive have this name"):
        read_zip_member(path, lambda names: "pred.json")
    tar = tmp_path / "c.tar"
    tar.write_bytes(tar_bytes([("000000.hands.json", b"{}"), ("other/000000.hands.json", b"[]")]))
    listing = list_tar(tar, lambda name: Path(name).name)
    with pytest.raises(DataError, match=r"c.tar: '000000.hands.json': two members of the tar are '000000.hands.json' "
                                        r"\('000000.hands.json' and 'other/000000.hands.json'\)"):
        listing.read("000000.hands.json")


# --- the examples, through `hoisdf score` ------------------------------------------------------------------


def _one_line(capsys, argv, *words) -> str:
    code = score([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert all(w in err for w in words), err
    return err


@pytest.fixture
def pred(tmp_path) -> bytes:
    xyz = [[[0.01 * i, 0.0, -0.5] for i in range(21)]]
    return json.dumps([xyz, [[[0.0, 0.0, -0.5]] * 778]]).encode()


def _zip(path: Path, data: bytes, name: str = "pred.json") -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(name, data)
    return path


def test_score_ho3d_examples_are_one_line_naming_the_file(pred, tmp_path, capsys):
    gt = tmp_path / "gt"  # never reached: each submission is refused first
    good = _zip(tmp_path / "ok.zip", pred).read_bytes()
    crc = bytearray(good)
    at = good.index(b"pred.json") + 30
    crc[at:at + 50] = bytes(b ^ 0x5A for b in crc[at:at + 50])
    cases = {"crc.zip": (bytes(crc), ["crc.zip", "pred.json"]),
             "trunc.zip": (good[:len(good) // 2], ["trunc.zip", "not a readable", "cut short or damaged"]),
             "deep.json": (b"[" * 200_000 + b"]" * 200_000, ["deep.json", "nested more than 64"]),
             "nonutf8.json": (b"[[\x80\x81]]", ["nonutf8.json", "not UTF-8"]),
             "strings.json": (pred.replace(b"[0.0, 0.0, -0.5]", b'["1", "2", "3"]', 1),
                              ["strings.json", "'xyz_list[0]'", "expected numbers, got a string ('1')"]),
             "bool.json": (pred.replace(b"[0.0, 0.0, -0.5]", b"[true, false, true]", 1),
                           ["bool.json", "'xyz_list[0]'", "got a boolean (true)"])}
    for name, (data, words) in cases.items():
        (tmp_path / name).write_bytes(data)
        _one_line(capsys, ["ho3d", "--pred", tmp_path / name, "--gt", gt], *words)
    _zip(tmp_path / "nonutf8.zip", b"[[\x80]]")
    _one_line(capsys, ["ho3d", "--pred", tmp_path / "nonutf8.zip", "--gt", gt], "nonutf8.zip", "'pred.json'",
              "not UTF-8")


def test_score_contact_hot3d_and_recon_examples_are_one_line(pred, tmp_path, capsys):
    import io

    buf = io.BytesIO()
    np.savez(buf, verts=np.zeros((2, 778, 3)), keys=np.array(["a", "b"]))
    (tmp_path / "h_trunc.npz").write_bytes(buf.getvalue()[:3000])
    _one_line(capsys, ["contact", "--pred", tmp_path / "h_trunc.npz", "--store", tmp_path, "--mano", tmp_path],
              "h_trunc.npz", "cannot decode")
    sub = tmp_path / "sub"
    sub.mkdir()
    (sub / "result_pose_hot3d.json").write_bytes(b"[" * 200_000 + b"]" * 200_000)
    _one_line(capsys, ["hot3d", "--pred", sub, "--gt", tmp_path / "gt", "--mano", tmp_path],
              "result_pose_hot3d.json", "nested more than 64")
    entry = {"sequence_name": "s", "frame_id": 0, "mano_theta": [float("nan")] * 15, "wrist_xform": [0.0] * 6,
             "hand_side": 1}
    (sub / "result_pose_hot3d.json").write_text(json.dumps([entry]))
    gt = tmp_path / "gt"
    gt.mkdir()
    (gt / "gt_shape_hot3d.json").write_text(json.dumps([{"sequence_name": "s", "mano_beta": [0.0] * 10,
                                                          "hand_side": 1}]))
    (gt / "gt_landmarks_hot3d.json").write_text(json.dumps([{"sequence_name": "s", "frame_id": 0,
                                                             "landmarks": [[0.0] * 3] * 20}]))
    from hoidata.toy.hand import write_toy_mano

    write_toy_mano(tmp_path / "mano")
    _one_line(capsys, ["hot3d", "--pred", sub, "--gt", gt, "--mano", tmp_path / "mano"],
              "'entry 0: mano_theta': expected 15 finite numbers, got 15 numbers, 15 of them NaN")
    import trimesh

    (tmp_path / "pred").mkdir()
    (tmp_path / "rgt").mkdir()
    for part in ("hand", "obj"):
        trimesh.creation.icosahedron().export(tmp_path / "rgt" / f"f0_{part}.ply")
    (tmp_path / "ids.txt").write_bytes(b"f0\n\xff\xfe\n")
    _one_line(capsys, ["recon", "--pred", tmp_path / "pred", "--gt", tmp_path / "rgt", "--ids", tmp_path / "ids.txt"],
              "ids.txt", "not UTF-8 frame list: byte 0xff at offset 3 (line 2)")


def test_a_pickled_npy_runs_no_code(tmp_path):
    """ARCTIC ships dicts saved with np.save (pickles inside .npy): read with the allow-list, a crafted one is refused
    and its code never runs (np.load(allow_pickle=True) would have run it); a dict of arrays reads as ARCTIC's."""
    import os

    from hoidata.safe_pickle import load_npy

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'ran'}",))

    np.save(tmp_path / "evil.npy", np.array(Payload(), dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match=r"evil.npy: refusing to load global posix.system"):
        load_npy(tmp_path / "evil.npy")
    assert not (tmp_path / "ran").exists()
    np.save(tmp_path / "seq.npy", {"right": {"rot": np.zeros((51, 3), np.float32)}}, allow_pickle=True)
    assert load_npy(tmp_path / "seq.npy").item()["right"]["rot"].shape == (51, 3)
