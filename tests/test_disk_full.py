"""Real OS errors name the file (issue 25, item 6), on a REALLY full filesystem: a 1 MiB tmpfs filled to the last
page, not a mocked error. The errno of write()/flush()/fsync()/close() carries no file name; every writer attaches
the path it writes (hoidata.errors.naming_os_errors), so each command prints ``error: <path>: No space left on
device``. Needs root to mount (skipped with the reason otherwise).

Training (issue 30, item 4): the checkpoint, metrics.csv and the TensorBoard events fail the same way, on a full
tmpfs and under a file size limit (RLIMIT_FSIZE in a child process: "File too large"), and the run resumes exactly
from its last good checkpoint."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from test_faults_train import _args

from hoidata.errors import user_message

pytestmark = pytest.mark.slow  # every writer run against a full filesystem, on a built store

NOSPACE = "No space left on device"


@pytest.fixture
def full(tmp_path):
    """A mounted 1 MiB tmpfs with every page taken by a filler file (so any new data fails with ENOSPC)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a tmpfs needs root (mount -t tmpfs)")
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        pytest.skip(f"mount -t tmpfs not permitted here: {proc.stderr.strip()}")
    try:
        fd = os.open(mnt / "filler", os.O_WRONLY | os.O_CREAT)
        try:
            while True:
                os.write(fd, bytes(4096))
        except OSError as err:
            assert err.errno == 28
        finally:
            os.close(fd)
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _names(path: Path, call) -> None:
    with pytest.raises(OSError) as info:
        call()
    assert user_message(info.value) == f"{path}: {NOSPACE}"


def test_every_writer_names_its_file(full, tiny_store, mano_dir, tmp_path):
    from hoidata.atomic import write_atomic, write_json_atomic
    from hoidata.export import files
    from hoidata.store import read_index
    from hoidata.store.index import write_index
    from hoidata.store.inspect import inspect_store
    from hoidata.store.shards import write_shard
    from hoisdf.scoring.official import write_scores_txt
    from hoisdf.evaluation.outputs import write_per_object
    from hoisdf.scoring.submissions import write_dexycb_hpe, write_ho3d_pred

    _names(full / "a.bin", lambda: write_atomic(full / "a.bin", bytes(9000)))
    _names(full / "b.json", lambda: write_json_atomic(full / "b.json", {"x": list(range(3000))}))
    _names(full / "s" / "shard-000000.tar", lambda: write_shard(full / "s", 0, []))  # the tar's end blocks
    idx = read_index(tiny_store)
    labels = {"key": np.asarray(idx.keys), **{k: v for k, v in idx.labels.items() if k not in ("key", "shard")}}
    _names(full / "s" / "index.zarr", lambda: write_index(full / "s", idx.shards, labels, idx.objects, idx.skipped,
                                                          idx.config, idx.provenance))
    assert not [p for p in (full / "s").iterdir() if "index" in p.name]  # the failed index left nothing
    _names(full / "e.json", lambda: files.write_json(full / "e.json", list(range(3000))))
    _names(full / "e.npz", lambda: files.write_npz(full / "e.npz", {"a": np.zeros(3000)}))
    _names(full / "e.obj", lambda: files.write_obj(full / "e.obj", np.zeros((900, 3)), np.zeros((300, 3), int)))
    _names(full / "c.json", lambda: files.write_coco(full / "c.json", lambda: [{"split": "t", "image": {"id": 1},
                                                                              "annotation": {"a": [0] * 3000}}], "t"))
    joints, verts = np.full((3, 21, 3), -0.5), np.full((3, 778, 3), -0.5)
    _names(full / "pred.zip", lambda: write_ho3d_pred(full / "pred.zip", ["A/1", "A/2", "A/3"], joints * -1, verts))
    _names(full / "h.txt", lambda: write_dexycb_hpe(full / "h.txt", [0, 1, 2], joints))
    scores = dict.fromkeys(json.loads(json.dumps(["xyz_mean3d"])), 1.0)
    from hoisdf.scoring.official import HO3D_SCORES

    _names(full / "scores.txt", lambda: write_scores_txt(full / "scores.txt", {**scores, **dict.fromkeys(HO3D_SCORES, 1.0)}))
    summary = {"all": {f"m{i}": 1.0 for i in range(400)}}
    _names(full / "per_object.csv", lambda: write_per_object(full / "per_object.csv", summary, {"x": 1}))
    _names(full / "grid.png", lambda: inspect_store(tiny_store, n=4, out=full / "grid.png"))
    assert sorted(p.name for p in full.iterdir()) == ["filler", "s"]  # no temporary file left behind


def _cli(capsys, main, argv) -> str:
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    return err


def test_each_command_prints_the_file_on_a_full_disk(full, tiny_dexycb, tiny_store, untrained_run, mano_dir, capsys):
    """build-sdf, export, evaluate and inspect, with their output on the full disk: one line, the path, the reason."""
    from hoidata.cli import main as hoidata
    from hoisdf.evaluate import main as evaluate

    def check(err, command):
        assert err.endswith(f": {NOSPACE}") and f"error: {full}/" in err, (command, err)

    splits = 'dataset.splits=["train"]'
    check(_cli(capsys, hoidata, ["build-sdf", "--dataset", "toy", "--root", str(tiny_dexycb), "--out",
                                 str(full / "store"), "--workers", "1", splits]), "build-sdf")
    check(_cli(capsys, hoidata, ["export", "--format", "gsdf", "--dataset", "toy", "--root", str(tiny_dexycb),
                                 "--out", str(full / "export"), "--workers", "1", "--splits", "train"]), "export")
    check(_cli(capsys, evaluate, ["--ckpt", str(untrained_run), "--shards", str(tiny_store), "--mano", str(mano_dir),
                                  "--out", str(full / "eval"), "--plausibility", "0", "--workers", "0", "--limit", "2",
                                  "--no-progress"]), "evaluate")
    check(_cli(capsys, hoidata, ["inspect", str(tiny_store), "--out", str(full / "grid.png")]), "inspect")


