"""The project's promises about bad inputs and faults, training and evaluation side (docs/reliability.md); the
data side is test_faults_build.py. One test per class of fault, named after the promise it checks.

Promises here: no training is lost to validation; exact resume under DDP (2 processes, gloo); logs drop what
was logged after the checkpoint a run resumes from, and never append to a dead run; one clear line for every
user error in every CLI (numbers, settings, unused overrides, loader-worker errors, OS errors, corrupt
checkpoints); result files readable by others.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hoidata.cli import main as hoidata
from hoidata.errors import DataError
from hoisdf.evaluate import main as evaluate
from hoisdf.toy import main as toy
from hoisdf.train import main as train

pytestmark = pytest.mark.slow  # each fault is a training or evaluation run on a built store

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=2",
        "model.decoder_layers=2", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16",
        "model.chunk=2048", "train.batch_size=2", "train.workers=0", "train.lr=1e-3", "train.log_every=1",
        "train.shuffle_buffer=4", "train.val_every=0"]


def _args(store, mano_dir, out, *extra):
    return ["--shards", str(store), "--mano", str(mano_dir), "--out", str(out), "--no-progress", "--device", "cpu",
            *TINY, *extra]


@pytest.fixture(scope="module")
def run_dir(tiny_store, mano_dir, tmp_path_factory):
    """A 2-step training run of the tiny model (its checkpoint is the source of the damaged ones)."""
    out = tmp_path_factory.mktemp("faults_run") / "run"
    assert train(_args(tiny_store, mano_dir, out, "train.max_steps=2")) == 0
    return out


def _one_error_line(capsys, rc, *needles):
    """rc is 2 and stderr's last line is the one error line holding every needle, without a traceback."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2 and lines and "Traceback" not in err, err[-3000:]
    assert "error" in lines[-1] and all(n in lines[-1] for n in needles), err[-3000:]
    return lines[-1]


def _call(fn, argv):
    try:
        return fn(argv)
    except SystemExit as exc:  # argparse's own "usage ... error:" exit
        return exc.code


def _damage_sdf(store: Path, tmp_path: Path) -> Path:
    """A copy of the store whose first record's sdf.npy has the wrong shape, index re-hashed to match."""
    import io

    from test_faults_build import _rewrite_shard

    out = tmp_path / "bad-store"
    shutil.copytree(store, out)
    buf = io.BytesIO()
    np.save(buf, np.zeros((10, 5), np.int16))
    _rewrite_shard(out / "shard-000000.tar",
                   lambda ms: [(n, buf.getvalue()) if n.endswith(".sdf.npy") and i < 5 else (n, d)
                               for i, (n, d) in enumerate(ms)])
    return out


# --- 2. no training lost to validation -----------------------------------------------------------------------


def test_validation_stores_are_checked_before_the_first_step(tiny_store, mano_dir, tmp_path, capsys):
    out = tmp_path / "run"
    rc = train(_args(tiny_store, mano_dir, out, "train.max_steps=4", "--val-shards", str(tmp_path / "typo")))
    _one_error_line(capsys, rc, "typo")
    assert not (out / "metrics.csv").exists()  # not a single step was trained before the error


def test_an_epoch_is_saved_before_its_validation_runs(tiny_store, mano_dir, tmp_path, capsys):
    val = tmp_path / "val"
    shutil.copytree(tiny_store, val)
    shard = val / "shard-000000.tar"
    shard.write_bytes(bytes(shard.stat().st_size))  # found only when validation reads it
    out = tmp_path / "run"
    rc = train(_args(tiny_store, mano_dir, out, "train.epoch_samples=4", "train.epochs=2", "train.val_every=1",
                     "--val-shards", str(val)))
    _one_error_line(capsys, rc, "shard-000000.tar")
    assert (out / "checkpoints" / "epoch-000.pt").is_file()
    assert train(["--resume", *_args(tiny_store, mano_dir, out, "train.val_every=0")]) == 0  # nothing lost


# --- 4. exact resume under DDP, logs that match the checkpoint ------------------------------------------------


