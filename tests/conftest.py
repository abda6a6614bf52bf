"""Shared fixtures: the procedural MANO files are written once per test session."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


@pytest.fixture(scope="session")
def mano_dir(tmp_path_factory):
    from hoidata.hand.toy import write_toy_mano

    out = tmp_path_factory.mktemp("mano")
    write_toy_mano(out)
    return out


@pytest.fixture(scope="session")
def mano_right(mano_dir):
    import torch

    from hoidata.hand import load_mano

    return load_mano(mano_dir, side="right", dtype=torch.float64)


@pytest.fixture(scope="session")
def mano_left(mano_dir):
    import torch

    from hoidata.hand import load_mano

    return load_mano(mano_dir, side="left", dtype=torch.float64)
