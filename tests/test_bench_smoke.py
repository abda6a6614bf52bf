"""Every benchmark script runs end to end at its smallest size and prints its table (issue 35): a bench that
breaks fails here, not in front of a user. No timing is asserted, only the exit status and the table.

SCRIPTS names each runnable module under bench/ (one with a ``__main__`` block) with its smallest arguments and a
line of its table; ``test_every_bench_script_is_covered`` fails when a script is added without an entry. The toy
DexYCB and the toy store are written once for the module and handed to the scripts that take ``--root`` /
``--store`` (placeholders {root}, {store}, {mano}, {tmp}). The model's benches (``MODEL_SCRIPTS``) run from
tests/test_bench_smoke_model.py, so that the two halves run side by side under ``pytest -n 2``.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SMALL_SDF = ["--frames", "1", "--rounds", "1", "--n-hand", "256", "--n-object", "128"]
TOY_MODEL = ["--config", "toy", "--store", "{store}", "--mano", "{mano}", "--device", "cpu"]
TINY_MODEL = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
               "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
               "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16",
               "model.grid_resolution=12", "model.chunk=1000"]
TINY_RECIPE = [*TINY_MODEL, "train.batch_size=2",
               "augment.upstream=false"]  # the smoke store is a project-crop store (a region store: 256 px)

# module -> list of (arguments, a piece of the table it prints); several entries run one after the other
SCRIPTS: dict[str, list[tuple[list[str], str]]] = {
    "bench_sdf": [(SMALL_SDF, "all frames (sum of medians)")],
    "bench_grid_features": [(["--points", "1000", "--size", "64", "--reps", "1", "--device", "cpu"],
                             "decoder  sum C  direct ms")],
    "bench_plausibility": [(["--frames", "1", "--workers", "1", "--tolerance", "1e-6"], "inherited, 1 process")],
    "plausibility_cases": [(["--tolerance", "1e-6"], "cylinder through box")],
    "bench_build": [(["--root", "{root}", "--frames", "12", "--rounds", "1", "--workers", "1"],
                     "1 worker(s): bvh")],
    "bench_hot3d": [(["--dexycb-root", "{root}", "--frames", "1", "--rounds", "1"], "HOT3D / DexYCB rate")],
    "bench_build_ab": [(["--baseline", str(ROOT), "--root", "{root}", "--rounds", "1"],
                        "shards byte-identical across trees and rounds: True")],
    "bench_export": [(["--root", "{root}", "--frames", "8"], "export gsdf --store")],
    "bench_synthetic": [(["--count", "2", "--workers", "1"], "physical check:")],
    "bench_loader": [(["--root", "{root}", "--batch", "4", "--batches", "2", "--rounds", "1", "--workers", "0", "1"],
                      "workers cores  training  upstream")],
    "bench_train": [([*TOY_MODEL, "--batch-size", "2", "--steps", "1", "--warmup", "0", "--frames", "2",
                      "--infer-batch", "2", "--workers", "0", "--loader-batches", "2"], "augment_batch on cpu")],
    "bench_train_step": [([*TOY_MODEL, "--batch-size", "2", "--rounds", "1", "--steps", "1", "--variants", "nchw"],
                          "backbone alone")],
    "bench_evaluate": [([*TOY_MODEL, "--frames", "4", "--batch-size", "2", "--workers", "0", *TINY_MODEL],
                        "evaluate end to end")],
    # the GPU rows: inputs prepared here, then the run on the CPU when there is no CUDA, without code generation
    # (--backend eager): every row of the table, no inductor compile
    "bench_gpu": [(["prepare", "--config", "toy", "--store", "{store}", "--mano", "{mano}", "--out", "{tmp}/gpu",
                    "--batch", "2", *TINY_MODEL],
                   "inputs.pt"),
                  (["run", "--inputs", "{tmp}/gpu", "--backend", "eager", "--frames", "2", "--warmup", "1",
                    "--steps", "1", "--precision", "fp32"], "compiled fixed")],
    # the upstream recipe's steps: dexycb's settings with a tiny model; no CUDA here, so the CPU-only rows
    "bench_recipe_gpu": [(["prepare", "--store", "{store}", "--mano", "{mano}", "--out", "{tmp}/recipe", "--batches", "1",
                           *TINY_RECIPE], "inputs.pt"),
                         (["run", "--inputs", "{tmp}/recipe", "--steps", "1", "--warmup", "0", "--compare", "1"],
                          "projected 70 epochs")],
    "bench_cluster": [(["--root", "{root}", "--rounds", "1", "--records-per-shard", "8", "--passes", "1"],
                       "ray (running)")],
    "bench_volume": [(["--frames", "1", "--split-frames", "2", "--workers", "1"], "mean seconds per frame: exact cells")],
    "bench_recon": [(["--frames", "1", "--tolerance", "0.1", "--max-queries", "100000"],
                     "mean CPU seconds per frame: gsdf")],
    "bench_scaling": [(["--out", "{tmp}/scaling", "--points", "500", "1000", "--faces", "320", "1280", "--frames", "12",
                        "24", "--workers", "0", "1", "--recon-faces", "80", "320", "--rounds", "1"],
                       "| series | size | cost | log-log slope | reading |")],
    "bench_shuffle": [(["--store", "{store}", "--batch", "4", "--workers", "0", "--epochs", "1", "--rounds", "1"],
                       "load average (1 min):")],
    "bench_upstream_aug": [(["--root", "{root}", "--batch", "2", "--batches", "1", "--rounds", "1", "--workers", "0"],
                            "upstream __getitem__")],
    "bench_suite_disk": [(["--every", "0.5", "tests/test_safe_pickle.py"], "| the suite's settings |")],
    "bench_loaders": [(["--store", "{store}", "--loaders", "iter_records", "webdataset"], "| webdataset |")],
}
# scripts that cannot run here, with the reason; the test checks the reason still holds
NEEDS = {"bench_cluster": ("ray", "submitit")}  # the cluster extra
# the benches of the model, training, loading and evaluation run from tests/test_bench_smoke_model.py: a file of
# their own, so that pytest -n 2 (--dist loadfile) runs the two halves of the set side by side
MODEL_SCRIPTS = frozenset({"bench_gpu", "bench_recipe_gpu", "bench_train_step", "bench_train", "bench_evaluate",
                           "bench_grid_features", "bench_upstream_aug", "bench_loader", "bench_shuffle"})


def runnable_scripts() -> set[str]:
    return {p.stem for p in (ROOT / "bench").glob("*.py") if re.search(r"^if __name__ == .__main__.:", p.read_text(),
                                                                        re.M)}


def test_every_bench_script_is_covered():
    """A new bench script without an entry here fails, so none can break unnoticed."""
    assert runnable_scripts() == set(SCRIPTS), sorted(runnable_scripts() ^ set(SCRIPTS))
    assert {"bench_loader", "bench_sdf", "bench_gpu"} <= runnable_scripts()  # the scan itself finds scripts
    assert MODEL_SCRIPTS < set(SCRIPTS)  # each script runs in one of the two files


def write_toy_data(tmp_path_factory) -> dict[str, str]:
    """A toy DexYCB (its MANO and models folders inside) and a 512 px train store built from it: the placeholders
    of the scripts' arguments."""
    from bench.common import toy_root
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    work = tmp_path_factory.mktemp("bench_smoke")
    root = toy_root(24, work)
    cfg = load_build_config("toy", ['dataset.splits=["train"]', "record.crop_size=512", "store.records_per_shard=8"])
    build_store(cfg, root, root / "mano", root / "models", work / "store", workers=1, progress=False)
    return {"root": str(root), "store": str(work / "store"), "mano": str(root / "mano"), "tmp": str(work)}


