"""Issue 30, items 7 and 9: a list that names a thing twice, and a size that leaves a later stage with nothing to do,
are one line before anything is written. The promises:
docs/reliability.md, "19. Edges: full disks in training, repeated names, toy sizes (issue 30)".
Item 4 (training on a full disk) is in tests/test_disk_full.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from hoidata.cli import main as hoidata
from hoidata.errors import DataError


def _one_line(capsys, rc: int, *words: str) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and "error:" in lines[0] and "Traceback" not in err, err[-1500:]
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


# --- item 7: a list of names names each once ---------------------------------------------------------------------

REPEATS = ['dataset.splits=["train","train"]', 'dataset.sides=["right","left","right"]',
           'dataset.proximity_splits=["test","test"]', 'dataset.box_splits=["val","train","val"]',
           'record.crop_splits=["test","test"]']


@pytest.mark.parametrize("override", REPEATS)
@pytest.mark.parametrize("command", ["estimate", "build-sdf", "export"])
def test_a_repeated_name_in_a_list_setting_is_one_line_before_anything_is_written(tmp_path, capsys, override,
                                                                                   command):
    """was: build-sdf --estimate counted every frame of dataset.splits=["train","train"] twice (96 of 48)."""
    out = tmp_path / "out"
    argv = (["export", "--format", "gsdf"] if command == "export" else ["build-sdf"]) + [
        "--dataset", "toy", "--root", str(tmp_path / "toy"), "--out", str(out), override]
    rc = hoidata(argv + (["--estimate"] if command == "estimate" else []))
    key, _, value = override.partition("=")
    _one_line(capsys, rc, f"'{key}'", "more than once", f"the command line's {override}")
    assert not out.exists()


def test_a_repeat_in_a_pipeline_file_names_the_file(tmp_path):
    from hoidata.records.settings import load_build_config

    toml = tmp_path / "p.toml"
    toml.write_text('[dataset]\nname = "dexycb"\nsplits = ["train", "test", "train"]\n')
    with pytest.raises(DataError, match=r"p\.toml: 'dataset\.splits': names 'train' more than once"):
        load_build_config(str(toml))
    assert load_build_config(str(toml), ['dataset.splits=["train","test"]']).dataset.splits == ("train", "test")


def test_reading_a_split_twice_is_refused_below_the_settings(tmp_path):
    """read_splits, the one way every command reads a dataset, refuses a repeated split too: no duplicate records."""
    from hoidata.datasets.open import read_splits

    with pytest.raises(DataError, match="names a split more than once"):
        read_splits("dexycb", tmp_path, tmp_path, ("train", "test", "train"))


def _store_twice(tmp_path: Path, monkeypatch) -> list[tuple[str, str]]:
    store = tmp_path / "store"
    store.mkdir()
    (tmp_path / "link").symlink_to(store)
    monkeypatch.chdir(tmp_path)
    return [("store", "store"), ("store", "./store/"), (str(store), "link"), ("store:1", "store:2"),
            ("http://h:8000/s?sig=a", "http://h:8000/s/?sig=b")]


def test_a_store_named_twice_is_one_line(tmp_path, monkeypatch, capsys):
    """train --shards / --val-shards and evaluate --shards: the same store twice, spelled the same or another way."""
    from hoisdf.evaluate import main as evaluate
    from hoisdf.train import main as train

    out = tmp_path / "out"
    for a, b in _store_twice(tmp_path, monkeypatch):
        rc = train(["--shards", a, b, "--mano", "mano", "--out", str(out), "--no-progress"])
        _one_line(capsys, rc, "--shards names this store twice", "STORE:2")
        rc = train(["--shards", "other", "--val-shards", a.partition(":")[0] if "//" not in a else a,
                    b.partition(":")[0] if "//" not in b else b, "--mano", "mano", "--out", str(out)])
        _one_line(capsys, rc, "--val-shards names this store twice")
        rc = evaluate(["--ckpt", "run", "--shards", a.partition(":")[0] if "//" not in a else a,
                       b.partition(":")[0] if "//" not in b else b, "--mano", "mano", "--out", str(out)])
        _one_line(capsys, rc, "the stores to evaluate (--shards) names this store twice")
    assert not out.exists()
    rc = train(["--shards", "http://alice:secret@h/s", "http://alice:secret@h/s/", "--mano", "m", "--out", str(out)])
    assert "secret" not in _one_line(capsys, rc, "twice")


# --- item 9: sizes that leave a later stage with nothing to do ----------------------------------------------------

@pytest.mark.parametrize("sequences", [1, 2, 3, 4])
def test_a_toy_chain_size_without_a_test_split_is_refused_before_anything_is_written(tmp_path, capsys, sequences):
    """was: toy-pipeline --sequences 1-4 built and verified the train store, then ended with 'no frames to build for
    splits ('test',)'."""
    out = tmp_path / "run"
    rc = hoidata(["toy-pipeline", "--out", str(out), "--sequences", str(sequences)])
    _one_line(capsys, rc, f"--sequences {sequences}", "--sequences 5 or more", "nothing was written")
    assert not out.exists()


