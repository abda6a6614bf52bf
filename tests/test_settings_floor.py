"""Settings on the ground floor (:mod:`hoidata.sections`): one pipeline file, two readers that each check their own
sections, the build knowing none of training's; and ``python -m hoisdf.toy`` running the data steps as the
``hoidata`` command in a child process instead of importing it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hoidata.errors import DataError
from hoidata.records import settings as build
from hoidata.sections import check_sections, refuse_unused
from hoisdf import config as training

ROOT = Path(__file__).resolve().parents[1]


def test_each_reader_names_its_sections_and_training_knows_the_builds():
    assert build.BUILD_SECTIONS == ("dataset", "record", "store")
    assert training.TRAIN_SECTIONS == ("model", "train", "augment", "loss")
    assert training.BUILD_SECTIONS == build.BUILD_SECTIONS  # the copy training keeps, to stay off the build
    assert not hasattr(build, "TRAIN_SECTIONS")


@pytest.mark.parametrize("name", sorted(p.stem for p in (ROOT / "pipelines").glob("*.toml")))
def test_every_shipped_pipeline_loads_for_both_readers(name):
    assert build.load_build_config(name).dataset.name in ("dexycb", "ho3d", "hot3d_clips")
    assert training.load_train_config(name).model.depth in (18, 34, 50)


def _toml(tmp_path, text: str) -> str:
    path = tmp_path / "p.toml"
    path.write_text(text)
    return str(path)


def test_a_misspelt_build_section_is_an_error_for_the_build_and_an_unknown_one_for_training(tmp_path):
    path = _toml(tmp_path, "[recrod]\nn_hand = 8\n")
    with pytest.raises(DataError, match=r"p\.toml: 'recrod': unknown section; did you mean \[record\]\?"):
        build.load_build_config(path)
    with pytest.raises(DataError, match=r"p\.toml: 'recrod': unknown section; expected one of \[model\], "
                                        r"\[train\], \[augment\], \[loss\], \[dataset\], \[record\], \[store\]"):
        training.load_train_config(path)


def test_the_build_leaves_other_readers_sections_to_them_and_training_refuses_a_section_nobody_reads(tmp_path):
    path = _toml(tmp_path, "[model]\ndepth = 18\n[optimizer]\nlr = 0.1\n")
    assert build.load_build_config(path).record.sdf_samples_hand > 0  # [model] is training's, [optimizer] no build section
    with pytest.raises(DataError, match=r"'optimizer': unknown section"):
        training.load_train_config(path)
    with pytest.raises(DataError, match=r"'depth': expected a \[section\] table of settings, got 18"):
        build.load_build_config(_toml(tmp_path, "depth = 18\n"))


@pytest.mark.parametrize("overrides,command,needle", [
    (["model.depth=18"], "build", (r"'model\.depth': build-sdf does not use \[model\] settings \(it reads "
                                   r"\[dataset\], \[record\], \[store\]\)")),
    (["recrod.n_hand=8"], "build", r"'recrod\.n_hand': build-sdf does not use \[recrod\] settings"),
    (["record.sdf_samples_hand=8"], "train", (r"'record\.sdf_samples_hand': training does not use \[record\] "
                                              r"settings \(hoidata build-sdf reads them\)")),
    (["optimizer.lr=1"], "train", (r"'optimizer\.lr': training does not use \[optimizer\] settings \(it reads "
                                   r"\[model\], \[train\], \[augment\], \[loss\]\)")),
])
def test_an_override_of_a_section_the_command_does_not_read_names_the_key(overrides, command, needle):
    load = build.load_build_config if command == "build" else training.load_train_config
    with pytest.raises(DataError, match=needle):
        load("toy", overrides)


def test_the_section_checks_name_no_section_themselves(tmp_path):
    """hoidata.sections knows sections only from its callers: the same table passes or fails by what they say."""
    data, path = {"a": {}, "b": {}}, tmp_path / "x.toml"
    check_sections(data, path, ("a", "b"), None)
    check_sections(data, path, ("a",), ("b",))
    check_sections(data, path, ("a",), None)  # 'b' is not like 'a': another reader's
    with pytest.raises(DataError, match="'b': unknown section; expected one of \\[a\\]"):
        check_sections(data, path, ("a",), ())
    refuse_unused(["a.k=1"], ("a",), "cmd", path)
    with pytest.raises(DataError, match=r"'b\.k': cmd does not use \[b\] settings \(other reads them\)"):
        refuse_unused(["b.k=1"], ("a",), "cmd", path, {"b": "other"})


def test_a_saved_config_with_overrides_is_checked_and_left_unchanged(tmp_path):
    saved = training.TrainConfig().as_dict()
    config = training.overridden_config(saved, ["train.max_steps=3", "model.depth=18"], tmp_path / "last.pt")
    assert (config.train.max_steps, config.model.depth) == (3, 18)
    assert saved["train"]["max_steps"] == 0 and saved["model"]["depth"] == 50
    with pytest.raises(DataError, match=r"last\.pt: 'record\.sdf_samples_hand': training does not use \[record\]"):
        training.overridden_config(saved, ["record.sdf_samples_hand=8"], tmp_path / "last.pt")


def test_git_commit_is_one_function_the_build_and_training_share():
    from hoidata.records import store_writer as finish
    from hoidata.provenance import git_commit

    assert finish.git_commit is git_commit
    assert subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=False).stdout.strip() in (git_commit(), "")


def test_hoidata_runs_as_a_module(tmp_path):
    """``python -m hoidata`` is the hoidata command; its error is its one line and exit 2."""
    done = subprocess.run([sys.executable, "-m", "hoidata", "make-toy", "--out", str(tmp_path), "--frames", "0"],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines()[-1].startswith("hoidata make-toy: error: argument --frames")


def test_the_main_job_runs_the_data_steps_as_the_hoidata_command():
    from hoisdf.toy import data_command

    argv = data_command(Path("run"), 3, 7, 10, None, debug=True)
    assert argv == [sys.executable, "-m", "hoidata", "toy-pipeline", "--out", "run", "--workers", "3", "--seed", "7",
                    "--sequences", "10", "--debug"]


def test_a_failing_data_step_of_the_main_job_is_its_one_line_and_stops_the_job(tmp_path, capfd, monkeypatch):
    """The child's own error line is the only one (exit 2), and nothing is trained or evaluated after it."""
    import hoisdf.toy

    out = tmp_path / "run"
    failing = [sys.executable, "-m", "hoidata", "make-toy", "--out", str(out / "data"), "--frames", "0"]
    monkeypatch.setattr(hoisdf.toy, "data_command", lambda *args: failing)  # fails as fast as argparse does
    assert hoisdf.toy.main(["--out", str(out), "--steps", "1"]) == 2
    captured = capfd.readouterr()
    assert captured.out.startswith("$ python -m hoidata make-toy --out ")
    errors = [line for line in captured.err.splitlines() if "error" in line]
    assert len(errors) == 1 and errors[0].startswith("hoidata make-toy: error: argument --frames"), errors
    assert not out.exists()


def test_a_data_step_killed_by_a_signal_is_one_line(capfd):
    from hoisdf.toy import run_data

    code = run_data([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"])
    assert code == 128 + 9
    assert capfd.readouterr().err.strip().endswith("was stopped by SIGKILL")
