"""The hoidata command line: make-toy end to end, checks, and errors on bad input."""

from __future__ import annotations

import pathlib
import re

import pytest

from hoidata.cli import main


@pytest.mark.slow
def test_make_toy_writes_and_checks_everything(tmp_path, capsys):
    argv = ["make-toy", "--out", str(tmp_path / "toy"), "--layout", "ho3d", "--sequences", "1", "--frames", "2",
            "--cache-dir", str(tmp_path / "cache")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert re.search(r"ho3d\s+train\s+2\s+0", out) and re.search(r"ho3d\s+evaluation\s+2\s+0", out)
    assert (tmp_path / "toy/train.txt").read_text().splitlines() == ["BB10/0000", "BB10/0001"]
    assert (tmp_path / "toy/mano/MANO_RIGHT.pkl").is_file() and (tmp_path / "toy/mano/MANO_LEFT.pkl").is_file()
    objects = sorted(p.name for p in (tmp_path / "toy/models").iterdir())
    assert {"002_master_chef_can", "003_cracker_box", "006_mustard_bottle", "011_banana", "025_mug"} <= set(objects)
    assert re.search(r"left vs mirrored right\s+ok", out)
    for name in objects:
        assert re.search(rf"{name}\s+\d+\s+\d+\s+\S+\s+True", out), name  # watertight after repair
    assert main(["check-mano", str(tmp_path / "toy/mano")]) == 0


def test_check_mano_reports_missing_and_broken_files(tmp_path, capsys):
    assert main(["check-mano", str(tmp_path)]) == 1
    assert "missing" in capsys.readouterr().out
    (tmp_path / "MANO_RIGHT.pkl").write_bytes(b"\x80\x02}q\x00(X")
    assert main(["check-mano", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "MANO_RIGHT.pkl" in err and "truncated or corrupt" in err


def test_help_lists_subcommands(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for cmd in ("make-toy", "check-mano", "check-objects"):
        assert cmd in out


def test_hoidata_never_imports_hoisdf():
    root = pathlib.Path(__file__).resolve().parents[1] / "hoidata"
    offenders = [p for p in root.rglob("*.py") if re.search(r"^\s*(from|import)\s+hoisdf", p.read_text(), re.MULTILINE)]
    assert offenders == []
