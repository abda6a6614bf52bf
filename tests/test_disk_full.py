"""Real OS errors name the file (issue 25, item 6), on a REALLY full filesystem: a 1 MiB tmpfs filled to the last
page, not a mocked error. The errno of write()/flush()/fsync()/close() carries no file name; every writer attaches
the path it writes (hoidata.errors.naming_os_errors), so each command prints ``error: <path>: No space left on
device``. Needs root to mount (skipped with the reason otherwise)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

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
    from hoisdf.evaluation.official import write_scores_txt
    from hoisdf.evaluation.outputs import write_per_object
    from hoisdf.evaluation.submissions import write_dexycb_hpe, write_ho3d_pred

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
    from hoisdf.evaluation.official import HO3D_SCORES

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
