"""The project's promises about bad inputs and faults, data side (docs/reliability.md); training side in
test_faults_train.py. One test per class of fault, named after the promise; each builds on the tiny toy DexYCB.

Promises here: no store path runs code; no build work is lost (all-skipped shards, failed index writes, lost
skips files); nothing is silent (the loader compares shards with the index, a lost index chunk, truncated
source images, changed inputs on resume, the reader's skips, make-toy into a used folder, unknown cameras,
small data defects); no pool hangs when a worker cannot start; bounded memory on hostile shards.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from hoidata import store
from hoidata.cli import main as hoidata
from hoidata.errors import DataError
from hoidata.build_sdf import build_store
from hoidata.records.settings import load_build_config
from hoisdf.data import StoreSpec, build_dataset, make_loader

pytestmark = pytest.mark.slow  # each fault is a build of the tiny toy DexYCB

SMALL = ['dataset.splits=["train"]', "record.crop_size=128", "record.sdf_samples_hand=256", "record.sdf_samples_object=128",
         "store.records_per_shard=4"]
ROOT = Path(__file__).resolve().parents[1]


def _build(root, out, extra=(), part=(0, 1), mano=None, models=None, workers=1):
    cfg = load_build_config("toy", SMALL + list(extra))
    return build_store(cfg, root, mano or root / "mano", models or root / "models", out, workers=workers, part=part,
                       progress=False)


def _read_all(path, training=False, workers=0):
    """Every key one pass of the training loader reads (the evaluation order when not training)."""
    data = build_dataset([StoreSpec(path)], 2, epoch_samples=16 if training else None, n_hand=8, n_object=8,
                         training=training)
    data.set_epoch(0)
    return [k for batch in make_loader(data, workers) for k in batch["key"]]


def _rewrite_shard(path: Path, transform) -> None:
    """Rewrite a shard's members through ``transform`` and give the index the new size and sha256 (a store
    re-hashed by a tool, or a hostile one: only the structure can tell)."""
    with tarfile.open(path) as tar:
        members = [(m.name, tar.extractfile(m).read()) for m in tar if m.isreg()]
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for name, data in transform(members):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    path.write_bytes(buf.getvalue())
    _fix_index_entry(path)


def _fix_index_entry(path: Path) -> None:
    size, sha = store.file_digest(path)
    index_json = path.parent / "index.zarr" / "zarr.json"
    meta = json.loads(index_json.read_text())
    for entry in meta["attributes"]["shards"]:
        if entry["name"] == path.name:
            entry["size"], entry["sha256"] = size, sha
    index_json.write_text(json.dumps(meta))


@pytest.fixture()
def dexycb_copy(tiny_dexycb, tmp_path):
    root = tmp_path / "dexycb"
    shutil.copytree(tiny_dexycb, root)
    return root


@pytest.fixture()
def store_copy(tiny_store, tmp_path):
    out = tmp_path / "store"
    shutil.copytree(tiny_store, out)
    return out


# --- 1. no path runs code ------------------------------------------------------------------------------------


def test_a_store_path_is_a_folder_never_a_command(tiny_store, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    marker = tmp_path / "MARK"
    for name in ("pipe:touch MARK #", "http:x", "s3:bucket"):  # URL-like prefixes mean nothing in a folder name
        shutil.copytree(tiny_store, tmp_path / name)
        assert len(_read_all(name)) == 16 and not marker.exists()
        assert store.verify_store(name).ok
    # only an explicit URL string is remote (read by fsspec, tests/test_cluster_stores.py); a Path never is
    assert isinstance(store.resolve_store("s3://bucket/store"), store.RemoteStore)
    assert store.resolve_store(Path("s3://bucket/store")) == Path("s3:/bucket/store")
    report = store.verify_store("https://example.org/store")  # refused before any request: verify is local
    assert not report.ok and "local store folder" in report.problems[0]


# --- 2. no work lost -----------------------------------------------------------------------------------------


def test_a_shard_whose_frames_all_fail_is_an_empty_shard_and_the_store_finishes(dexycb_copy, tmp_path, capsys):
    import yaml

    from hoidata.objects import YCB_CLASSES

    meta = yaml.safe_load(sorted(dexycb_copy.glob("*/*/meta.yml"))[0].read_text())  # the first (right-hand) sequence
    grasped = YCB_CLASSES[meta["ycb_ids"][meta["ycb_grasp_ind"]]]
    (dexycb_copy / "models" / grasped / "textured_simple.obj").write_text("not an obj\n")  # its 2 shards all fail
    args = ["build-sdf", "--dataset", "toy", "--root", str(dexycb_copy), "--out", str(tmp_path / "s"), *SMALL]
    assert hoidata(args) == 0 and hoidata(args) == 0  # and a rerun does not fail either
    report = store.verify_store(tmp_path / "s")
    assert report.ok and report.shards == 4 and report.empty_shards == 2 and report.records == 8, str(report)
    assert "2 empty" in capsys.readouterr().out
    assert len(_read_all(tmp_path / "s", training=True)) == 16  # the loader takes the empty shards in its stride


def test_a_failed_index_write_leaves_nothing_that_breaks_the_next_run(dexycb_copy, tmp_path, monkeypatch):
    import errno

    import zarr

    out = tmp_path / "s"
    dead = out / "index.zarr.tmp999999"  # a killed writer of another process (no such pid)
    dead.mkdir(parents=True)
    real = zarr.Group.create_array
    monkeypatch.setattr(zarr.Group, "create_array", lambda *a, **k: (_ for _ in ()).throw(
        OSError(errno.ENOSPC, "No space left on device", str(out / "index.zarr"))))
    with pytest.raises(OSError, match="No space"):
        _build(dexycb_copy, out)
    assert not [p for p in out.iterdir() if p.name.startswith("index.zarr")]  # own and dead temp folders gone
    monkeypatch.setattr(zarr.Group, "create_array", real)
    assert _build(dexycb_copy, out).finished and store.verify_store(out).ok


def test_a_lost_or_corrupt_skips_file_is_rebuilt(dexycb_copy, tmp_path):
    out = tmp_path / "s"
    _build(dexycb_copy, out)
    shards = {p.name: p.read_bytes() for p in out.glob("shard-*.tar")}
    (out / "shard-000001.skips.json").unlink()
    (out / "shard-000002.skips.json").write_text("{not json")
    summary = _build(dexycb_copy, out)
    assert summary.units_written == 2 and summary.finished
    assert {p.name: p.read_bytes() for p in out.glob("shard-*.tar")} == shards and store.verify_store(out).ok


def test_rebuilding_a_finished_store_writes_nothing(dexycb_copy, tmp_path, monkeypatch):
    import errno

    import hoidata.atomic

    out = tmp_path / "s"
    _build(dexycb_copy, out)

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(out))

    for module, name in ((store, "write_index"), (hoidata.atomic, "write_atomic"), (Path, "unlink")):
        monkeypatch.setattr(module, name, read_only)  # a finished store on a read-only disk
    summary = _build(dexycb_copy, out)
    assert summary.units_kept == 4 and summary.units_written == 0 and summary.finished


# --- 3. nothing silent ---------------------------------------------------------------------------------------


def _cut_at_record(members):
    return members[:5]


def _duplicate_record(members):
    return members + members[:5]


def _foreign_record(members):
    return [(n.replace("dexycb-train-", "dexycb-train-x", 1) if i < 5 else n, d) for i, (n, d) in enumerate(members)]


def _zeroed(path: Path) -> None:
    path.write_bytes(bytes(path.stat().st_size))


@pytest.mark.parametrize("damage", [_cut_at_record, _duplicate_record, _foreign_record, _zeroed])
@pytest.mark.parametrize("training", [False, True])
def test_the_loader_reads_exactly_what_the_index_lists(store_copy, damage, training):
    shard = store_copy / "shard-000000.tar"
    if damage is _zeroed:
        damage(shard)  # same size as the index says
    else:
        _rewrite_shard(shard, damage)
    with pytest.raises(DataError, match="shard-000000.tar"):
        _read_all(store_copy, training=training, workers=1)


def test_a_missing_index_chunk_is_an_error(store_copy):
    chunks = sorted((store_copy / "index.zarr" / "labels" / "mirrored").rglob("c/*"))
    chunks[0].unlink()
    with pytest.raises(DataError, match="labels/mirrored"):
        store.read_index(store_copy)


@pytest.mark.parametrize("cut", ["jpeg", "labels"])
def test_a_truncated_source_file_is_a_skipped_frame_with_its_reason(dexycb_copy, tmp_path, cut):
    pattern = "color_000001.jpg" if cut == "jpeg" else "labels_000001.npz"
    victim = sorted(dexycb_copy.glob(f"*/*/*/{pattern}"))[0]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    summary = _build(dexycb_copy, tmp_path / "s")
    skips = summary.skipped + summary.reader_skipped
    assert summary.written == 15 and len(skips) == 1 and str(victim.name) in json.dumps(skips)
    assert ("truncated JPEG" if cut == "jpeg" else "npz") in skips[0]["reason"]


def _scale_models(models: Path, factor: float) -> None:
    for obj in models.glob("*/textured_simple.obj"):
        lines = [("v " + " ".join(f"{float(t) * factor:.6f}" for t in ln.split()[1:4])) if ln.startswith("v ") else ln
                 for ln in obj.read_text().splitlines()]
        obj.write_text("\n".join(lines) + "\n")


def _change_input(root: Path, what: str) -> dict:
    """Change one input of a build after its first part was written; returns build_store's keyword overrides."""
    if what == "mano":
        from hoidata.toy.hand import build_toy_mano, mirror_to_left, write_mano_pickle

        arrays = build_toy_mano()
        arrays["v_template"] = arrays["v_template"] * 1.02
        write_mano_pickle(root / "mano" / "MANO_LEFT.pkl", mirror_to_left(arrays))
        return {}
    if what == "models":
        shutil.copytree(root / "models", root.parent / "models2")
        _scale_models(root.parent / "models2", 1.3)
        return {"models": root.parent / "models2"}
    if what == "labels":  # shard 0's first frame: its annotation moves by 1 mm
        path = sorted(root.glob("*/*/*/labels_000000.npz"))[0]
        labels = dict(np.load(path))
        labels["joint_3d"] = labels["joint_3d"] + 0.001
        np.savez_compressed(path, **labels)
        return {}
    image = sorted(root.glob("*/*/*/color_000000.jpg"))[0]  # an image a kept shard was built from
    shutil.copyfile(sorted(root.glob("*/*/*/color_000005.jpg"))[0], image)
    return {}