def test_ddp_resume_is_exact(tiny_store_two_shards, mano_dir, tmp_path):
    """torchrun 2 processes (gloo): 2 steps + --resume 2 steps == 4 steps, bit for bit, weights and optimizer."""
    def torchrun(out, *extra, resume=False):
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--standalone",
               "-m", "hoisdf.train", *(["--resume"] if resume else []),
               *_args(tiny_store_two_shards, mano_dir, out, "train.epoch_samples=12", "train.point_sampling_epoch=0",
                      "train.field_prob=0.5", *extra)]
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        result = subprocess.run(cmd, capture_output=True, text=True, timeout=400, env=env, check=False)
        assert result.returncode == 0, result.stderr[-3000:]

    torchrun(tmp_path / "four", "train.max_steps=4")
    torchrun(tmp_path / "split", "train.max_steps=2")
    torchrun(tmp_path / "split", "train.max_steps=4", resume=True)
    a, b = (torch.load(tmp_path / run / "checkpoints" / "last.pt", weights_only=True) for run in ("four", "split"))
    assert a["progress"] == b["progress"] == {"epoch": 1, "step": 1, "global_step": 4}
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    for k, state in a["optimizer"]["state"].items():
        assert all(torch.equal(v, b["optimizer"]["state"][k][n]) for n, v in state.items() if torch.is_tensor(v))
    assert len(a["rng_ranks"]) == 2 and not torch.equal(a["rng_ranks"][0]["generator"], a["rng_ranks"][1]["generator"])


def _steps(run: Path) -> list[int]:
    rows = [line.split(",") for line in (run / "metrics.csv").read_text().splitlines()[1:]]
    return [int(r[2]) for r in rows if r[3] == "total"]


