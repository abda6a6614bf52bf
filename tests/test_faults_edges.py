"""Issue 25, items 2 and 4 ("nothing silent at the edges"): launchers forward exactly what was parsed, and every
folder option is resolved before any work (items 3 and 7: tests/test_faults_edges_files.py).

Each test tries other members of the class than the probe's listed case (docs/reliability.md,
"15. Edges: launchers, export inputs, folder options (issue 25)")."""

from __future__ import annotations

import os
import shlex
import shutil
import sys
from pathlib import Path

import pytest
from test_faults_build import SMALL

from hoidata.cli import main as hoidata
from hoidata.cli import parse_args
from hoidata.errors import DataError

URLS = ("s3://bucket/stores/x", "gs://bucket/x", "https://example.org/x", "http:/typo/x", "ftp://host/x")


def _one_error_line(err: str, *words: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in err, err[-1500:]
    assert all(w in lines[0] for w in words), lines[0]


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --- item 2: launchers forward exactly what was parsed ---------------------------------------------------------

LAUNCHER_DESTS = ("launcher", "ray_address", "slurm_array", "slurm_partition", "slurm_cpus", "slurm_time",
                  "slurm_extra", "slurm_executor", "dry_run", "part", "workers")
COMMANDS = {  # each command's own options, abbreviated where argparse lets them be (other prefixes than the probe's)
    "build-sdf": ["--datas", "toy", "--ro", "R", "--mod", "M", "--man", "MANO", "--ou", "OUT",
                  "record.sdf_samples_hand=256"],
    "export": ["--form", "gsdf", "--datas", "toy", "--ro", "R", "--ou", "OUT", "--sto", "{store}", "--spl",
               "train,test", "--man=-odd-mano-folder", "dataset.frame_stride=2"],
    "render-synthetic": ["--sou", "SRC", "--ou", "OUT", "--cou", "12", "--records-per", "4", "--crop", "64", "--man",
                         "MANO"],
}


@pytest.mark.slow
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_array_task_line_is_rebuilt_from_the_parsed_values(command, tiny_store, capsys):
    launcher = ["--laun", "slurm", "--slurm-ar", "3", "--slurm-c", "2", "--slurm-ti", "0-01:00", "--slurm-p", "cpu",
                "--slurm-ext", "account=lab", "--ray-addr", "auto", "--work", "7", "--dry"]
    own = [a.format(store=tiny_store) for a in COMMANDS[command]]
    argv = [command, *own[:2], "--deb", *launcher, *own[2:]]
    assert hoidata(argv) == 0
    line = shlex.split(capsys.readouterr().out.strip())
    flags = dict(item.partition("=")[::2] for item in line[1:] if item.startswith("--"))
    assert line[0] == "sbatch" and flags["--array"] == "0-2" and flags["--cpus-per-task"] == "2"
    task = shlex.split(flags["--wrap"])
    assert task[:2] == ["hoidata", command]
    original, again = parse_args(argv), parse_args(task[1:])
    # the task line names every option in full (no abbreviation of a launcher option survives), --workers its own
    actions = original.command_parser._actions
    names = {s for a in actions for s in a.option_strings}
    launcher_names = {s for a in actions if a.dest in LAUNCHER_DESTS for s in a.option_strings} - {"--workers"}
    used = [t.partition("=")[0] for t in task[2:] if t.startswith("-")]
    assert set(used) <= names and not set(used) & launcher_names, task
    assert again.launcher == "local" and again.slurm_array is None and not again.dry_run and again.part is None
    assert again.workers == 2  # the task's CPUs
    mine = {k: v for k, v in vars(original).items() if k not in (*LAUNCHER_DESTS, "argv", "command_parser")}
    assert mine == {k: v for k, v in vars(again).items() if k in mine}


@pytest.mark.slow
def test_a_task_inside_an_array_refuses_to_submit_another(tiny_dexycb, tmp_path, monkeypatch, capsys):
    bin_dir, marker = tmp_path / "bin", tmp_path / "sbatch-ran"
    bin_dir.mkdir()
    (bin_dir / "sbatch").write_text(f"#!/bin/sh\ntouch {marker}\n")
    (bin_dir / "sbatch").chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "1")
    monkeypatch.setenv("HOIDATA_PARTS", "2")
    out = tmp_path / "store"
    argv = ["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(out), *SMALL,
            "--launc", "slurm", "--slurm-a", "2", "--slurm-exe", "slurm"]
    assert hoidata(argv) == 2
    _one_error_line(capsys.readouterr().err, "inside Slurm array task 1", "SLURM_ARRAY_TASK_ID")
    assert not marker.exists() and not out.exists()