@pytest.mark.parametrize("what", ["mano", "models", "labels", "image"])
def test_a_resumed_build_refuses_inputs_that_changed(dexycb_copy, tmp_path, what):
    out = tmp_path / "s"
    _build(dexycb_copy, out, part=(0, 2))  # shards 0 and 2 written, like an interrupted build
    kwargs = _change_input(dexycb_copy, what)
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(DataError, match="changed|differ"):
        _build(dexycb_copy, out, **kwargs)
    assert sorted(p.name for p in out.iterdir()) == before  # nothing was changed


def test_the_build_summary_names_the_readers_skips_and_their_reasons(tiny_dexycb, tmp_path, capsys):
    mano = tmp_path / "mano"
    mano.mkdir()
    shutil.copy(tiny_dexycb / "mano" / "MANO_RIGHT.pkl", mano)  # no MANO_LEFT.pkl: every left hand is dropped
    args = ["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(tmp_path / "s"), "--mano",
            str(mano), *SMALL]
    assert hoidata(args) == 0
    out = capsys.readouterr().out
    assert "1 by the dataset reader" in out and "MANO_LEFT.pkl" in out and "not found" in out
    assert hoidata([*args[:5], "--out", str(tmp_path / "e"), "--mano", str(tmp_path / "nothing"), *SMALL]) == 2
    err = capsys.readouterr().err
    assert "MANO_RIGHT.pkl" in err and "not found" in err and len(err.strip().splitlines()) == 1