def test_logs_drop_rows_logged_after_the_checkpoint_they_resume_from(tiny_store, mano_dir, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "run"
    assert train(_args(tiny_store, mano_dir, out, "train.max_steps=2")) == 0
    kept = out / "step2.pt"
    shutil.copy(out / "checkpoints" / "last.pt", kept)
    assert train(["--resume", *_args(tiny_store, mano_dir, out, "train.max_steps=4")]) == 0
    shutil.copy(kept, out / "checkpoints" / "last.pt")  # killed after logging steps 3, 4 but before their checkpoint
    assert train(["--resume", *_args(tiny_store, mano_dir, out, "train.max_steps=4")]) == 0
    assert _steps(out) == [1, 2, 3, 4]
    events = EventAccumulator(str(out / "tb"))
    events.Reload()
    assert [e.step for e in events.Scalars("train/total")] == [1, 2, 3, 4]


def test_a_fresh_run_never_appends_to_a_dead_run(tiny_store, mano_dir, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "metrics.csv").write_text("split,epoch,step,name,value\ntrain,0,1,total,-777\ntrain,0,2,total,-778\n")
    (out / "config.json").write_text("{}")  # an earlier run that died before its first checkpoint
    assert train(_args(tiny_store, mano_dir, out, "train.max_steps=1")) == 0
    assert _steps(out) == [1] and "-777" not in (out / "metrics.csv").read_text()
    assert json.loads((out / "config.json").read_text())["config"]["train"]["max_steps"] == 1


# --- 7. one clear line for every user error -------------------------------------------------------------------


BUILD = ["build-sdf", "--dataset", "toy", "--root", "ROOT", "--out", "OUT"]
CASES = [
    (hoidata, [*BUILD, "--workers", "0"], "--workers"), (hoidata, [*BUILD, "--workers", "-3"], "--workers"),
    (hoidata, [*BUILD, "store.records_per_shard=0"], "records_per_shard"),
    (hoidata, [*BUILD, "store.records_per_shard=-1"], "records_per_shard"),
    (hoidata, [*BUILD, "record.crop_size=0"], "crop_size"), (hoidata, [*BUILD, "dataset.frame_stride=0"], "frame_stride"),
    (hoidata, [*BUILD, "dataset.frame_stride=-1"], "frame_stride"), (hoidata, [*BUILD, "record.cube=inf"], "cube"),
    (hoidata, [*BUILD, "model.depth=34"], "model.depth"),  # an override build-sdf does not use
    (hoidata, [*BUILD[:5], "dataset.frame_stride=1", "--out", "OUT", "record.cube=nan"], "cube"),  # both sides of --out
    (hoidata, ["render-synthetic", "--source", "ROOT", "--out", "OUT", "--count", "2", "--crop-size", "0"], "--crop-size"),
    (hoidata, ["render-synthetic", "--source", "ROOT", "--out", "OUT", "--count", "0"], "--count"),
    (hoidata, ["render-synthetic", "--source", "ROOT", "--out", "OUT", "--count", "2", "--records-per-shard", "0"],
     "--records-per-shard"),
    (hoidata, ["make-toy", "--out", "OUT", "--sequences", "0"], "--sequences"),
    (hoidata, ["make-toy", "--out", "OUT", "--frames", "0"], "--frames"),
    (hoidata, ["make-toy", "--out", "OUT", "--sequences", "-1"], "--sequences"),
    (hoidata, ["make-toy", "--out", "OUT", "--seed", "-1"], "--seed"),
    (hoidata, ["toy-pipeline", "--out", "OUT", "--sequences", "0"], "--sequences"),
    (hoidata, ["inspect", "OUT", "--n", "0"], "--n"),
    (train, ["TRAIN", "train.log_every=0"], "log_every"), (train, ["TRAIN", "train.max_steps=-1"], "max_steps"),
    (train, ["TRAIN", "train.epochs=0"], "epochs"), (train, ["TRAIN", "train.epoch_samples=-5"], "epoch_samples"),
    (train, ["TRAIN", "model.grid_resolution=0"], "grid_resolution"), (train, ["TRAIN", "train.lr=inf"], "lr"),
    (train, ["TRAIN", "record.sdf_samples_hand=100"], "record.sdf_samples_hand"),  # an override training does not use
    (train, ["TRAIN:0", "train.max_steps=1"], "weight"),
    (evaluate, ["EVAL", "--limit", "0"], "--limit"), (evaluate, ["EVAL", "--batch-size", "0"], "--batch-size"),
    (evaluate, ["EVAL", "--workers", "-1"], "--workers"),
    (toy, ["--out", "OUT", "--steps", "0"], "--steps"), (toy, ["--out", "OUT", "--seed", "-1"], "--seed"),
]


@pytest.mark.parametrize("fn,argv,needle", CASES, ids=[f"{fn.__module__}-{' '.join(a[-2:])}" for fn, a, _ in CASES])
def test_every_cli_gives_one_error_line_for_a_bad_number_or_setting(tiny_dexycb, tiny_store, mano_dir, tmp_path,
                                                                      capsys, fn, argv, needle):
    subs = {"ROOT": str(tiny_dexycb), "OUT": str(tmp_path / "out")}
    argv = [subs.get(a, a) for a in argv]
    if argv[0].startswith("TRAIN"):  # TRAIN: the tiny store; TRAIN:0: with weight 0
        argv = _args(str(tiny_store) + argv[0][len("TRAIN"):], mano_dir, tmp_path / "run", *argv[1:])
    if argv[0] == "EVAL":
        argv = ["--ckpt", str(tmp_path / "run"), "--shards", str(tiny_store), "--mano", str(mano_dir), *argv[1:]]
    _one_error_line(capsys, _call(fn, argv), needle)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.tar"))


@pytest.mark.parametrize("workers", [0, 2])
def test_a_data_error_in_a_loader_worker_is_one_line(tiny_store, mano_dir, run_dir, tmp_path, capsys, workers):
    bad = _damage_sdf(tiny_store, tmp_path)
    rc = train(_args(bad, mano_dir, tmp_path / "run", "train.max_steps=2", f"train.workers={workers}"))
    _one_error_line(capsys, rc, "shard-000000.tar", "sdf.npy")
    rc = evaluate(["--ckpt", str(run_dir), "--shards", str(bad), "--mano", str(mano_dir), "--out", str(tmp_path / "e"),
                   "--workers", str(workers), "--no-progress", "--plausibility", "0"])
    _one_error_line(capsys, rc, "shard-000000.tar", "sdf.npy")


def test_disk_full_and_read_only_errors_are_one_line(tiny_dexycb, tiny_store, mano_dir, tmp_path, capsys,
                                                      monkeypatch):
    import hoidata.store.shards as shards
    import hoisdf.training.checkpoint as checkpoint

    def full(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.tmp))

    monkeypatch.setattr(shards._OpenShard, "finish", full)
    rc = hoidata([*BUILD[:4], str(tiny_dexycb), "--out", str(tmp_path / "s"), 'dataset.splits=["train"]'])
    _one_error_line(capsys, rc, "shard-000000.tar", "No space left on device")

    def read_only(payload, file):  # torch.save writes through a file object: its write errors name no file
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(checkpoint.torch, "save", read_only)
    _one_error_line(capsys, train(_args(tiny_store, mano_dir, tmp_path / "run", "train.max_steps=1")),
                    "last.pt", "Read-only file system")
    with pytest.raises(OSError):  # --debug shows the traceback instead
        train([*_args(tiny_store, mano_dir, tmp_path / "run2", "train.max_steps=1"), "--debug"])