# --- training on a full disk (issue 30, item 4): every file the trainer writes fails the same clean way ------------

def _sha(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()  # the file's bytes are the contract: it must stay untouched


def _train_limited(argv: list[str], limit: int) -> subprocess.CompletedProcess:
    """``python -m hoisdf.train ARGV`` in a child whose files may not grow past ``limit`` bytes (RLIMIT_FSIZE: a write
    past it fails with EFBIG, "File too large", as Python ignores SIGXFSZ)."""
    import resource
    import sys

    def cap():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "hoisdf.train", *argv], capture_output=True, text=True, timeout=300,
                          env=env, preexec_fn=cap, check=False)


def _whole_rows(run: Path) -> list[list[str]]:
    rows = [line.split(",") for line in (run / "metrics.csv").read_text().splitlines()]
    assert rows[0] == ["split", "epoch", "step", "name", "value"] and all(len(r) == 5 for r in rows), rows
    float(rows[-1][4])  # the last row is whole
    return rows[1:]


def test_a_checkpoint_that_does_not_fit_is_one_line_and_the_run_resumes_exactly(tiny_store, mano_dir, tmp_path):
    """--resume to step 4 under a 1 MiB file size limit: the step-4 checkpoint cannot be written. One line naming it,
    exit 2, the step-2 checkpoint untouched and no temporary file; the logs hold whole rows; a --resume with room
    continues from step 2 and ends bit for bit where an uninterrupted 4-step run ends."""
    from hoisdf.train import main as train

    assert train(_args(tiny_store, mano_dir, tmp_path / "four", "train.max_steps=4")) == 0
    run = tmp_path / "run"
    assert train(_args(tiny_store, mano_dir, run, "train.max_steps=2")) == 0
    last = run / "checkpoints" / "last.pt"
    before = _sha(last)
    result = _train_limited(["--resume", *_args(tiny_store, mano_dir, run, "train.max_steps=4")], 1 << 20)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert lines == [f"error: {last}: File too large"]  # was: torch's RuntimeError from its zip writer
    assert _sha(last) == before and [p.name for p in last.parent.iterdir()] == ["last.pt"]
    assert {int(r[2]) for r in _whole_rows(run)} == {1, 2, 3, 4}  # steps 3 and 4 were logged before the save failed
    assert train(["--resume", *_args(tiny_store, mano_dir, run, "train.max_steps=4")]) == 0
    assert sorted({int(r[2]) for r in _whole_rows(run)}) == [1, 2, 3, 4] and len(_whole_rows(run)) == len(
        _whole_rows(tmp_path / "four"))  # the rows after step 2 were dropped and logged again, once
    a, b = (torch.load(path / "checkpoints" / "last.pt", weights_only=True) for path in (tmp_path / "four", run))
    assert a["progress"] == b["progress"] and a["progress"]["global_step"] == 4
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    for k, state in a["optimizer"]["state"].items():
        assert all(torch.equal(v, b["optimizer"]["state"][k][n]) for n, v in state.items() if torch.is_tensor(v))


def test_a_training_run_on_a_full_disk_names_the_checkpoint(full, tiny_store, mano_dir, capsys):
    """A real ENOSPC: the run folder on a tmpfs with 64 KiB free (room for config.json and the logs, not for a
    checkpoint). One line naming last.pt and "No space left on device", and the logs stay readable."""
    from hoisdf.train import main as train

    os.truncate(full / "filler", os.path.getsize(full / "filler") - (64 << 10))
    run = full / "run"
    err = _cli(capsys, train, _args(tiny_store, mano_dir, run, "train.max_steps=2"))
    assert err == f"error: {run}/checkpoints/last.pt: {NOSPACE}"
    assert not any((run / "checkpoints").iterdir())  # no temporary file stays
    assert json.loads((run / "config.json").read_text())["config"]["train"]["max_steps"] == 2
    assert {int(r[2]) for r in _whole_rows(run)} == {1, 2}


def test_logs_that_cannot_grow_are_one_line_naming_them(tiny_store, mano_dir, tmp_path):
    """Under a 4 KiB file size limit config.json (3.4 KB) fits and the TensorBoard events (about 0.9 KB a step) stop
    growing first: one line naming RUN/tb, without the event writer thread's own traceback, and metrics.csv holds
    whole rows."""

    run = tmp_path / "run"
    result = _train_limited(_args(tiny_store, mano_dir, run, "train.max_steps=8"), 4096)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert lines == [f"error: {run / 'tb'}: File too large"]
    _whole_rows(run)


def test_a_log_append_is_whole_or_not_at_all(full):
    """append_whole on a real full disk: a row that does not fit is cut back off, and the error names the file."""
    from hoidata.atomic import append_whole

    os.truncate(full / "filler", os.path.getsize(full / "filler") - 4096)  # one page free
    log = full / "metrics.csv"
    append_whole(log, b"a,b\n" * 500)
    _names(log, lambda: append_whole(log, b"c,d\n" * 2000))  # 8000 bytes: about 2 KB of it would fit
    assert log.read_bytes() == b"a,b\n" * 500
