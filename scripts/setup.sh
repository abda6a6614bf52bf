#!/usr/bin/env bash
# Set up a fresh machine for hoidata/hoisdf: system GL libraries for offscreen rendering, a virtual
# environment in .venv, torch, and the package with all extras (s3fs / gcsfs for s3:// and gs:// stores are not
# among them: pip install them where needed). Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

GL_PACKAGES=(libegl1 libgl1-mesa-dri libegl-mesa0)
if ! dpkg -s "${GL_PACKAGES[@]}" >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo"; else SUDO="none"; fi
  if [ "$SUDO" = none ]; then
    echo "setup: cannot install ${GL_PACKAGES[*]} (not root, no sudo); offscreen rendering may not work" >&2
  else
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${GL_PACKAGES[@]}" >/dev/null
  fi
fi

PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# torch first, pinned: pip finds these on local disk here; a looser spec would pull a newer CUDA build.
.venv/bin/python -m pip install -q "torch==2.14.1" "torchvision==0.29.1"
# cluster: submitit, ray, fsspec, aiohttp; interop, dali: the other loaders of docs/other-loaders.md (about 1.8 GB
# installed, pyproject.toml says what each adds); their tests run in CI
.venv/bin/python -m pip install -q -e ".[test,docs,cluster,interop,dali]"
echo "setup: done ($(.venv/bin/python -c 'import hoidata, torch; print("hoidata", hoidata.__version__, "torch", torch.__version__)'))"