def test_make_toy_never_mixes_old_and_new_files(tmp_path, capsys):
    from hoidata.toy.make import split_rows

    out = tmp_path / "toy"
    base = ["make-toy", "--out", str(out), "--layout", "dexycb", "--frames", "1"]
    assert hoidata([*base, "--sequences", "2"]) == 0
    assert hoidata([*base, "--sequences", "1"]) == 0  # a folder make-toy wrote is replaced as a whole
    train = next(r for r in split_rows(out, "dexycb") if r["setting"] == "dexycb_full" and r["split"] == "train")
    assert train["frames"] == 4 * 3 * 1  # 4 subjects, 3 cameras, 1 frame of the 1 sequence each: no stale folders
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    capsys.readouterr()
    assert hoidata(["make-toy", "--out", str(foreign), "--layout", "dexycb", "--frames", "1", "--sequences", "1"]) == 2
    assert "not empty" in capsys.readouterr().err and sorted(os.listdir(foreign)) == ["notes.txt"]


def test_an_unknown_camera_serial_is_a_skip_with_a_reason(dexycb_copy, tmp_path):
    meta = sorted(dexycb_copy.glob("*/*/meta.yml"))[0]
    meta.write_text(meta.read_text().replace("836212060125", "836212060126"))  # a typo in the serial
    summary = _build(dexycb_copy, tmp_path / "s")
    assert summary.written == 8
    assert any("836212060126" in s["reason"] for s in summary.reader_skipped)
    assert any("836212060126" in s["reason"] for s in store.read_index(tmp_path / "s").skipped)


