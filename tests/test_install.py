"""What a user installs is what is tested: the presets as an installed wheel holds them, and the wheel itself in a
fresh environment, run from outside the checkout (scripts/check_install.sh, which CI runs as its own step)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_presets_read_through_the_resources_api_of_any_package_kind(tmp_path, monkeypatch):
    """Outside a checkout the presets come from importlib.resources; a namespace package (no __init__.py, how the
    wheel shipped them before) gives a MultiplexedPath, whose str() is not a folder name. Every Traversable must do."""
    import importlib.resources
    from importlib.resources.readers import MultiplexedPath

    from hoidata import sections
    from hoidata.records.settings import load_build_config

    (tmp_path / "toy.toml").write_bytes((REPO / "pipelines" / "toy.toml").read_bytes())
    monkeypatch.setattr(sections, "CHECKOUT_PIPELINES", tmp_path / "no-checkout")
    monkeypatch.setattr(importlib.resources, "files", lambda name: MultiplexedPath(tmp_path))
    assert load_build_config("toy", ["record.sdf_samples_hand=8"]).record.sdf_samples_hand == 8
    assert sections.read_pipeline("toy")[1] == sections.read_pipeline(str(REPO / "pipelines" / "toy.toml"))[1]
    from hoidata.errors import DataError

    with pytest.raises(DataError, match=r"nope\.toml: pipeline config not found"):
        sections.resolve_pipeline("nope")


def test_the_wheel_ships_the_presets_as_a_regular_package():
    assert (REPO / "pipelines" / "__init__.py").is_file()  # setup.py maps pipelines/ to hoidata.presets
    assert "hoidata.presets" in (REPO / "setup.py").read_text()


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("HOISDF_INSTALL_CHECK") == "ci", reason="CI runs scripts/check_install.sh itself")
def test_installed_wheel_runs_a_chain_outside_the_checkout():
    """pip wheel -> fresh venv -> make-toy, build-sdf (the installed 'ho3d' preset), verify, one training step,
    from a temporary folder; the script asserts hoidata and hoisdf are imported from the wheel, not the checkout."""
    proc = subprocess.run(["bash", str(REPO / "scripts" / "check_install.sh")], capture_output=True, text=True,
                          timeout=900, check=False, env={**os.environ, "PYTHON": sys.executable, "PYTHONPATH": ""},
                          cwd=REPO)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "check_install: ok" in proc.stdout and "/venv/" in proc.stdout


def test_the_scripts_import_only_names_the_package_has():
    """Fast tier: every ``from hoidata|hoisdf... import`` line in scripts/*.sh (their Python heredocs) names a module
    and names that exist. CI runs scripts/check_install.sh after the suite, so a moved name would otherwise fail only
    there (it did once: pipelines_dir after the move to hoidata.sections)."""
    import importlib
    import re

    found = 0
    for script in sorted((Path(__file__).resolve().parents[1] / "scripts").glob("*.sh")):
        for line in script.read_text().splitlines():
            match = re.match(r"\s*from\s+((?:hoidata|hoisdf)[\w.]*)\s+import\s+([\w, ]+)", line)
            if match:
                module = importlib.import_module(match[1])
                missing = [n.strip() for n in match[2].split(",") if not hasattr(module, n.strip())]
                assert not missing, f"{script.name}: {match[1]} has no {missing}"
                found += 1
    assert found  # the check reads the heredocs at all
