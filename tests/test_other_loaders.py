"""docs/other-loaders.md, run: each loader of another stack reads every member of every record of a toy store (a
default one and one of upstream-region records) with the values ``hoidata.store.iter_records`` gives; the store
verifies and resumes with the files they add; ``hoidata view`` writes a recording rerun's own reader opens.

Each test skips when its loader is not installed (the ``interop`` and ``dali`` extras bring them); none installs or
downloads anything.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hoidata import schema, store
from hoidata.store.card import CARD_NAME, write_store_files

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # a local folder: nothing to ask the Hub
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
DOC = Path(__file__).resolve().parents[1] / "docs" / "other-loaders.md"
KINDS = ["tiny_store_two_shards", "tiny_region_store"]
pytestmark = pytest.mark.slow


def recipe(heading: str) -> str:
    """The first python block of a section of docs/other-loaders.md."""
    text = DOC.read_text()
    return re.search(r"```python\n(.*?)```", text[text.index(f"## {heading}"):], re.S).group(1)


def recipes(*headings: str) -> dict:
    """The decoding block and the named sections' blocks, run: their names."""
    names: dict = {}
    exec(recipe("The project's decoding, for the loaders below") + "".join(recipe(h) for h in headings), names)
    return names


def ours(folder: Path) -> dict[str, tuple[dict, set]]:
    """key -> (the record as iter_records decodes it, its member names)."""
    names = [{m for m in raw if not m.startswith("__")} for path in sorted(folder.glob("shard-*.tar"))
             for raw in store.read_shard_members(path)]
    return {rec[store.KEY]: (rec, members) for rec, members in zip(store.iter_records(folder), names, strict=True)}


def assert_meta_equal(got: dict, want: dict) -> None:
    """A loader's meta.json (JSON values; None for a field the record lacks) against the decoded one."""
    got = {k: v for k, v in got.items() if v is not None}
    assert set(got) == set(want)
    for name, value in got.items():
        if isinstance(want[name], np.ndarray):
            assert np.asarray(value).shape == want[name].shape, name
            np.testing.assert_array_equal(np.asarray(value, want[name].dtype), want[name], err_msg=name)
        else:
            assert value == want[name], name


def assert_same(got: dict, expected: tuple[dict, set]) -> None:
    """A loader's decoded members (name -> value; None for a member the record lacks) against iter_records."""
    rec, members = expected
    got = {k: v for k, v in got.items() if v is not None}
    assert set(got) == members
    for name, value in got.items():
        value = value if name == schema.META else np.asarray(value)
        if name in schema.FRAME_MEMBERS:  # stored as shipped: the reader flips a mirrored record's frame
            frame = value[:, ::-1] if rec[schema.META]["mirrored"] else value
            np.testing.assert_array_equal(frame, rec[store.FRAME_IMAGE])
        elif name in (schema.IMG, schema.IMG_LOSSLESS):
            assert value.dtype == np.uint8
            np.testing.assert_array_equal(value, rec[schema.IMG])
        elif name == schema.META:
            assert_meta_equal(value, rec[schema.META])
        else:
            assert value.dtype == rec[name].dtype and value.shape == rec[name].shape, name
            np.testing.assert_array_equal(value, rec[name])


@pytest.mark.parametrize("kind", KINDS)
def test_hugging_face_datasets_opens_the_store_by_its_path(kind, request, tmp_path):
    datasets = pytest.importorskip("datasets")
    folder = request.getfixturevalue(kind)
    expected = ours(folder)
    records = datasets.load_dataset(str(folder), split="train", cache_dir=str(tmp_path / "cache"))
    assert records.features["sdf.npy"] == datasets.Array2D(shape=(None, 6), dtype="int16")
    assert records.num_rows == len(expected)
    arrays = records.with_format("numpy", dtype=None)
    for row, sample in enumerate(records):
        sdf = arrays[row]["sdf.npy"]
        assert sdf.dtype == np.int16 and sdf.shape[1] == 6
        assert_same({k: v for k, v in {**sample, "sdf.npy": sdf}.items() if not k.startswith("__")},
                    expected[sample["__key__"]])
    streamed = list(datasets.load_dataset(str(folder), split="train", streaming=True))
    assert [s["__key__"] for s in streamed] == list(expected)
    for sample in streamed:
        assert sample["sdf.npy"].dtype == np.int16
        assert_same({k: v for k, v in sample.items() if not k.startswith("__")}, expected[sample["__key__"]])


def test_hoidata_card_rewrites_the_same_card_for_a_store_built_before(tiny_region_store, tmp_path):
    datasets = pytest.importorskip("datasets")
    folder = tmp_path / "store"
    shutil.copytree(tiny_region_store, folder)
    built = (folder / CARD_NAME).read_bytes()
    for name in (CARD_NAME, "shardindex.json", *(p.name for p in folder.glob("shard-*.idx"))):
        (folder / name).unlink()  # a store as built before the card existed
    from hoidata.cli import main

    assert main(["card", str(folder)]) == 0
    assert (folder / CARD_NAME).read_bytes() == built
    assert datasets.load_dataset(str(folder), split="train", streaming=True).features["meta.json"]["frame_size"]


