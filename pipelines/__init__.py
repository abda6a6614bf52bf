"""The named pipeline settings (``<name>.toml``), installed as the package ``hoidata.presets`` (see setup.py).

This file makes the installed folder a regular package, so ``importlib.resources.files("hoidata.presets")`` is one
folder rather than a namespace package's ``MultiplexedPath``. It holds no code.
"""
