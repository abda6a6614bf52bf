"""A folder of stores, the stores' preset and their MANO folder (hoisdf.data.store_choice), on stand-in facts: which
stores train and validate, which preset trains them, and one error line naming --shards / --config / --mano and
MANO_DIR where the folder is ambiguous or the MANO folder moved."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from hoidata.errors import DataError
from hoisdf.data.store_choice import (
    StoreFacts,
    choose_stores,
    folder_facts,
    folder_lines,
    folder_of_stores,
    stores_preset,
    training_mano,
)


def facts(name, split="train", pipeline="dexycb", preset=None, synthetic=False, mano=None, digest="d1", records=10):
    inputs = {"pipeline": pipeline, "train_preset": preset or pipeline, "preset_why": f"built with {pipeline}"}
    if mano is not None:
        inputs.update(mano=str(mano), mano_sha256={"MANO_RIGHT.pkl": digest})
    return StoreFacts(Path("shards") / name, split, records, inputs if pipeline else {}, synthetic)


def test_train_stores_train_and_the_test_stores_beside_them_validate():
    choice = choose_stores(Path("shards"), [facts("dexycb"), facts("dexycb_test", "test"),
                                            facts("ho3d_eval", "evaluation", "ho3d_eval"),
                                            facts("other_test", "test", "hot3d_clips")])
    assert [f.path.name for f in choice.train] == ["dexycb"]
    assert [f.path.name for f in choice.validation] == ["dexycb_test"]
    assert sorted(f.path.name for f, _ in choice.unused) == ["ho3d_eval", "other_test"]
    lines = folder_lines(Path("shards"), choice)
    assert lines[0] == "--shards shards: a folder of stores"
    assert any("shards/dexycb " in line and "1.0" in line and line.endswith("train") for line in lines)
    assert any("dexycb_test" in line and line.endswith("validation") for line in lines)


def test_val_stores_are_preferred_to_test_stores():
    stores = [facts("toy", pipeline="toy"), facts("toy_val", "val", "toy"), facts("toy_test", "test", "toy")]
    choice = choose_stores(Path("s"), stores)
    assert [f.path.name for f in choice.validation] == ["toy_val"]


@pytest.mark.parametrize("stores, words", [
    ([facts("dexycb_test", "test")], ("without a train store", "--shards", "dexycb_test (test)")),
    ([facts("both", "mixed")], ("several splits", "--shards", "test records")),
])
def test_an_ambiguous_folder_is_one_line(stores, words):
    with pytest.raises(DataError) as err:
        choose_stores(Path("shards"), stores)
    assert all(w in str(err.value) for w in words) and "\n" not in str(err.value)


def test_the_stores_preset():
    assert stores_preset([facts("dexycb")])[0] == "dexycb"
    toy = [facts("dexycb", preset="toy"), facts("ho3d_render", pipeline="ho3d_render", preset="toy", synthetic=True)]
    assert stores_preset(toy)[0] == "toy"
    paper = [facts("ho3d", pipeline="ho3d"), facts("ho3d_render", pipeline="ho3d_render", synthetic=True)]
    preset, why = stores_preset(paper)
    assert preset == "ho3d_render" and "co-trains" in why  # the paper's HO-3D + renders
    assert stores_preset([facts("old", pipeline=None)]) is None  # built before stores recorded their inputs


def test_presets_that_train_different_models_are_refused():
    for stores in ([facts("dexycb"), facts("ho3d", pipeline="ho3d")],
                   [facts("dexycb"), facts("ho3d_render", pipeline="ho3d_render", synthetic=True)]):
        with pytest.raises(DataError) as err:
            stores_preset(stores)
        assert "--shards" in str(err.value) and "--config" in str(err.value)


def _mano(folder: Path, content: bytes) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "MANO_RIGHT.pkl").write_bytes(content)
    return hashlib.sha256(content).hexdigest()


def test_mano_from_the_build_record_while_its_digest_holds(tmp_path, monkeypatch):
    monkeypatch.delenv("MANO_DIR", raising=False)
    digest = _mano(tmp_path / "mano", b"right hand")
    store = facts("dexycb", mano=tmp_path / "mano", digest=digest)
    assert training_mano(None, [store]).folder == tmp_path / "mano"
    assert training_mano(Path("given"), [store]).origin == "--mano"
    (tmp_path / "mano").rename(tmp_path / "moved")
    with pytest.raises(DataError) as err:
        training_mano(None, [store])
    text = str(err.value)
    assert "shards/dexycb" in text and "missing now" in text and "--mano" in text and "MANO_DIR" in text
    monkeypatch.setenv("MANO_DIR", str(tmp_path / "moved"))
    chosen = training_mano(None, [store])
    assert chosen.folder == tmp_path / "moved" and chosen.origin.startswith("MANO_DIR")
    _mano(tmp_path / "moved", b"another hand")
    with pytest.raises(DataError, match="holds another MANO_RIGHT.pkl"):
        training_mano(None, [store])


def test_a_changed_mano_file_and_stores_of_two_manos_are_refused(tmp_path, monkeypatch):
    monkeypatch.delenv("MANO_DIR", raising=False)
    digest = _mano(tmp_path / "mano", b"right hand")
    _mano(tmp_path / "mano", b"edited")
    with pytest.raises(DataError, match="changed since"):
        training_mano(None, [facts("a", mano=tmp_path / "mano", digest=digest)])
    with pytest.raises(DataError, match="another MANO_RIGHT.pkl than"):
        training_mano(None, [facts("a", mano=tmp_path / "x", digest="d1"),
                             facts("b", mano=tmp_path / "y", digest="d2")])
    with pytest.raises(DataError, match=r"does not record its MANO folder.*--mano.*MANO_DIR"):
        training_mano(None, [facts("old", pipeline=None)])


def test_a_folder_of_stores_is_told_from_a_store(tmp_path):
    (tmp_path / "shards/dexycb/index.zarr").mkdir(parents=True)
    assert folder_of_stores(str(tmp_path / "shards")) == tmp_path / "shards"
    assert folder_of_stores(str(tmp_path / "shards/dexycb")) is None  # a store
    assert folder_of_stores("https://example.org/shards") is None
    assert folder_of_stores(str(tmp_path / "empty")) is None
    (tmp_path / "shards/unfinished").mkdir()
    (tmp_path / "shards/unfinished/build.json").write_text("{}")
    (tmp_path / "shards/dexycb/index.zarr").rmdir()
    with pytest.raises(DataError, match="did not finish"):
        folder_facts(tmp_path / "shards")