def test_small_data_defects_are_named(dexycb_copy, tmp_path, monkeypatch):
    from hoidata.objects import load_object_mesh

    # a label array of the wrong dtype is a skipped frame, not a crashed build
    path = sorted(dexycb_copy.glob("*/*/*/labels_000003.npz"))[0]
    labels = dict(np.load(path))
    np.savez_compressed(path, **{**labels, "pose_m": labels["pose_m"].astype(str)})
    summary = _build(dexycb_copy, tmp_path / "s")
    assert summary.written == 15 and "pose_m" in json.dumps(summary.reader_skipped)
    # an OBJ with a latin-1 byte in a comment loads without any text-encoding guesser installed
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    monkeypatch.setitem(sys.modules, "chardet", None)
    obj = sorted((dexycb_copy / "models").glob("*/textured_simple.obj"))[0]
    obj.write_bytes(b"# \xa9 latin-1\n" + obj.read_bytes())
    assert len(load_object_mesh(obj).faces) > 0


@pytest.mark.parametrize("field,value,match", [("object_id", 10 ** 30, "object_id"), ("object_id", -5, "object_id"),
                                               ("hand_root", [1e300, 0, 0], "hand_root")])
def test_record_labels_out_of_range_are_refused(store_copy, field, value, match):
    def edit(members):
        out = []
        for name, data in members:
            if name.endswith(".meta.json") and not out[-1:] == [None]:
                meta = json.loads(data)
                meta[field] = value
                data = json.dumps(meta).encode()
            out.append((name, data))
        return out

    _rewrite_shard(store_copy / "shard-000000.tar", edit)
    with pytest.raises(DataError, match=match):
        _read_all(store_copy)


def test_member_names_and_sizes_are_checked_exactly(store_copy):
    import cv2

    small = cv2.imencode(".jpg", np.zeros((32, 32, 3), np.uint8))[1].tobytes()
    _rewrite_shard(store_copy / "shard-000000.tar",
                   lambda ms: [(n, small) if i == 0 else (n, d) for i, (n, d) in enumerate(ms)])
    with pytest.raises(DataError, match=r"img\.jpg'?: 32x32 px"):  # the image is named, not seg.png
        _read_all(store_copy)
    _rewrite_shard(store_copy / "shard-000000.tar", lambda ms: [(n.replace(".img.jpg", ".IMG.JPG"), d) for n, d in ms])
    with pytest.raises(DataError, match="IMG.JPG"):
        _read_all(store_copy)


# --- 5. no hangs when a worker cannot start ------------------------------------------------------------------


@pytest.mark.parametrize("command", ["make-toy", "build-sdf"])
def test_a_worker_that_cannot_start_ends_the_command_with_one_error(tiny_dexycb, tmp_path, command):
    fake = tmp_path / "fake"
    (fake / "pyrender").mkdir(parents=True)  # an install where pyrender cannot be imported
    (fake / "pyrender" / "__init__.py").write_text("raise ImportError('no EGL here (test)')\n")
    if command == "make-toy":
        args = ["make-toy", "--out", str(tmp_path / "toy"), "--layout", "dexycb", "--sequences", "1", "--frames", "1"]
    else:
        args = ["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(tmp_path / "s"),
                "--workers", "2", *SMALL]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fake), str(ROOT)]), "PYOPENGL_PLATFORM": "egl"}
    result = subprocess.run([sys.executable, "-m", "hoidata.cli", *args], capture_output=True, text=True, env=env,
                            timeout=120, check=False)
    assert result.returncode == 2, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if "error" in line.lower()]
    assert len(lines) == 1 and "no EGL here" in lines[0] and "Traceback" not in result.stderr, result.stderr[-2000:]


def test_a_loader_worker_that_dies_is_one_error(tiny_store, monkeypatch):
    import signal

    import hoisdf.data.shards as shards

    monkeypatch.setattr(shards, "read_checked_shard", lambda *a: os.kill(os.getpid(), signal.SIGKILL))
    with pytest.raises(DataError, match="data loader worker"):
        _read_all(tiny_store, workers=1)


# --- 6. bounded memory on hostile shards ---------------------------------------------------------------------


def test_a_hostile_member_is_refused_before_it_is_read(store_copy):
    shard = store_copy / "shard-000000.tar"
    with tarfile.open(shard) as tar:
        first = next(m for m in tar if m.isreg())
        key = first.name.split(".")[0]
    huge = store.MAX_MEMBER_BYTES + (1 << 20)
    info = tarfile.TarInfo(first.name)
    info.size = huge
    with open(shard, "wb") as f:  # a member as big as the limit allows, plus 1 MiB: the file is sparse
        f.write(info.tobuf(tarfile.PAX_FORMAT))
        f.truncate(f.tell() + huge + 2048)
    _fix_index_entry(shard)
    tracemalloc.start()
    with pytest.raises(DataError, match=key):
        _read_all(store_copy)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < huge // 4, peak
