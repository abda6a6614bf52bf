"""Before a process creates its first EGL context: what must be loaded first, and only where it is needed.

Loading torch's compiler stack (``torch._dynamo``, which ``import torchvision`` pulls in) after an EGL context
exists segfaults (CUDA bindings vs Mesa). A main process that renders and then builds the model (the test
suite, the toy main job, a serial ``build-sdf`` followed by training) must therefore load it before rendering.
A spawned pool worker (build-sdf, make-toy, render-synthetic workers) only renders and never builds the model,
so it skips the import, which costs about 1.3 s of every worker's start-up.
"""

from __future__ import annotations

import multiprocessing
import os


def prepare_for_egl() -> None:
    """Load torch's compiler stack in a main process (not in pool workers); select EGL for PyOpenGL."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # before any pyrender / OpenGL import
    if multiprocessing.parent_process() is None:
        import torch._dynamo  # noqa: F401