@pytest.mark.parametrize("kind", KINDS)
def test_wids_reads_every_record_by_index(kind, request, tmp_path):
    pytest.importorskip("wids")
    folder = request.getfixturevalue(kind)
    expected = ours(folder)
    names = recipes("`wids` (indexed random access)")
    dataset = names["hoidata_wids"](str(folder), str(tmp_path / "cache"))
    assert len(dataset) == len(expected)
    got = dict(names["wids_record"](dataset, i) for i in reversed(range(len(dataset))))  # any order
    assert sorted(got) == sorted(expected)
    for key, members in got.items():
        assert_same(members, expected[key])


@pytest.mark.parametrize("kind", KINDS)
def test_dali_reads_every_record_on_the_cpu(kind, request):
    pytest.importorskip("nvidia.dali")
    folder = request.getfixturevalue(kind)
    expected = ours(folder)
    members = sorted(set().union(*(m for _, m in expected.values())))
    names = recipes("NVIDIA DALI")
    pipe = names["hoidata_dali"](folder, members)
    pipe.build()
    assert pipe.epoch_size("store") == len(expected)
    got = {}
    for _ in range(len(expected)):
        outputs = pipe.run()
        sample = {m: bytes(np.asarray(out[0])) for m, out in zip(members, outputs) if np.asarray(out[0]).size}
        decoded = names["decode_sample"](sample)
        got[decoded[schema.META]["key"]] = decoded
    assert list(got) == list(expected)  # in store order
    for key, decoded in got.items():
        assert_same(decoded, expected[key])


def _files(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_energon_reads_every_record_after_prepare_and_the_store_verifies_and_resumes(tiny_region_store, tiny_dexycb,
                                                                                      tmp_path):
    pytest.importorskip("megatron.energon")
    from conftest import _build_tiny_store

    folder = tmp_path / "store"
    shutil.copytree(tiny_region_store, folder)
    before = _files(folder)
    command = [sys.executable, "-c", "from megatron.energon.cli.main import main; main()", "prepare",
               "--non-interactive", "--split-ratio", "1,0,0", "--sample-type", "CrudeWebdataset", "--no-progress",
               str(folder)]
    subprocess.run(command, check=True, capture_output=True, timeout=300)
    after = _files(folder)
    added = sorted(set(after) - set(before))
    assert all(after[name] == digest for name, digest in before.items())  # nothing changed, files added
    assert ".nv-meta/split.yaml" in added and sum(n.endswith(".tar.idx") for n in added) == 4
    from megatron.energon import WorkerConfig, get_val_dataset, get_loader

    names = recipes("Megatron-Energon")
    dataset = get_val_dataset(str(folder), split_part="train", batch_size=1, task_encoder=names["HoidataTaskEncoder"](),
                              worker_config=WorkerConfig(rank=0, world_size=1, num_workers=0))
    got = {batch[0].__key__: batch[0].members for batch in get_loader(dataset)}
    expected = ours(folder)
    assert list(got) == list(expected)
    for key, members in got.items():
        assert_same(members, expected[key])
    report = store.verify_store(folder)
    assert report.ok, str(report)
    _build_tiny_store(tiny_dexycb, folder, records_per_shard=5, more=['record.upstream_region=["train"]'])
    assert _files(folder) == after  # the resumed build found every shard done and rewrote nothing


def test_view_writes_a_recording_that_reruns_reader_opens(tiny_region_store, tiny_dexycb, tmp_path):
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    from hoidata.cli import main
    from hoidata.view import sequence_of

    expected = list(store.iter_records(tiny_region_store))
    sequence = sequence_of(expected[0][store.KEY])
    frames = [r for r in expected if sequence_of(r[store.KEY]) == sequence]
    out = tmp_path / "sequence.rrd"
    assert main(["view", str(tiny_region_store), "--sequence", sequence, "--mano", str(tiny_dexycb / "mano"),
                 "--out", str(out)]) == 0
    chunks = list(RrdReader(out).stream())
    paths = {c.entity_path for c in chunks}
    assert {"/world/camera", "/world/camera/image", "/world/hand/mesh", "/world/object/mesh", "/world/hand/joints",
            "/world/sdf/hand_distance", "/world/sdf/object_distance", "/world/sdf/hand_part"} <= paths
    joints = {}
    for chunk in chunks:
        if chunk.entity_path == "/world/hand/joints":
            batch = chunk.to_record_batch()
            steps = batch.column(batch.schema.names.index("record")).to_pylist()
            for step, value in zip(steps, batch.column(batch.schema.names.index("Points3D:positions"))):
                joints[step] = np.asarray(value.values.flatten()).reshape(-1, 3)
    assert sorted(joints) == list(range(len(frames))) and len(frames) > 1  # one record per step of the timeline
    for step, record in enumerate(frames):
        np.testing.assert_allclose(joints[step], record[schema.META]["joints_3d"], rtol=1e-6, atol=1e-7)
