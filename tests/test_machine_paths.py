"""No path of one machine in the repository (issue 35): a command in the docs that starts ``/work/venv/bin/python``
works only where it was written. Commands use the README's form (``.venv/bin/python -m bench.X``, relative
folders); a printed table keeps no temporary folder of the run that made it.

Flagged: absolute paths under a user's or a build machine's folders (``/work/``, ``/root/``, ``/home/``,
``/Users/``), pytest's ``/tmp/pytest-of-*`` and any folder inside ``/tmp`` (some run's temporary folder). A bare
``/tmp/name`` stays allowed (an example output path, a string a test masks).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# not preceded by a word, path or URL character: "https://host/work/x" and "a/home/b" are not machine paths
MACHINE_PATH = re.compile(r"(?<![\w.~/@:-])(/(?:work|root|home|Users)/|/tmp/pytest-of|/tmp/[\w.-]+/)")


def machine_paths(text: str) -> list[str]:
    return [m.group(1) for m in MACHINE_PATH.finditer(text)]


def tracked_text_files() -> list[Path]:
    try:
        names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: no list of tracked files")
    return [ROOT / n for n in names.decode().split("\0") if n]


def test_the_pattern_finds_machine_paths_and_leaves_other_paths():
    found = machine_paths("run /work/venv/bin/python; see /root/.cache/x, /home/ann/data and /Users/b/c; "
                          "/tmp/pytest-of-root/p0; store checks: /tmp/bench_build_u2xbw8t0/store-bvh1: OK")
    assert found == ["/work/", "/root/", "/home/", "/Users/", "/tmp/pytest-of", "/tmp/bench_build_u2xbw8t0/"]
    assert machine_paths(".venv/bin/python -m bench.bench_sdf --out /tmp/unused; https://host.org/work/x; "
                         "s3://bucket/home/a; toy_run/work/store; ~/work/data; git worktree add /tmp/base") == []


def test_no_machine_paths_in_tracked_files():
    here = Path(__file__).resolve()
    problems = []
    for path in tracked_text_files():
        if path == here or not path.is_file():
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:  # a binary file (images, archives)
            continue
        for number, line in enumerate(text.splitlines(), 1):
            if found := machine_paths(line):
                problems.append(f"{path.relative_to(ROOT)}:{number}: {', '.join(found)}")
    assert not problems, "machine paths (use .venv/bin/python and relative folders):\n" + "\n".join(problems)
