"""Cluster launchers for the build (issue 16), with no cluster: a Slurm array's tasks (read from the environment,
as ``--dry-run``'s sbatch line runs them), submitit's local executor and a local Ray instance all write the shards
of a local build, byte for byte, and resume the same way; the last part to finish writes the index, whatever the
order, and concurrent finishers write it one at a time."""

from __future__ import annotations

import multiprocessing as mp
import shlex
import shutil
import threading
from pathlib import Path

import pytest
from test_faults_build import SMALL, _build
from test_synthetic import RECORD, _render, ho3d_source, synth_store  # noqa: F401 - fixtures used below

from hoidata import store
from hoidata.cli import main as hoidata
from hoidata.errors import DataError
from hoidata.records import store_writer as finish
from hoidata.engine.slurm import array_part, resolve_part, slurm_minutes

pytestmark = pytest.mark.slow  # Slurm/submitit/Ray builds in subprocesses


@pytest.fixture(scope="module")
def local_build(tiny_dexycb, tmp_path_factory):
    out = tmp_path_factory.mktemp("local_build") / "store"
    assert _build(tiny_dexycb, out).finished
    return out


def _build_args(root: Path, out: Path, *extra: str) -> list[str]:
    return ["build-sdf", "--dataset", "toy", "--root", str(root), "--out", str(out), *SMALL, *extra]


def _files(folder: Path) -> dict[str, bytes]:
    """Every shard and sidecar of a store, by name."""
    return {p.name: p.read_bytes() for p in sorted(folder.glob("shard-*")) if p.suffix in (".tar", ".json")}


def _same_store(a: Path, b: Path) -> None:
    assert _files(a) == _files(b) and len(_files(a)) >= 8
    ia, ib = store.read_index(a), store.read_index(b)
    assert ia.shards == ib.shards and ia.keys == ib.keys and store.verify_store(b).ok


# --- Slurm: parts from the array task's environment --------------------------------------------------------------


def test_the_array_task_environment_gives_the_part():
    assert array_part({}) is None and resolve_part(None, {}) == (0, 1)
    task = {"SLURM_ARRAY_TASK_ID": "3", "SLURM_ARRAY_TASK_COUNT": "8", "SLURM_ARRAY_TASK_MIN": "0"}
    assert array_part(task) == (3, 8) and resolve_part((1, 2), task) == (1, 2)  # an explicit --part wins
    assert array_part({**task, "SLURM_ARRAY_TASK_MIN": "1"}) == (2, 8)  # --array=1-8
    assert array_part({"SLURM_ARRAY_TASK_ID": "6", "SLURM_ARRAY_TASK_COUNT": "8", "SLURM_ARRAY_TASK_MIN": "0",
                       "SLURM_ARRAY_TASK_STEP": "2"}) == (3, 8)  # --array=0-14:2
    rerun = {"SLURM_ARRAY_TASK_ID": "5", "SLURM_ARRAY_TASK_COUNT": "1", "SLURM_ARRAY_TASK_MIN": "5"}
    assert array_part({**rerun, "HOIDATA_PARTS": "8"}) == (5, 8)  # one task of 8 resubmitted: still part 5 of 8
    with pytest.raises(DataError, match="pass --part"):
        array_part({"SLURM_ARRAY_TASK_ID": "9", "SLURM_ARRAY_TASK_COUNT": "3", "SLURM_ARRAY_TASK_MIN": "1",
                    "SLURM_ARRAY_TASK_STEP": "3"})  # --array=1,4,9 is not evenly spaced
    with pytest.raises(DataError, match="pass --part"):
        array_part({**rerun, "HOIDATA_PARTS": "4"})
    assert [slurm_minutes(t) for t in ("90", "30:10", "2:00:00", "1-00", "1-02:30", "0-00:00:30")] == \
        [90, 31, 120, 1440, 1590, 1]


