"""The store's dataset card and the other loaders' index files, on small stores written directly (no toy data)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import yaml
from test_store import build_store, make_record

from hoidata.store import ShardWriter, encode_record, index_labels, read_index, write_index
from hoidata.store.card import CARD_NAME, MIXED_SPLIT, hf_splits, write_store_files
from hoidata.store.loader_files import WIDS_DESCRIPTOR, dali_index_name
from hoidata.store.sources import source_of


def header(folder) -> dict:
    text = (folder / CARD_NAME).read_text()
    return yaml.safe_load(text.split("---\n")[1])


def test_the_card_declares_every_member_and_each_split_count(tmp_path):
    build_store(tmp_path, n=7, per_shard=3)
    assert write_store_files(tmp_path) == []
    card = header(tmp_path)
    assert card["configs"] == [{"config_name": "default", "data_files": [{"split": "train", "path": "shard-*.tar"}]}]
    info = card["dataset_info"]
    assert info["splits"] == [{"name": "train", "num_bytes": sum(s.size for s in read_index(tmp_path).shards),
                               "num_examples": 7}]
    features = {f["name"]: f for f in info["features"]}
    assert list(features) == ["__key__", "__url__", "img.jpg", "seg.png", "hm.png", "sdf.npy", "meta.json"]
    assert features["sdf.npy"]["dtype"] == {"array2_d": {"shape": [None, 6], "dtype": "int16"}}
    meta = {f["name"]: f for f in features["meta.json"]["struct"]}
    assert meta["K"]["dtype"]["array2_d"]["shape"] == [3, 3] and meta["source"]["dtype"] == "json"
    assert card["license"] == "other" and "not recorded" in (tmp_path / CARD_NAME).read_text()  # no source named
    datasets = pytest.importorskip("datasets")  # the card is written without it; here its own parser reads it
    parsed = datasets.Features._from_yaml_list(info["features"])
    assert parsed["sdf.npy"] == datasets.Array2D(shape=(None, 6), dtype="int16")
    assert parsed["meta.json"]["joints_3d"] == datasets.Array2D(shape=(21, 3), dtype="float64")


def test_the_card_and_index_files_are_the_same_bytes_when_rewritten(tmp_path):
    build_store(tmp_path, n=5, per_shard=2)
    write_store_files(tmp_path, "dexycb")
    first = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    write_store_files(tmp_path, "dexycb")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == first
    text = first[CARD_NAME].decode()
    assert "cc-by-nc-4.0" in text and "@inproceedings{chao2021dexycb" in text and "romero2017embodied" in text


def test_the_dali_index_is_what_dalis_own_wds2idx_writes(tmp_path):
    wds2idx = pytest.importorskip("wds2idx")  # ships with nvidia-dali
    if shutil.which("tar") is None:
        pytest.skip("wds2idx lists tars with GNU tar")
    build_store(tmp_path, n=7, per_shard=3)
    write_store_files(tmp_path)
    for info in read_index(tmp_path).shards:
        theirs = tmp_path / f"theirs-{info.number}.idx"
        with wds2idx.IndexCreator(str(tmp_path / info.name), str(theirs), verbose=False) as creator:
            creator.create_index()
        assert (tmp_path / dali_index_name(info.number)).read_text() == theirs.read_text()


def test_a_member_name_longer_than_the_tar_name_field_refuses_the_wids_descriptor(tmp_path):
    key = "toy-train-" + "f" * 85  # key.meta.json: 105 bytes, past ustar's 100-byte name field
    _, img, seg, hm, sdf, meta = make_record(0)
    meta = {**meta, "key": key, "frame_id": key[10:]}
    with ShardWriter(tmp_path, 4) as writer:
        writer.add(key, encode_record(key, img, seg, hm, sdf, meta))
    write_index(tmp_path, writer.shards, index_labels([meta]), {"002_master_chef_can": (np.eye(3), [[0, 1, 2]])}, [],
                {}, {})
    (tmp_path / WIDS_DESCRIPTOR).write_text("{}")  # an earlier build's: it would describe other names
    notes = write_store_files(tmp_path)
    assert len(notes) == 1 and f"{key}.img.jpg" in notes[0] and "100-byte" in notes[0] and "wids" in notes[0]
    assert not (tmp_path / WIDS_DESCRIPTOR).exists()
    assert notes[0] in (tmp_path / CARD_NAME).read_text()


def test_shards_that_mix_source_splits_make_one_split(tmp_path):
    build_store(tmp_path, n=7, per_shard=3)
    index = read_index(tmp_path)
    assert hf_splits(index) == {"train": [s.name for s in index.shards]}
    index.labels["split"] = np.array(["train"] * 4 + ["test"] * 3)  # shard 1 holds both
    assert hf_splits(index) == {MIXED_SPLIT: [s.name for s in index.shards]}
    index.labels["split"] = np.array(["train"] * 6 + ["test"])  # each shard one split
    assert hf_splits(index) == {"train": ["shard-000000.tar", "shard-000001.tar"], "test": ["shard-000002.tar"]}


def test_the_source_is_the_stores_own_else_its_reader_else_unknown():
    assert source_of({"dataset": {"name": "ho3d"}}, {"source_dataset": "toy"}) == "toy"
    assert source_of({"dataset": {"name": "ho3d"}}, {}) == "ho3d"
    assert source_of({"synthetic": {}}, {}) == "unknown"
    assert json.loads(json.dumps(source_of({}, {"source_dataset": "elsewhere"}))) == "unknown"


def test_a_build_from_a_folder_make_toy_wrote_records_the_toy_source(tmp_path):
    from hoidata.build_sdf import store_provenance
    from hoidata.records.settings import load_build_config
    from hoidata.store.sources import TOY_MARKER

    cfg = load_build_config("toy", ['dataset.splits=["train"]'])
    assert store_provenance(cfg, tmp_path)["source_dataset"] == "dexycb"
    (tmp_path / TOY_MARKER).write_text("{}")
    assert store_provenance(cfg, tmp_path)["source_dataset"] == "toy"