@pytest.mark.slow
def test_the_slurm_launcher_without_slurm_is_one_line(tiny_dexycb, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch anywhere
    monkeypatch.delenv("SLURM_ARRAY_TASK_ID", raising=False)
    for command, args in (("build-sdf", ["--dataset", "toy", "--root", str(tiny_dexycb), *SMALL]),
                          ("export", ["--format", "handoccnet", "--dataset", "toy", "--root", str(tiny_dexycb)])):
        out = tmp_path / command
        assert hoidata([command, *args, "--out", str(out), "--launcher", "slurm", "--slurm-array", "2"]) == 2
        _one_error_line(capsys.readouterr().err, "no sbatch")
        assert not out.exists()


def test_toy_commands_build_whole_stores_inside_an_array_task(tmp_path, monkeypatch, capsys):
    """An array task's environment (a seed sweep run as an array) is not a part of toy-pipeline's stores."""
    import hoisdf.toy
    from hoidata import build_sdf as runner

    def in_process(argv):  # the child's command line (python -m hoidata ...), run here so the stand-in sees it
        assert argv[:3] == [sys.executable, "-m", "hoidata"]
        return hoidata(argv[3:])

    monkeypatch.setattr(hoisdf.toy, "run_data", in_process)
    parts = []

    def build_store(*args, part, **kwargs):  # stands in for the build: records the part it was asked for
        parts.append(part)
        raise DataError(args[4], None, "stopped by the test")

    monkeypatch.setattr(runner, "build_store", build_store)
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "3")
    monkeypatch.setenv("SLURM_ARRAY_TASK_COUNT", "4")
    for name, run in (("a", lambda out: hoidata(["toy-pipeline", "--out", str(out)])),
                      ("b", lambda out: hoisdf.toy.main(["--out", str(out), "--steps", "1"]))):
        (tmp_path / name / "data" / "dexycb" / "mano").mkdir(parents=True)  # build-sdf's MANO folder, found
        (tmp_path / name / "data" / ("made-seed0" + ("--sequences10--frames5" if name == "b" else "") + ".ok")).touch()
        assert run(tmp_path / name) == 2  # the stand-in's error, after it saw the part
    assert parts == [(0, 1), (0, 1)]  # toy-pipeline and python -m hoisdf.toy: the whole store, not part 3 of 4
    assert capsys.readouterr().err.count("stopped by the test") == 2


# --- item 4: one resolver for every folder option ----------------------------------------------------------------


def _write_commands(url: str, root: Path, store: Path) -> list[list[str]]:
    base = ["--dataset", "toy", "--root", str(root)]
    return [["build-sdf", *base, "--out", url, *SMALL],
            ["build-sdf", "--dataset", "toy", "--root", url, "--out", "o1", *SMALL],
            ["export", "--format", "gsdf", *base, "--out", url],
            ["export", "--format", "gsdf", *base, "--out", "o2", "--store", url],
            ["export", "--format", "handoccnet", *base, "--out", "o3", "--models", url],
            ["render-synthetic", "--source", str(store), "--out", url, "--count", "2"],
            ["render-synthetic", "--source", url, "--out", "o4", "--count", "2"],
            ["make-toy", "--out", url], ["toy-pipeline", "--out", url], ["inspect", url],
            ["inspect", str(store), "--out", url + "/grid.png"]]


@pytest.mark.slow
@pytest.mark.parametrize("url", URLS)
def test_a_url_where_a_folder_is_needed_is_one_line_before_anything_is_written(url, tiny_dexycb, tiny_store,
                                                                               tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    for argv in _write_commands(url, tiny_dexycb, tiny_store):
        assert hoidata(argv) == 2, argv
        _one_error_line(capsys.readouterr().err, "not a URL", url)
    assert not list(tmp_path.iterdir())  # no folder named 'http:', 's3:', 'o1', ...


@pytest.mark.parametrize("module", ["hoisdf.train", "hoisdf.evaluate", "hoisdf.toy", "hoisdf.scoring.cli"])
def test_the_model_commands_refuse_a_url_as_out(module, tmp_path, monkeypatch, capsys):
    import importlib

    monkeypatch.chdir(tmp_path)
    main = importlib.import_module(module).main
    args = {"hoisdf.train": ["--shards", "s", "--mano", "m"], "hoisdf.evaluate": ["--ckpt", "c", "--shards", "s",
                                                                                   "--mano", "m"],
            "hoisdf.scoring.cli": ["ho3d", "--pred", "p.json", "--gt", "g"]}.get(module, [])
    for url in ("s3://bucket/run", "gs://b/run", "https://host/run"):
        with pytest.raises(SystemExit) as stop:
            main([*args, "--out", url])
        assert stop.value.code == 2 and "not a URL" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_an_export_store_that_cannot_be_opened_is_one_line_and_pins_nothing(tiny_dexycb, tiny_store, tmp_path,
                                                                             capsys):
    (tmp_path / "unfinished").mkdir()
    (tmp_path / "damaged").mkdir()
    shutil.copytree(tiny_store / "index.zarr", tmp_path / "damaged" / "index.zarr")
    (tmp_path / "damaged" / "index.zarr" / "zarr.json").write_text("{")
    out = tmp_path / "export"
    base = ["export", "--format", "gsdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out", str(out),
            "--splits", "train"]
    for store, words in ((tmp_path / "nonexistent" / "store", "no such store folder"),
                         (tmp_path / "unfinished", "index.zarr"), (tmp_path / "damaged", "index.zarr"),
                         (tiny_dexycb / "calibration", "index.zarr")):
        assert hoidata([*base, "--store", str(store)]) == 2
        _one_error_line(capsys.readouterr().err, str(store), words)
        assert not out.exists()  # nothing written: a later export into the same folder is not pinned to it
