"""The docs site builds with ``mkdocs build --strict`` (broken links, missing pages, unreadable docstrings
fail), and the generated settings reference documents every key of every pipeline section."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # builds the whole docs site

ROOT = Path(__file__).resolve().parents[1]


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_setting_has_a_description():
    text = _hooks().settings_reference()
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert len(rows) > 100  # every section's keys are listed
    cells = [row.split(" | ") for row in rows]  # key, type, default, range, meaning
    undocumented = [c[0].strip("| `") for c in cells if not c[-1].rstrip(" |")]
    assert not undocumented, f"settings without a comment beside their field: {undocumented}"


def test_docs_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    result = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                            cwd=ROOT, capture_output=True, text=True, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    assert (tmp_path / "site" / "settings" / "index.html").exists()