def test_the_dry_run_line_runs_as_array_tasks_finishing_in_any_order(tiny_dexycb, local_build, tmp_path, capsys,
                                                                     monkeypatch):
    out = tmp_path / "store"
    argv = _build_args(tiny_dexycb, out, "--launcher", "slurm", "--slurm-array", "3", "--slurm-cpus", "1",
                       "--slurm-partition", "cpu", "--slurm-time", "0-01:00", "--slurm-extra", "account=lab",
                       "--dry-run")
    assert hoidata(argv) == 0
    line = shlex.split(capsys.readouterr().out.strip())
    flags = dict(item.partition("=")[::2] for item in line[1:])
    assert line[0] == "sbatch" and flags["--array"] == "0-2" and flags["--time"] == "60"
    assert flags["--partition"] == "cpu" and flags["--account"] == "lab" and "HOIDATA_PARTS=3" in flags["--export"]
    task = shlex.split(flags["--wrap"])
    assert task[:2] == ["hoidata", "build-sdf"] and "--launcher" not in task and "--part" not in task
    assert not out.exists()  # nothing submitted, nothing written
    monkeypatch.setenv("HOIDATA_PARTS", "3")
    for index in (2, 0, 1):  # the tasks, finishing in any order; the last one writes the index
        monkeypatch.setenv("SLURM_ARRAY_TASK_ID", str(index))
        assert hoidata(task[1:]) == 0
        written = "index.zarr written" in capsys.readouterr().out
        assert written == (index == 1)
    _same_store(local_build, out)
    index_file = (out / "index.zarr" / "zarr.json").read_bytes()
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "0")  # a task rerun after the store is done: nothing changes
    assert hoidata(task[1:]) == 0 and "0 shards written" in capsys.readouterr().out
    assert (out / "index.zarr" / "zarr.json").read_bytes() == index_file


def test_a_submitit_array_writes_the_local_shards(tiny_dexycb, local_build, tmp_path, capsys):
    pytest.importorskip("submitit")
    out = tmp_path / "store"
    argv = _build_args(tiny_dexycb, out, "--launcher", "slurm", "--slurm-executor", "local", "--slurm-array", "2",
                       "--slurm-cpus", "1", "--slurm-time", "10")
    assert hoidata(argv) == 0
    printed = capsys.readouterr().out
    assert "submitted 2 parts" in printed and "16 records written" in printed and "index.zarr written" in printed
    _same_store(local_build, out)
    assert sorted(p.name for p in (out / ".slurm").glob("*/*.out"))  # each task's log


