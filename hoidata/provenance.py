"""Where a result came from: the checkout's commit, recorded in every store's index and every training run's
``config.json``. A ground-floor module: both the build and ``hoisdf`` record it without reaching into either."""

from __future__ import annotations

import subprocess
from pathlib import Path


def git_commit() -> str:
    """The ``git rev-parse HEAD`` of the checkout this package runs from; "unknown" outside a git checkout (an
    installed wheel), without git, or when git does not answer within 5 s."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, check=False,
                              text=True, timeout=5).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"
