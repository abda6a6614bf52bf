"""The user's three commands exactly as written, in a fresh folder with only the environment set (slow tier):

    hoidata build-sdf --dataset dexycb
    hoidata render-synthetic
    python -m hoisdf.train --shards shards/

on make-toy's data laid out where the defaults look (DEX_YCB_DIR, HO3D_DIR, MANO_DIR). The third trains on what the
first two wrote, under the toy preset its stores recorded; the test stops it (SIGTERM, as a scheduler would) once
its first training step is logged, so the test is about the chain, not about a finished run. And a store of the
dexycb pipeline on data that is not make-toy's trains under that preset's upstream recipe without --config, with
its MANO folder from its build record, refused in one line once that folder moved.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hoidata.cli import main as hoidata
from hoisdf.train import main as train

VARIABLES = ("DEX_YCB_DIR", "HO3D_DIR", "HO3D_V3_DIR", "HOT3D_CLIPS_DIR", "MANO_DIR")


def _environment(**variables) -> dict:
    """This process's environment without the dataset variables, with ``variables`` and the venv first on PATH."""
    env = {k: v for k, v in os.environ.items() if k not in VARIABLES}
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return {**env, **{k: str(v) for k, v in variables.items()}}


def _run(argv: list[str], cwd: Path, env: dict) -> str:
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, (f"{' '.join(argv)} exited {done.returncode}:\n{done.stdout[-3000:]}\n"
                                  f"{done.stderr[-3000:]}")
    return done.stdout


def _first_step(argv: list[str], cwd: Path, env: dict, curve: Path, limit: float = 420.0) -> str:
    """Run ``argv`` until ``curve`` logs a training step, then stop it with SIGTERM; returns what it printed."""
    log = cwd / "train.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + limit
            while time.monotonic() < deadline and proc.poll() is None:
                if curve.is_file() and any(line.startswith("train,") for line in curve.read_text().splitlines()):
                    break
                time.sleep(1.0)
            else:
                pytest.fail(f"no training step logged (exit {proc.poll()}):\n{log.read_text()[-3000:]}")
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)  # the run and its loader workers: this test's own processes
                proc.wait(timeout=60)
    return log.read_text()


@pytest.mark.slow
def test_the_three_commands_run_as_written_on_the_toy(tmp_path):
    env = _environment(HOIDATA_CACHE=tmp_path / "cache")
    _run(["hoidata", "make-toy", "--out", "toy", "--sequences", "5", "--frames", "1"], tmp_path, env)  # the set-up
    work = tmp_path / "fresh"
    work.mkdir()
    env = _environment(DEX_YCB_DIR=tmp_path / "toy/dexycb", HO3D_DIR=tmp_path / "toy/ho3d",
                       MANO_DIR=tmp_path / "toy/dexycb/mano", HOIDATA_CACHE=tmp_path / "cache")

    first = _run(["hoidata", "build-sdf", "--dataset", "dexycb"], work, env)
    assert f"{tmp_path / 'toy/dexycb'}" in first and "(DEX_YCB_DIR)" in first
    assert (work / "shards/dexycb/index.zarr").is_dir() and (work / "shards/dexycb_test/index.zarr").is_dir()

    second = _run(["hoidata", "render-synthetic"], work, env)
    assert "HO3D_DIR" in second and (work / "shards/ho3d_render/index.zarr").is_dir()

    third = _first_step(["python", "-m", "hoisdf.train", "--shards", "shards/"], work, env,
                        work / "runs/toy/metrics.csv")
    table = {line.split()[0]: line.split()[1:] for line in third.splitlines() if line.startswith("  shards/")}
    assert table["shards/dexycb"][0] == "train" and table["shards/dexycb"][-1] == "train"
    assert table["shards/ho3d_render"][-1] == "train" and table["shards/dexycb_test"][-1] == "validation"
    assert "config: pipelines/toy.toml (the stores' preset" in third
    assert f"mano: {tmp_path / 'toy/dexycb/mano'} (the build record of shards/dexycb)" in third
    info = json.loads((work / "runs/toy/config.json").read_text())
    assert [Path(p).name for p, _ in info["stores"]] == ["dexycb", "ho3d_render"]
    assert [Path(p).name for p in info["val_stores"]] == ["dexycb_test"]


@pytest.mark.slow
def test_a_dexycb_store_trains_under_its_preset_with_the_mano_it_was_built_with(tiny_dexycb, tmp_path, monkeypatch,
                                                                                capsys):
    for name in VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.chdir(tmp_path)
    shutil.copytree(tiny_dexycb / "mano", tmp_path / "mano")
    monkeypatch.setenv("DEX_YCB_DIR", str(tiny_dexycb))  # not make-toy's folder: no toy mark
    assert hoidata(["build-sdf", "--dataset", "dexycb", "--mano", "mano", "dataset.complete_subjects=false"]) == 0
    assert "shards/dexycb_test not written" in capsys.readouterr().out  # the tiny toy has no test frames

    assert train(["--shards", "shards/dexycb", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert 'train.recipe = "upstream"' in out
    assert "config: pipelines/dexycb.toml (the stores' preset; shards/dexycb: built with pipelines/dexycb.toml)" in out
    assert f"mano: {tmp_path / 'mano'} (the build record of shards/dexycb)" in out

    (tmp_path / "mano").rename(tmp_path / "moved")
    assert train(["--shards", "shards/dexycb", "--dry-run"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "missing now" in err[0] and "--mano" in err[0] and "MANO_DIR" in err[0]
    monkeypatch.setenv("MANO_DIR", str(tmp_path / "moved"))  # the same files elsewhere: taken, as their digest holds
    assert train(["--shards", "shards/dexycb", "--dry-run"]) == 0
    assert f"mano: {tmp_path / 'moved'} (MANO_DIR" in capsys.readouterr().out
    assert not (tmp_path / "runs").exists()  # --dry-run writes nothing
