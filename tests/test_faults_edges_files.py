"""Issue 25, items 3 and 7: exports pinned to their inputs, and the smaller holes (a planted lock link, a --root
spelled two ways, damaged or absurdly nested JSON, a split listed twice, an unbounded --count, torch's refusal text,
an error that blamed the pipeline file for a command-line override, a rerun that said it wrote the index).

Each test tries other members of the class than the probe's listed case (docs/reliability.md,
"15. Edges: launchers, export inputs, folder options (issue 25)")."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from test_faults_build import SMALL, _build
from test_faults_edges import _one_error_line, _tree
from test_synthetic import ho3d_source, synth_store  # noqa: F401 - fixtures used below

from hoidata.cli import main as hoidata
from hoidata.errors import DataError


# --- item 3: exports pinned to their inputs ------------------------------------------------------------------------


def _changed_copy(folder: Path, dst: Path, name: str, edit) -> Path:
    """A copy of ``folder`` with file ``name`` edited (``edit(path)``)."""
    shutil.copytree(folder, dst)
    edit(dst / name)
    return dst


def _append(text: bytes):
    def edit(path: Path) -> None:
        with open(path, "ab") as f:  # a pickle stops at its end mark, an OBJ ignores a comment: both still load
            f.write(text)
    return edit


def _scale_obj(factor: float):
    def edit(path: Path) -> None:
        lines = [" ".join(["v", *(f"{float(x) * factor!r}" for x in line.split()[1:4])]) if line.startswith("v ")
                 else line for line in path.read_text().splitlines()]
        path.write_text("\n".join(lines) + "\n")
    return edit


def _move_object(path: Path) -> None:
    """Move the grasped object of one DexYCB label file by 1 mm (the labels stay consistent)."""
    import numpy as np

    labels = dict(np.load(path))
    labels["pose_y"] = labels["pose_y"].copy()
    labels["pose_y"][:, :, 3] += 0.001
    np.savez(path, **labels)


@pytest.mark.slow
def test_an_export_rerun_with_other_inputs_is_refused_naming_them(tiny_dexycb, tmp_path, capsys):
    root = shutil.copytree(tiny_dexycb, tmp_path / "data")
    mano2 = _changed_copy(root / "mano", tmp_path / "mano2", "MANO_RIGHT.pkl", _append(b"\n"))
    obj = "002_master_chef_can/textured_simple.obj"
    models2 = _changed_copy(root / "models", tmp_path / "models2", obj, _append(b"# edited\n"))
    out = tmp_path / "export"
    base = ["export", "--format", "handoccnet", "--dataset", "toy", "--root", str(root), "--out", str(out),
            "--splits", "train,train"]  # a split listed twice is one split
    assert hoidata(base) == 0
    capsys.readouterr()
    first = _tree(out)
    assert sorted(p.name for p in (out / ".hoidata-export").iterdir()) == ["handoccnet-train"]
    doc = json.loads((out / "annotations" / "DEX_YCB_s0_train_data.json").read_text())
    ids = [im["id"] for im in doc["images"]]
    assert len(ids) == len(set(ids)) == 16
    labels = sorted(root.glob("*/*/*/labels_000003.npz"))[0]
    for extra, words in ((["--mano", str(mano2)], "the MANO file MANO_RIGHT.pkl changed"),
                         (["--models", str(models2)], "the object model 002_master_chef_can changed"),
                         (["record.sdf_samples_hand=512"], "the setting record.sdf_samples_hand differs"),
                         (["annotations"], "the dataset's annotations")):
        if extra == ["annotations"]:
            _move_object(labels)
            extra = []
        assert hoidata([*base, *extra]) == 2, extra
        _one_error_line(capsys.readouterr().err, "export.json", words, "nothing was changed")
        assert _tree(out) == first  # nothing written


@pytest.mark.slow
def test_a_gsdf_export_uses_a_store_only_when_it_was_built_from_the_same_inputs(tiny_dexycb, tiny_store, tmp_path,
                                                                                capsys):
    from hoidata.export import gsdf
    from hoidata.export.job import export_frames
    from hoidata.build_sdf import build_inputs
    from hoidata.records.settings import load_build_config

    obj = "002_master_chef_can/textured_simple.obj"
    scaled = _changed_copy(tiny_dexycb / "models", tmp_path / "scaled", obj, _scale_obj(1.3))  # the probe's X1
    touched = _changed_copy(tiny_dexycb / "models", tmp_path / "touched", obj, _append(b"# edited\n"))
    mano2 = _changed_copy(tiny_dexycb / "mano", tmp_path / "mano2", "MANO_RIGHT.pkl", _append(b"\n"))
    base = ["export", "--format", "gsdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--store", str(tiny_store),
            "--splits", "train"]
    for n, (extra, words) in enumerate(((["--models", str(scaled)], "another object model 002_master_chef_can"),
                                        (["--models", str(touched)], "another object model 002_master_chef_can"),
                                        (["--mano", str(mano2)], "another MANO file MANO_RIGHT.pkl"))):
        out = tmp_path / f"out{n}"
        assert hoidata([*base, "--out", str(out), *extra]) == 2
        _one_error_line(capsys.readouterr().err, str(tiny_store / "build.json"), words, "--store")
        assert not out.exists()
    # the same files elsewhere (a copied models folder) are the same inputs: the store's rows are used
    same = shutil.copytree(tiny_dexycb / "models", tmp_path / "same")
    cfg = load_build_config("toy", ['dataset.splits=["train"]'])
    frames, _, _ = export_frames(cfg, tiny_dexycb, tiny_dexycb / "mano", same, ("train",))
    gsdf.check_store_inputs(tiny_store, build_inputs(frames, tiny_dexycb, tiny_dexycb / "mano", same))


# --- item 7: the smaller ones -----------------------------------------------------------------------------------


def test_the_index_lock_never_follows_a_planted_link(tmp_path):
    from hoidata.store.paths import index_lock

    store = tmp_path / "store"
    store.mkdir()
    victim, elsewhere = tmp_path / "victim", tmp_path / "created-elsewhere"
    victim.write_bytes(b"keep")
    stamp = victim.stat().st_mtime_ns
    for target in (victim, elsewhere, store / "index.lock.real"):
        (store / "index.lock").unlink(missing_ok=True)
        (store / "index.lock").symlink_to(target)
        with pytest.raises(DataError, match="symbolic link"), index_lock(store):
            pass
    assert victim.read_bytes() == b"keep" and victim.stat().st_mtime_ns == stamp
    assert not elsewhere.exists() and not (store / "index.lock.real").exists()
    (store / "index.lock").unlink()
    os.mkfifo(store / "index.lock")
    with pytest.raises(DataError, match="not a plain file"), index_lock(store):
        pass
    (store / "index.lock").unlink()
    with index_lock(store):  # a plain lock file works as before
        assert (store / "index.lock").is_file()


@pytest.mark.slow
def test_a_root_spelled_another_way_is_the_same_dataset(tiny_dexycb, tmp_path, monkeypatch, capsys):
    from hoidata import schema, store

    monkeypatch.chdir(tmp_path)
    (tmp_path / "link").symlink_to(tiny_dexycb)
    relative = os.path.relpath(tiny_dexycb, tmp_path)
    args = ["build-sdf", "--dataset", "toy", *SMALL]
    assert hoidata([*args, "--root", relative, "--out", "a"]) == 0
    assert hoidata([*args, "--root", "link/./", "--out", "b"]) == 0  # through a link, with ./ and a trailing slash
    shards = sorted(p.name for p in Path("a").iterdir() if p.name.startswith("shard-"))
    assert len(shards) >= 8 and shards == sorted(p.name for p in Path("b").iterdir() if p.name.startswith("shard-"))
    assert all((Path("a") / n).read_bytes() == (Path("b") / n).read_bytes() for n in shards), "bytes depend on --root"
    meta = next(store.iter_records(Path("a")))[schema.META]
    assert not os.path.isabs(meta["source"]["labels"]) and "tiny_dexycb" not in meta["source"]["labels"]
    (Path("a") / "shard-000000.tar").unlink()  # an interrupted build, resumed with the root spelled absolute
    capsys.readouterr()
    assert hoidata([*args, "--root", str(tiny_dexycb.resolve()) + "/", "--out", "a"]) == 0
    assert "1 shards written" in capsys.readouterr().out
    assert (Path("a") / shards[0]).read_bytes() == (Path("b") / shards[0]).read_bytes()


DEEP = "[" * 100_000 + "]" * 100_000


@pytest.mark.slow
def test_damaged_or_deeply_nested_json_is_one_line_naming_the_file(tiny_dexycb, tmp_path, capsys):
    from hoidata.export.job import chunk_done, read_manifest

    out = tmp_path / "export"
    base = ["export", "--format", "handoccnet", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(out),
            "--splits", "train"]
    assert hoidata(base) == 0
    capsys.readouterr()
    work = out / ".hoidata-export" / "handoccnet-train"
    spec, manifest = work / "export.json", work / "chunk-000000.json"
    good, files = spec.read_bytes(), _tree(out)
    for damage in (b"{", DEEP.encode(), b"\xff\xfe", b""):
        spec.write_bytes(damage)
        assert hoidata(base) == 2
        _one_error_line(capsys.readouterr().err, str(spec))
    spec.write_bytes(good)
    for damage in ('{"skipped": []}', DEEP, '{"entries": [{"files": 3}], "skipped": []}'):
        manifest.write_text(damage)
        with pytest.raises(DataError, match="chunk-000000.json"):
            read_manifest(work, 0)
        assert not chunk_done(out, work, 0)  # a damaged manifest: the chunk is exported again, the same files
        capsys.readouterr()
        assert hoidata(base) == 0 and "1 chunks written" in capsys.readouterr().out
        assert _tree(out) == files
    frame_list = tmp_path / "frames.json"
    frame_list.write_text(DEEP)
    assert hoidata(["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(tmp_path / "s"),
                    *SMALL, f"dataset.frame_list={frame_list}"]) == 2
    _one_error_line(capsys.readouterr().err, str(frame_list), "nested more than")


@pytest.mark.slow
def test_a_deeply_nested_build_file_is_one_line(tiny_dexycb, tmp_path, capsys):
    out = tmp_path / "store"
    _build(tiny_dexycb, out, part=(0, 4))
    (out / "build.json").write_text(DEEP)
    assert hoidata(["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(out), *SMALL]) == 2
    _one_error_line(capsys.readouterr().err, str(out / "build.json"))


@pytest.mark.slow
def test_render_synthetic_count_is_bounded_before_anything_is_allocated(tiny_store, tmp_path, capsys):
    from hoidata.render_synthetic import MAX_COUNT, render_synthetic

    out = tmp_path / "synth"
    for count in (10**12, MAX_COUNT + 1):
        assert hoidata(["render-synthetic", "--source", str(tiny_store), "--out", str(out), "--count",
                        str(count)]) == 2
        _one_error_line(capsys.readouterr().err, "--count", f"{MAX_COUNT:,}")
    with pytest.raises(ValueError, match="--count"):
        render_synthetic(tiny_store, out, 10**15, tiny_store / "mano", tiny_store / "models")
    assert not out.exists()


def test_torch_refusals_are_plain_and_never_advise_running_code(tmp_path, untrained_run):
    import torch

    from hoidata.reading_media import refusal_text
    from hoisdf.training.checkpoint import load_checkpoint

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'ran'}",))

    good = torch.load(untrained_run / "checkpoints" / "last.pt", weights_only=True, map_location="cpu")
    torch.save({**good, "extra": Payload()}, tmp_path / "crafted.pt")
    (tmp_path / "junk.pt").write_bytes(b"\x1b[31mnot a checkpoint")
    for name, words in (("crafted.pt", "would run code"), ("junk.pt", "damaged")):
        with pytest.raises(DataError) as caught:
            load_checkpoint(tmp_path / name)
        text = str(caught.value)
        assert str(tmp_path / name) in text and words in text and "\n" not in text, text
        assert "\x1b" not in text and "weights_only" not in text and "trusted" not in text, text
    assert not (tmp_path / "ran").exists()
    # the wording of other torch versions: bold codes, numbered advice, an allow-list hint after the finding
    older = ("Weights only load failed. This file can still be loaded, to do so you have two options, \x1b[1mdo those "
             "steps only if you trust the source of the checkpoint\x1b[0m.\n\t(1) Re-running `torch.load` with "
             "`weights_only` set to `False` will likely succeed, but it can result in arbitrary code execution.\n\t"
             "(2) Alternatively, load with `weights_only=True` after allow-listing.\n\tWeightsUnpickler error: "
             "Unsupported global: GLOBAL builtins.exec was not an allowed global by default. Please use "
             "`torch.serialization.add_safe_globals([exec])` to allowlist this global if you trust this class.")
    text = refusal_text(__import__("pickle").UnpicklingError(older))
    assert "GLOBAL builtins.exec" in text and "would run code" in text
    assert not any(w in text for w in ("\x1b", "weights_only", "add_safe_globals", "trust")), text


def test_an_error_caused_by_an_override_names_the_command_line(tmp_path):
    from hoidata.records.settings import load_build_config

    frame_list = tmp_path / "ids.json"
    frame_list.write_text("[1, 2]")
    with pytest.raises(DataError) as caught:  # the toy pipeline has three splits; the list came from the command line
        load_build_config("toy", [f"dataset.frame_list={frame_list}"])
    assert f"with the command line's dataset.frame_list={frame_list}" in str(caught.value)
    with pytest.raises(DataError) as caught:
        load_build_config("toy", ["dataset.name=ho4d"])
    assert "command line's dataset.name=ho4d" in str(caught.value)
    with pytest.raises(DataError) as caught:  # a mistake of the file itself still names the file alone
        load_build_config("toy", [f"dataset.frame_list={frame_list}", 'dataset.splits=["train"]',
                                  "record.sdf_backend=nope"])
    assert "command line" not in str(caught.value) and "toy.toml" in str(caught.value)


@pytest.mark.slow
def test_the_proximity_filter_reads_the_models_the_build_was_given(tiny_dexycb, tmp_path):
    """DexYCB's proximity filter (the dexycb preset) uses --models, as the SDF stage and export do, not ROOT/models."""
    from hoidata.export.job import export_frames
    from hoidata.build_sdf import read_frames
    from hoidata.records.settings import load_build_config

    root = tmp_path / "dataset"  # the dataset without its models folder: they live elsewhere
    root.mkdir()
    for item in tiny_dexycb.iterdir():
        if item.name != "models":
            (root / item.name).symlink_to(item)
    cfg = load_build_config("dexycb", ['dataset.splits=["train"]', "dataset.complete_subjects=false",
                                       "dataset.frame_stride=1"])
    assert cfg.dataset.proximity_mm > 0
    frames, skips = read_frames(cfg, root, root / "mano", tiny_dexycb / "models")
    exported, _, _ = export_frames(cfg, root, root / "mano", tiny_dexycb / "models", ("train",))
    assert [f.frame_id for f in frames] == [f.frame_id for f in exported]  # both commands select the same frames
    assert frames and not any("not found" in s.reason for s in skips), [s.reason for s in skips][:3]


@pytest.mark.slow
def test_a_synthetic_store_resumes_with_its_source_spelled_another_way(ho3d_source, synth_store, tmp_path,  # noqa: F811
                                                                       monkeypatch):
    from test_synthetic import _render

    out = shutil.copytree(synth_store[0], tmp_path / "store")
    (tmp_path / "link").symlink_to(ho3d_source)
    monkeypatch.chdir(tmp_path)
    again = _render(Path("link/./"), out)  # the same source through a link, relative: nothing to do
    assert again.units_written == 0 and again.units_kept > 0


@pytest.mark.slow
def test_a_rerun_of_a_finished_store_says_nothing_was_written(tiny_dexycb, tmp_path, capsys):
    out = tmp_path / "store"
    argv = ["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(out), *SMALL]
    assert hoidata(argv) == 0 and "index.zarr written" in capsys.readouterr().out
    before = _tree(out)
    assert hoidata(argv) == 0  # the probe's D4 ran this on a read-only disk: it said "index.zarr written"
    printed = capsys.readouterr().out
    assert "0 shards written" in printed and "index.zarr already lists every shard: nothing written" in printed
    assert "index.zarr written" not in printed and _tree(out) == before