def test_a_failed_array_part_is_one_line_naming_it(tiny_dexycb, tmp_path, capsys):
    pytest.importorskip("submitit")
    argv = _build_args(tiny_dexycb, tmp_path / "store", "--mano", str(tmp_path / "no-mano"), "--launcher", "slurm",
                       "--slurm-executor", "local", "--slurm-array", "2", "--slurm-cpus", "1")
    assert hoidata(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("error:") == 1 and "part 0/2" in err, err[-2000:]
    assert "DataError: " in err and "MANO right model file not found" in err, err[-2000:]  # the task's own error


# --- Ray ---------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=80 << 20)
    yield ray
    ray.shutdown()


def test_ray_tasks_write_the_local_shards_and_resume_the_same_way(local_ray, tiny_dexycb, local_build, tmp_path,
                                                                  capsys):
    out = tmp_path / "store"
    assert hoidata(_build_args(tiny_dexycb, out, "--launcher", "ray", "--workers", "2")) == 0
    _same_store(local_build, out)
    (out / "shard-000002.tar").write_bytes(b"damaged")  # resume: only this one is built again
    capsys.readouterr()
    assert hoidata(_build_args(tiny_dexycb, out, "--launcher", "ray", "--part", "0/1")) == 0
    assert "1 shards written" in capsys.readouterr().out
    _same_store(local_build, out)


def test_ray_renders_the_synthetic_store_of_a_local_run(local_ray, ho3d_source, synth_store, tmp_path):  # noqa: F811
    from functools import partial

    from hoidata.engine.ray_tasks import run_ray

    local, _ = synth_store
    out = tmp_path / "ray"
    assert _render(ho3d_source, out, workers=2, executor=partial(run_ray, address=None)).finished
    assert _files(out) == _files(local) and RECORD.crop_size == 128


def test_a_data_error_in_a_ray_task_is_the_error_itself(local_ray, tiny_dexycb, tmp_path, capsys):
    root = tmp_path / "dexycb"
    shutil.copytree(tiny_dexycb, root)
    for obj in (root / "models").glob("*/textured_simple.obj"):
        obj.write_text("not an obj\n")  # every frame fails: the store has no records
    assert hoidata(_build_args(root, tmp_path / "s", "--launcher", "ray")) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "no records" in err.strip().splitlines()[-1], err[-2000:]


# --- the index: written once, by one finisher at a time ---------------------------------------------------------


def _hold_lock(folder: str, entered, release, log: str) -> None:
    with store.index_lock(folder):
        entered.set()
        release.wait(60)
        with open(log, "a") as f:
            f.write("child-out\n")


def test_finishers_on_other_processes_take_the_index_lock_in_turn(tmp_path):
    ctx = mp.get_context("spawn")
    entered, release = ctx.Event(), ctx.Event()
    log = tmp_path / "order.txt"
    child = ctx.Process(target=_hold_lock, args=(str(tmp_path), entered, release, str(log)))
    child.start()
    try:
        assert entered.wait(60)

        def parent():
            with store.index_lock(tmp_path):
                with open(log, "a") as f:
                    f.write("parent-in\n")

        waiter = threading.Thread(target=parent)
        waiter.start()
        release.set()  # the child writes its line and only then lets go
        waiter.join(60)
    finally:
        child.join(60)
    assert log.read_text().split() == ["child-out", "parent-in"] and child.exitcode == 0


def test_a_finisher_that_waited_for_the_lock_does_not_write_the_index_again(tiny_dexycb, tmp_path, monkeypatch):
    out = tmp_path / "store"
    _build(tiny_dexycb, out, part=(0, 2))
    summary = _build(tiny_dexycb, out, part=(1, 2))
    assert summary.finished
    index = store.read_index(out)
    calls = []
    real_read = store.read_index

    def stale_then_current(path):  # the first look (before the lock) sees no index: another process writes it
        calls.append(path)
        if len(calls) == 1:
            raise DataError(path, None, "missing")
        return real_read(path)

    monkeypatch.setattr(store, "read_index", stale_then_current)
    monkeypatch.setattr(finish, "write_store_index", lambda *a, **k: pytest.fail("index written twice"))
    numbers = [s.number for s in index.shards]
    finish.finish_store(out, {}, tiny_dexycb / "models", numbers, [], type("S", (), {})())
    assert len(calls) == 2


def test_a_shard_damaged_after_it_was_written_stops_the_finisher(tiny_dexycb, tmp_path):
    out = tmp_path / "store"
    _build(tiny_dexycb, out, part=(0, 2))
    shard = out / "shard-000000.tar"
    data = bytearray(shard.read_bytes())
    data[600] ^= 1  # same size: only the bytes tell (the cheap check of the other parts passes)
    shard.write_bytes(bytes(data))
    with pytest.raises(DataError, match="shard-000000.tar.*rerun the build"):
        _build(tiny_dexycb, out, part=(1, 2))
    assert not (out / "index.zarr").exists()
    assert _build(tiny_dexycb, out).finished  # the rerun rewrites it


# --- the sbatch templates ----------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]


def test_the_sbatch_build_template_runs_one_part_per_array_task(tiny_dexycb, local_build, tmp_path):
    import os
    import subprocess
    import sys

    out = tmp_path / "store"
    for index in (1, 0):
        env = {**os.environ, "SLURM_ARRAY_TASK_ID": str(index), "HOIDATA_PARTS": "2", "SLURM_CPUS_PER_TASK": "1",
               "HOIDATA": f"{sys.executable} -m hoidata.cli", "PYTHONPATH": str(ROOT)}
        result = subprocess.run(["bash", str(ROOT / "scripts" / "sbatch_build.sh"), *_build_args(tiny_dexycb, out)],
                                capture_output=True, text=True, env=env, timeout=300, check=False)
        assert result.returncode == 0, result.stderr[-2000:]
        assert f"part {index} of 2" in result.stdout and ("index.zarr written" in result.stdout) == (index == 0)
    _same_store(local_build, out)


def test_the_sbatch_train_template_starts_torchrun_on_every_node_with_the_slurm_rendezvous(tmp_path):
    import os
    import subprocess

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "scontrol").write_text('#!/bin/sh\n[ "$1 $2" = "show hostnames" ] && printf "gpu-07\\ngpu-08\\n"\n')
    (bin_dir / "srun").write_text(f'#!/bin/sh\nprintf "%s\\n" "$@" > {tmp_path / "srun.txt"}\n')
    for tool in bin_dir.iterdir():
        tool.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "SLURM_JOB_NODELIST": "gpu-[07-08]",
           "SLURM_NNODES": "2", "SLURM_JOB_ID": "4242"}
    result = subprocess.run(["bash", str(ROOT / "scripts" / "sbatch_train.sh"), "--shards", "https://h/s", "--resume"],
                            capture_output=True, text=True, env=env, timeout=60, check=False)
    assert result.returncode == 0, result.stderr
    args = (tmp_path / "srun.txt").read_text().split("\n")[:-1]
    torchrun = args[args.index("torchrun"):]
    flags = dict(zip(torchrun[1:-5:2], torchrun[2:-5:2]))
    assert flags == {"--nnodes": "2", "--nproc_per_node": "8", "--rdzv_id": "4242", "--rdzv_backend": "c10d",
                     "--rdzv_endpoint": "gpu-07:29500"}
    assert torchrun[-5:] == ["-m", "hoisdf.train", "--shards", "https://h/s", "--resume"]