def _damaged(run_dir: Path, tmp_path: Path, name: str, edit) -> Path:
    out = tmp_path / name
    shutil.copytree(run_dir, out)
    path = out / "checkpoints" / "last.pt"
    payload = torch.load(path, weights_only=True)
    edit(payload)
    torch.save(payload, path)
    return out


DAMAGE = {
    "no-optimizer": (lambda p: p.pop("optimizer"), "optimizer"),
    "no-progress": (lambda p: p.pop("progress"), "progress"),
    "bad-rng": (lambda p: [s.update(torch=torch.zeros(3, dtype=torch.uint8)) for s in [p["rng"], *p.get("rng_ranks", [])]],
                "rng"),
    "huge-step": (lambda p: p["progress"].update(step=10 ** 9), "progress"),
    "step-past-the-epoch": (lambda p: p["progress"].update(step=50, global_step=50), "progress.step"),
    "negative-step": (lambda p: p["progress"].update(step=-3), "progress"),
    "bad-config": (lambda p: p["config"]["train"].update(seed="zero"), "train.seed"),
}


@pytest.mark.parametrize("name", sorted(DAMAGE))
def test_a_damaged_checkpoint_is_one_line_naming_file_and_field(tiny_store, mano_dir, run_dir, tmp_path, capsys, name):
    edit, field = DAMAGE[name]
    out = _damaged(run_dir, tmp_path, name, edit)
    _one_error_line(capsys, train(["--resume", *_args(tiny_store, mano_dir, out, "train.max_steps=100")]), "last.pt",
                    field)


def test_model_settings_cannot_change_on_resume(tiny_store, mano_dir, run_dir, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    rc = train(["--resume", *_args(tiny_store, mano_dir, out, "model.ff=64", "train.max_steps=3")])
    _one_error_line(capsys, rc, "last.pt", "model", "--resume")
    rc = train(_args(tiny_store, mano_dir, tmp_path / "new", "model.d_model=32"))  # settings that do not fit together
    _one_error_line(capsys, rc, "model.d_model")


# --- 8. files people can read ---------------------------------------------------------------------------------


def test_result_files_are_readable_by_others(run_dir, tiny_store, mano_dir, tmp_path):
    old = os.umask(0o022)
    try:
        out = tmp_path / "eval"
        assert evaluate(["--ckpt", str(run_dir), "--shards", str(tiny_store), "--mano", str(mano_dir), "--out", str(out),
                         "--vis", "1", "--workers", "0", "--no-progress", "--plausibility", "0", "--limit", "4"]) == 0
        from hoidata.store.inspect import inspect_store
        from hoisdf.scoring.submissions import write_ho3d_pred

        inspect_store(tiny_store, n=2, out=tmp_path / "grid.png")
        write_ho3d_pred(tmp_path / "pred.json", ["a/0"], np.zeros((1, 21, 3)), np.zeros((1, 778, 3)))
        files = [*out.rglob("*.*"), tmp_path / "grid.png", tmp_path / "pred.json", run_dir / "checkpoints" / "last.pt"]
        modes = {f.name: oct(f.stat().st_mode & 0o777) for f in files}
        assert files and set(modes.values()) == {"0o644"}, modes
    finally:
        os.umask(old)


def test_the_debug_flag_shows_the_traceback(tiny_dexycb, tmp_path):
    with pytest.raises(DataError, match="records_per_shard"):
        hoidata([*BUILD[:4], str(tiny_dexycb), "--out", str(tmp_path / "s"), "store.records_per_shard=0", "--debug"])