@pytest.mark.parametrize("layout", ["ho3d", "ho3d_v3"])
def test_more_toy_ho3d_sequences_than_it_has_is_refused(tmp_path, capsys, layout):
    """was: make-toy --layout ho3d --sequences 5 wrote 3 training sequences without a word."""
    out = tmp_path / "toy"
    rc = hoidata(["make-toy", "--out", str(out), "--layout", layout, "--sequences", "4"])
    _one_line(capsys, rc, "--sequences 4", "3 training sequences", "give 1 to 3")
    assert not out.exists()


def test_make_toy_all_gives_ho3d_its_three_sequences_and_says_so(tmp_path, capsys, monkeypatch):
    """--layout all --sequences 10 (python -m hoisdf.toy's default) is DexYCB's size; HO-3D gets its 3, with a note."""
    import hoidata.records.inputs as inputs
    import hoidata.toy.make as make

    calls = []
    monkeypatch.setattr(make, "make_toy", lambda root, layout, **kw: calls.append((layout, kw["sequences"])) or {})
    monkeypatch.setattr(make, "split_rows", lambda root, layout: [])
    monkeypatch.setattr(inputs, "mano_rows", lambda folder: [])
    monkeypatch.setattr(inputs, "object_rows", lambda folder, cache_dir=None: [])
    assert hoidata(["make-toy", "--out", str(tmp_path / "toy"), "--sequences", "10"]) == 0
    assert calls == [("dexycb", 10), ("ho3d", 3)]
    assert "note: --sequences 10 is DexYCB's; the toy HO-3D gets its 3 training sequences" in capsys.readouterr().out


def test_empty_split_notes_name_the_splits_and_the_size_that_fills_them():
    from hoidata.toy.make import empty_split_notes

    rows = [{"setting": "dexycb_full", "split": s, "frames": n} for s, n in (("train", 8), ("val", 0), ("test", 0))]
    assert empty_split_notes(rows, "dexycb", 3) == [
        "note: no frames in dexycb_full val, dexycb_full test at this size: the toolkit puts a subject's 5th sequence "
        "in val or test, give --sequences 5 or more"]
    assert empty_split_notes(rows[:1], "dexycb", 3) == []


@pytest.mark.slow  # writes a toy dataset
def test_make_toy_names_the_splits_its_size_leaves_empty(tmp_path, capsys):
    assert hoidata(["make-toy", "--out", str(tmp_path / "toy"), "--layout", "dexycb", "--sequences", "1",
                    "--frames", "1"]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note: no frames in")]
    assert len(notes) == 1 and "dexycb_full test" in notes[0] and "--sequences 5 or more" in notes[0], notes


@pytest.mark.slow  # starts the data step as a child process
def test_the_main_job_refuses_the_size_in_its_data_step_before_anything_is_written(tmp_path, capfd):
    from hoisdf.toy import main as toy

    out = tmp_path / "job"
    rc = toy(["--out", str(out), "--sequences", "3", "--steps", "1"])
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and "--sequences 3" in lines[0] and "Traceback" not in err, err[-1500:]
    assert not out.exists()


def test_empty_splits_are_the_asked_splits_without_a_frame():
    from types import SimpleNamespace

    from hoidata.build_sdf import empty_splits

    frames = [SimpleNamespace(split="train"), SimpleNamespace(split="test")]
    assert empty_splits(("train", "val", "test"), frames) == ("val",)
    assert empty_splits(("train",), frames) == ()


@pytest.mark.slow  # reads and builds the tiny toy DexYCB
def test_a_split_asked_for_but_without_frames_is_named(tiny_dexycb, tmp_path, capsys):
    """The toy pipeline asks for train, val and test; the tiny toy (2 sequences a subject) has train frames only. The
    store is built from them, and the estimate and the build summary name the splits it holds none of."""
    base = ["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(tmp_path / "s"),
            "dataset.frame_stride=8", "record.crop_size=64", "record.sdf_samples_hand=64", "record.sdf_samples_object=32"]
    assert hoidata([*base, "--estimate"]) == 0
    assert "splits_without_frames: val, test" in capsys.readouterr().out
    assert hoidata(base) == 0
    out = capsys.readouterr().out
    assert f"note: no frames in split(s) val, test of {tiny_dexycb}: the store holds none of them" in out, out
