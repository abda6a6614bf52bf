#!/usr/bin/env bash
# What a user installs is what is tested: build the wheel (not an editable install), install it into a fresh
# virtual environment and run a short chain of the commands from a folder outside the checkout, where the
# checkout's pipelines/ cannot stand in for the installed presets.
#
#   bash scripts/check_install.sh            (CI runs it after the test suite; tests/test_install.py too)
#
# The dependencies are not downloaded again: the fresh environment sees the main environment's site-packages
# (PYTHON's, default .venv) through a .pth line placed after its own, so torch is reused and the build stays
# fast; the package itself, its console script and its presets come only from the wheel (checked below). The
# main environment's editable install is not active there: its finder is started by a .pth file, and .pth files
# are only read in the environment's own site-packages.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON:-$REPO/.venv/bin/python}
WORK=$(mktemp -d "${TMPDIR:-/tmp}/hoisdf-install.XXXXXX")
[ -n "${KEEP_INSTALL_CHECK:-}" ] || trap 'rm -rf "$WORK"' EXIT
step() { echo "check_install: $*"; }

step "wheel from $REPO"
# a copy of the tracked files, so the build's own build/ and *.egg-info folders never land in the checkout
mkdir "$WORK/src"
git -C "$REPO" ls-files -z --cached --others --exclude-standard | (cd "$REPO" && xargs -0 cp --parents -t "$WORK/src" 2>/dev/null || true)
"$PY" -m pip wheel --no-deps --no-build-isolation -q -w "$WORK/dist" "$WORK/src" >/dev/null
WHEEL=$(ls "$WORK"/dist/hoisdf-*.whl)
"$PY" - "$WHEEL" <<'EOF'
import sys, zipfile
names = zipfile.ZipFile(sys.argv[1]).namelist()
presets = sorted(n for n in names if n.startswith("hoidata/presets/"))
assert "hoidata/presets/__init__.py" in presets and "hoidata/presets/toy.toml" in presets, presets
assert not any(n.endswith(".whl") or n.startswith(("tests/", "pipelines/")) for n in names), "stray files in the wheel"
print(f"check_install: {sys.argv[1].rsplit('/', 1)[-1]}: {len(names)} files, presets {[p.rsplit('/', 1)[-1] for p in presets]}")
EOF

step "fresh virtual environment"
BASE=$("$PY" -c 'import sys; print(getattr(sys, "_base_executable", sys.executable))')
"$BASE" -m venv "$WORK/venv"
NEW_SITE=$("$WORK/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
"$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])' > "$NEW_SITE/zz_reuse_dependencies.pth"
"$WORK/venv/bin/python" -m pip install -q --no-deps --no-index "$WHEEL"

step "a short chain from $WORK/outside"
mkdir "$WORK/outside"
cd "$WORK/outside"
export PATH="$WORK/venv/bin:$PATH" PYTHONPATH= PYTHONNOUSERSITE=1
python - "$NEW_SITE" <<'EOF'
import sys, hoidata, hoisdf
from hoidata.sections import pipelines_dir
for module in (hoidata, hoisdf):
    assert module.__file__.startswith(sys.argv[1]), f"{module.__name__} imported from {module.__file__}, not the wheel"
print(f"check_install: hoidata from {hoidata.__file__}; presets {pipelines_dir()}")
EOF
hoidata --version
hoidata make-toy --out toy --layout ho3d --sequences 1 --frames 1 >/dev/null
hoidata build-sdf --dataset ho3d --root toy --out store --workers 1 record.crop_size=64 record.sdf_samples_hand=64 \
  record.sdf_samples_object=64 'record.upstream_region=[]' 2>/dev/null  # the named preset, read from the installed
# hoidata.presets (no progress bars); project crops, not its upstream frame regions: the step below trains the toy's
# small model on them
hoidata verify store
python -m hoisdf.train --config toy --shards store --mano toy/mano --out run --no-progress model.depth=18 \
  model.image_size=64 model.hand_queries=32 model.object_queries=16 model.grid_resolution=16 model.hand_layers=1 \
  model.decoder_layers=1 model.object_layers=1 train.batch_size=1 train.workers=0 train.max_steps=1 \
  train.val_every=0 >/dev/null
test -f run/checkpoints/last.pt
step "ok: the installed wheel made, built, verified and trained on toy data outside the checkout"