@pytest.fixture(scope="module")
def toy_data(tmp_path_factory):
    return write_toy_data(tmp_path_factory)


def run_bench(module: str, args: list[str], python_prelude: str = "") -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYOPENGL_PLATFORM="egl", PYTHONUNBUFFERED="1")
    code = f"{python_prelude}import runpy, sys; sys.argv[0] = {module!r}; runpy.run_module({module!r}, run_name='__main__')"
    return subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=1800)


def check_script(script: str, toy_data: dict[str, str]) -> None:
    """Every run of ``script`` in :data:`SCRIPTS` exits 0 and prints its table (skipped where :data:`NEEDS` says)."""
    missing = [m for m in NEEDS.get(script, ()) if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"{script} needs {', '.join(missing)} (pip install -e '.[cluster]')")
    for args, table in SCRIPTS[script]:
        args = [a.format(**toy_data) for a in args]
        done = run_bench(f"bench.{script}", args)
        assert done.returncode == 0, f"{script} {' '.join(args)} exited {done.returncode}:\n{done.stderr[-3000:]}"
        assert table in done.stdout, f"{script}: no '{table}' in:\n{done.stdout[-3000:]}"


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(set(SCRIPTS) - MODEL_SCRIPTS))
def test_bench_script_runs_and_prints_its_table(script, toy_data):
    check_script(script, toy_data)


@pytest.mark.slow
def test_bench_sdf_without_open3d_prints_not_installed():
    """The open3d column is optional: with open3d hidden (as when the bench extra is not installed) the bench
    still runs and says so; with it installed the column has numbers (the plain run above)."""
    done = run_bench("bench.bench_sdf", SMALL_SDF, "import sys; sys.modules['open3d'] = None; ")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "open3d not installed" in done.stdout and "all frames (sum of medians)" in done.stdout
