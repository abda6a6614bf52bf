"""Issue 44, part 4: a run killed after its last checkpoint and resumed leaves a run folder equal to an uninterrupted
run's, file by file: every file a run appends to per step (metrics.csv, the keys files, TensorBoard's events) is cut
back to the checkpoint on ``--resume`` (docs/reliability.md, section 22).

The walk is over the run folder itself: whatever files the two runs hold are listed and compared, so a new file a
run appends to that resume does not trim fails here. A tiny model on a synthetic store keeps it in the fast tier.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_store import build_store

from hoisdf.train import main as train
from hoisdf.training.trainer import Trainer

TINY = ["model.depth=18", "model.image_size=32", "model.d_model=48", "model.ff=64", "model.hand_layers=1",
        "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=16", "model.sdf_hidden=64",
        "model.token_hidden=[16]", "model.hand_queries=16", "model.object_queries=8", "model.grid_resolution=8",
        "model.chunk=2048", "train.batch_size=2", "train.workers=0", "train.lr=1e-3", "train.log_every=1",
        "train.shuffle_buffer=4", "train.val_every=0", "train.record_keys=true", "train.epochs=2", "train.seed=3"]
TIMING = {"samples_per_s"}  # logged numbers that measure the machine, not the training


class Killed(BaseException):
    """Stands for SIGKILL: nothing catches it, nothing after it is written (every log write is whole and flushed)."""


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    out = tmp_path_factory.mktemp("resume_store") / "store"
    build_store(out, n=4, per_shard=2)  # 4 records: 2 batches of 2 per epoch
    return out


def _args(store, mano_dir, out, *extra):
    return ["--shards", str(store), "--mano", str(mano_dir), "--out", str(out), "--no-progress", "--device", "cpu",
            *TINY, *extra]


def _killed_at(monkeypatch, step: int):
    """Trainer.log raising Killed once the step ``step``'s training row is written (keys and rows past the last
    checkpoint are on disk)."""
    real = Trainer.log

    def log(self, split, values):
        real(self, split, values)
        if split == "train" and self.progress.global_step >= step:
            raise Killed

    monkeypatch.setattr(Trainer, "log", log)


def _scalars(folder: Path) -> dict:
    """{tag: [(step, value)]} as TensorBoard reads a run's event files (the purge a resumed writer records
    applied), timing tags left out."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(folder))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]
            if tag.rsplit("/", 1)[-1] not in TIMING}


def _same_value(a, b, where: str) -> None:
    if torch.is_tensor(a):
        assert torch.is_tensor(b) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            _same_value(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same_value(x, y, f"{where}[{i}]")
    else:
        assert a == b or (a != a and b != b), (where, a, b)


def _rows(path: Path) -> list:
    rows = list(csv.reader(io.StringIO(path.read_text())))
    return [r if r[3:4] and r[3] not in TIMING else r[:4] for r in rows]


def _config(path: Path) -> dict:
    """config.json with the run folder given to ``--out`` left out (the two runs write to two folders)."""
    info = json.loads(path.read_text())
    argv = info.get("argv", [])
    info["argv"] = [v for i, v in enumerate(argv) if not (i and argv[i - 1] == "--out")]
    return info


def compare_runs(a: Path, b: Path) -> list[str]:
    """Every file of run folder ``b`` against ``a``'s, by what it holds (checkpoints by value, metrics.csv by
    its rows, TensorBoard by the scalars its reader shows, config.json but for the run folder's own name, any
    other file byte for byte); returns the names compared. Fails on a file one of them lacks."""
    def files(root):
        return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and p.parent.name != "tb"}

    assert files(a) == files(b), (sorted(files(a)), sorted(files(b)))
    assert (a / "tb").is_dir() == (b / "tb").is_dir()
    compared = []
    for name in sorted(files(a)):
        pa, pb = a / name, b / name
        if name.endswith(".pt"):
            _same_value(torch.load(pa, weights_only=True), torch.load(pb, weights_only=True), name)
        elif name == "metrics.csv":
            assert _rows(pa) == _rows(pb), name
        elif name == "config.json":
            assert _config(pa) == _config(pb), name
        else:
            assert pa.read_bytes() == pb.read_bytes(), name
        compared.append(name)
    if (a / "tb").is_dir():
        assert _scalars(a / "tb") == _scalars(b / "tb"), "tb"
        compared.append("tb")
    return compared


@pytest.fixture(scope="module")
def runs(store, mano_dir, tmp_path_factory):
    """(an uninterrupted run, the same run killed at step 3 and resumed): 2 epochs of 2 batches of 2."""
    base = tmp_path_factory.mktemp("resume_runs")
    whole, cut = base / "whole", base / "cut"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a tiny model: one thread is faster, and kinder to the other test process
    try:
        _run_both(store, mano_dir, whole, cut)
    finally:
        torch.set_num_threads(threads)
    return whole, cut


def _run_both(store, mano_dir, whole, cut) -> None:
    assert train(_args(store, mano_dir, whole)) == 0
    with pytest.MonkeyPatch.context() as m:
        _killed_at(m, 3)  # epoch 1, step 1: the last checkpoint is epoch 0's end (step 2)
        with pytest.raises(Killed):
            train(_args(store, mano_dir, cut))
    assert len((cut / "keys-rank0.txt").read_text().splitlines()) == 6  # 3 steps of 2 keys on disk, 2 checkpointed
    assert train(_args(store, mano_dir, cut, "--resume")) == 0


def test_a_killed_and_resumed_run_folder_equals_an_uninterrupted_one(runs):
    compared = compare_runs(*runs)
    assert {"keys-rank0.txt", "metrics.csv", "tb", "checkpoints/last.pt", "config.json"} <= set(compared), compared


def test_the_comparison_sees_an_untrimmed_log(runs, tmp_path):
    """The walk fails where one log holds rows the other does not (the defect: keys logged before a kill kept),
    and on a file only one run holds."""
    import shutil

    a, b = runs[0], tmp_path / "b"
    shutil.copytree(runs[1], b)
    with open(b / "keys-rank0.txt", "a") as f:
        f.write("toy-train-f0001\n")
    with pytest.raises(AssertionError, match="keys-rank0.txt"):
        compare_runs(a, b)
    (b / "keys-rank0.txt").write_bytes((a / "keys-rank0.txt").read_bytes())
    (b / "extra.log").write_text("appended by something new\n")
    with pytest.raises(AssertionError, match="extra.log"):
        compare_runs(a, b)


def test_a_checkpoint_of_an_older_version_trims_the_keys_by_steps(tmp_path):
    """A checkpoint without ``keys_bytes``: the keys file keeps global_step x batch_size lines."""
    from hoisdf.training.trainer import trim_keys

    path = tmp_path / "keys-rank0.txt"
    path.write_text("".join(f"k{i}\n" for i in range(10)))
    assert trim_keys(path, None, 6) == len("".join(f"k{i}\n" for i in range(6)))
    assert path.read_text().splitlines() == [f"k{i}" for i in range(6)]
    assert trim_keys(path, 9, 0) == 9 and path.read_text() == "k0\nk1\nk2\n"
    assert trim_keys(path, 100, 0) == 9 and trim_keys(tmp_path / "none.txt", 5, 5) == 0
    np.testing.assert_equal(path.read_text(), "k0\nk1\nk2\n")
