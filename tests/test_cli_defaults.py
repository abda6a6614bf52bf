"""Where the commands look when a folder is not given (hoidata.cli_defaults), and help lists made from what exists.

Each missing input is one error line naming the flag and the variable, with nothing written; every name a command's
help lists (pipelines, make-toy layouts, export formats, launchers) comes from its table or folder, so a file or a
layout added there is listed without another edit.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from hoidata import cli_defaults as defaults
from hoidata.cli import main as hoidata
from hoidata.engine.launch import LAUNCHERS
from hoidata.export.formats import FORMATS
from hoidata.records.settings import load_build_config
from hoidata.sections import pipelines_dir
from hoidata.toy.make import LAYOUTS, MARKER

VARIABLES = ("DEX_YCB_DIR", "HO3D_DIR", "HO3D_V3_DIR", "HOT3D_CLIPS_DIR", "MANO_DIR")


@pytest.fixture
def bare(tmp_path, monkeypatch):
    """An empty working folder and none of the dataset variables set."""
    for name in VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit):
        hoidata([*argv, "--help"])
    return " ".join(capsys.readouterr().out.split())  # argparse's wrapping undone


@pytest.mark.parametrize("dataset, variable", [("dexycb", "DEX_YCB_DIR"), ("ho3d", "HO3D_DIR"),
                                               ("ho3d_v3", "HO3D_V3_DIR"), ("hot3d_clips", "HOT3D_CLIPS_DIR")])
def test_a_missing_dataset_folder_names_the_flag_and_the_variable(bare, capsys, dataset, variable):
    assert hoidata(["build-sdf", "--dataset", dataset]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "--root" in line and variable in line and "nothing was written" in line
    assert list(bare.iterdir()) == []


def test_a_variable_naming_no_folder_is_one_line(bare, monkeypatch, capsys):
    monkeypatch.setenv("DEX_YCB_DIR", str(bare / "nowhere"))
    assert hoidata(["build-sdf", "--dataset", "dexycb"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "DEX_YCB_DIR=" in line and "not a folder" in line and "--root" in line
    assert list(bare.iterdir()) == []


def test_the_dataset_folder_comes_from_the_flag_then_the_variable(bare, monkeypatch):
    where = defaults.home(load_build_config("dexycb").dataset)
    monkeypatch.setenv("DEX_YCB_DIR", str(bare))
    assert defaults.dataset_folder(None, where) == defaults.Chosen("root", bare, "DEX_YCB_DIR")
    assert defaults.dataset_folder("elsewhere", where) == defaults.Chosen("root", Path("elsewhere"), "--root")


def test_mano_comes_from_the_flag_the_dataset_folder_then_mano_dir(bare, monkeypatch):
    with pytest.raises(ValueError, match=r"--mano .*MANO_DIR"):
        defaults.mano_folder(None, bare)
    monkeypatch.setenv("MANO_DIR", "/somewhere/mano")
    assert defaults.mano_folder(None, bare) == defaults.Chosen("mano", Path("/somewhere/mano"), "MANO_DIR")
    (bare / "mano").mkdir()
    assert defaults.mano_folder(None, bare).value == bare / "mano"  # the dataset folder's own (make-toy's layout)
    assert defaults.mano_folder("m", bare).origin == "--mano"


def test_models_default_to_where_each_dataset_ships_its_meshes(tmp_path):
    for name, folder in (("dexycb", "models"), ("ho3d", "models"), ("hot3d_clips", "object_models_eval")):
        where = defaults.home(load_build_config(name).dataset)
        assert defaults.models_folder(None, tmp_path, where).value == tmp_path / folder
    assert defaults.models_folder("M", tmp_path, where).origin == "--models"


def test_the_default_stores_are_one_per_split_under_shards():
    assert defaults.split_stores("dexycb", ("train", "test")) == [("train", Path("shards/dexycb")),
                                                                 ("test", Path("shards/dexycb_test"))]
    assert defaults.split_stores("my/own.toml", ("evaluation",)) == [("evaluation", Path("shards/own"))]


def test_make_toys_data_trains_under_the_toy_preset(tmp_path):
    assert defaults.training_preset("dexycb", tmp_path) == ("dexycb", "built with pipelines/dexycb.toml")
    (tmp_path / MARKER).write_text("{}")
    assert defaults.training_preset("dexycb", tmp_path)[0] == "toy"
    assert defaults.toy_overrides(tmp_path, load_build_config("dexycb")) == [
        "dataset.complete_subjects=false", "record.upstream_region=[]"]
    assert defaults.toy_overrides(tmp_path, load_build_config("toy")) == []
    assert defaults.synth_preset(tmp_path, {})[0] == "toy"
    assert defaults.synth_preset(tmp_path.parent, {"train_preset": "toy"})[0] == "toy"
    assert defaults.synth_preset(tmp_path.parent, {"train_preset": "ho3d"})[0] == "ho3d_render"


def test_render_synthetic_without_a_source_names_the_flag_and_the_variable(bare, capsys):
    assert hoidata(["render-synthetic"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "--source" in line and "HO3D_DIR" in line and "shards/ho3d" in line
    assert list(bare.iterdir()) == []


def test_render_synthetic_takes_its_grasps_from_ho3d_dir_when_shards_ho3d_is_no_store(bare, monkeypatch):
    monkeypatch.setenv("HO3D_DIR", str(bare / "ho3d"))
    chosen = defaults.synth_source(None)
    assert chosen.value == bare / "ho3d" and chosen.origin.startswith("HO3D_DIR")
    (bare / "shards/ho3d/index.zarr").mkdir(parents=True)
    assert defaults.synth_source(None).value == Path("shards/ho3d")


# --- help that cannot go stale ---------------------------------------------------------------------------------

def _pipeline_files() -> list[str]:
    return sorted(p.name[:-5] for p in pipelines_dir().iterdir() if p.name.endswith(".toml"))


def test_every_pipeline_file_is_listed_in_the_help(capsys):
    assert len(_pipeline_files()) >= 11
    for command in ("build-sdf", "export"):
        text = _help([command], capsys)
        missing = [name for name in _pipeline_files() if not re.search(rf"\b{name}\b", text)]
        assert not missing, f"{command} --help leaves out {missing}"


def test_a_pipeline_file_added_is_listed(tmp_path, monkeypatch, capsys):
    import hoidata.sections

    for path in pipelines_dir().iterdir():
        (tmp_path / path.name).write_bytes(path.read_bytes()) if path.is_file() else None
    (tmp_path / "brand_new.toml").write_text((tmp_path / "toy.toml").read_text())
    monkeypatch.setattr(hoidata.sections, "CHECKOUT_PIPELINES", tmp_path)
    assert "brand_new" in _help(["build-sdf"], capsys)


def test_every_layout_format_and_launcher_is_listed(capsys, monkeypatch):
    top = _help([], capsys)
    toy = _help(["make-toy"], capsys)
    for layout in LAYOUTS:
        assert re.search(rf"\b{layout}\b", toy) and re.search(rf"\b{layout}\b", top), layout
    export = _help(["export"], capsys)
    assert all(re.search(rf"\b{name}\b", export) for name in FORMATS)
    build = _help(["build-sdf"], capsys)
    assert all(re.search(rf"\b{name}\b", build) for name in LAUNCHERS)
    monkeypatch.setitem(LAYOUTS, "arctic_like", "a layout added to the table")
    assert "arctic_like" in _help(["make-toy"], capsys)


def test_the_training_help_lists_the_pipelines(capsys):
    from hoisdf.train import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert not [name for name in _pipeline_files() if not re.search(rf"\b{name}\b", text)]
