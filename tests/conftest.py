"""Shared fixtures: the procedural MANO files are written once per test session."""

from __future__ import annotations

import os
import shutil

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

# the libraries whose behaviour on bad input the tests depend on (decoders, store formats): the suite says which
# versions it ran on, since a fresh install resolves the newest (e.g. OpenCV 5, whose imdecode raises on an empty
# buffer where 4.x returned None)
REPORTED_PACKAGES = ("opencv-python-headless", "numpy", "trimesh", "torch", "zarr", "webdataset", "scipy", "pyyaml")


def pytest_report_header(config):
    from importlib.metadata import PackageNotFoundError, version

    def found(name):
        try:
            return version(name)
        except PackageNotFoundError:
            return "not installed"

    lines = ["packages: " + ", ".join(f"{name} {found(name)}" for name in REPORTED_PACKAGES)]
    return lines + ([line] if (line := _disk_line(config)) else [])


def pytest_sessionstart(session):
    # -q (as CI runs the suite) prints no header: a disk short of room still gets its line
    line = _disk_line(session.config) or ""
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None and line.startswith("disk: only") and session.config.get_verbosity() < 0:
        reporter.write_line(line)


# Disk. The whole suite writes several GiB of toy datasets, stores and checkpoints (7.5 GiB at d951849, all of it
# kept to the end, which filled a CI machine's disk). A test's tmp_path is removed when the test passes (pyproject:
# tmp_path_retention_policy = "failed"), and the folders a module- or session-scoped fixture made under the base
# temporary folder during its set-up are removed when that fixture is torn down (FixtureFolders): the disk holds only
# the live fixtures and the test running. A fixture that hands out folders later (a factory) makes their parent
# folder in its set-up. `-o tmp_path_retention_policy=all` keeps everything, as pytest does by default.
NEEDED_GIB = 3


def _basetemp(config):
    """The session's base temporary folder, or None when pytest's tmp_path plugin is off."""
    factory = getattr(config, "_tmp_path_factory", None)
    return None if factory is None else factory.getbasetemp()


def _disk_line(config) -> str | None:
    """How much room the base temporary folder has, and a warning when it is less than the slow tier needs."""
    base = _basetemp(config)
    if base is None:
        return None
    free = shutil.disk_usage(base).free / 2**30
    return (f"disk: {'only ' if free < NEEDED_GIB else ''}{free:.1f} GiB free in {base} (the slow tier needs about "
            f"{NEEDED_GIB} GiB at once)")


def _cleaning(config) -> bool:
    return config.getini("tmp_path_retention_policy") != "all" and _basetemp(config) is not None


class FixtureFolders:
    """Removes the folders a module- or session-scoped fixture made under the base temporary folder when that
    fixture is torn down. A plugin of its own (registered below), not hooks of this conftest: pytest hands a
    conftest's hooks only the nodes under its folder, and a session-scoped fixture is torn down by the session."""

    def __init__(self):
        self.made: dict = {}  # fixturedef -> the folders its set-up made

    @pytest.hookimpl(wrapper=True)
    def pytest_fixture_setup(self, fixturedef, request):
        if fixturedef.scope == "function" or not _cleaning(request.config):
            return (yield)
        base = _basetemp(request.config)
        before = set(base.iterdir())
        try:
            return (yield)
        finally:
            claimed = set().union(*self.made.values())  # made by the fixtures this one set up first
            self.made[fixturedef] = self.made.get(fixturedef, set()) | (set(base.iterdir()) - before - claimed)

    def pytest_fixture_post_finalizer(self, fixturedef, request):
        for path in self.made.pop(fixturedef, ()):
            if path.is_symlink():  # mktemp's "<name>current" link
                path.unlink(missing_ok=True)
            else:
                shutil.rmtree(path, ignore_errors=True)


def pytest_configure(config):
    config.pluginmanager.register(FixtureFolders(), "fixture-folders")


# The fixtures that write a toy dataset or build a store (seconds each, and every fixture built on them): a test
# that uses one belongs to the slow tier (docs/development.md, "Test tiers"), so that `pytest -m "not slow"` stays a
# one-minute loop. A test left unmarked is refused at collection, or when it asks for one by name at run time.
STORE_FIXTURES = frozenset({
    "tiny_dexycb", "tiny_store", "tiny_store_two_shards", "tiny_region_store", "dexycb_8cam", "dexycb_s0", "ho3d_small",
    "ho3d_small_eval_store",
    "dex_root", "ho3d_root", "v3_root", "synth_store", "ho3d_source", "hot3d_root",  # the same kind, one file each
})
_RUNNING = pytest.StashKey()


def _store_fixture_misuse(item, names) -> str | None:
    """``item``'s nodeid and the store fixtures among ``names`` when ``item`` is not marked slow, else None."""
    used = sorted(STORE_FIXTURES.intersection(names))
    if used and item.get_closest_marker("slow") is None:
        return f"{item.nodeid} uses {', '.join(used)}"
    return None


def pytest_collection_modifyitems(config, items):
    wrong = [line for item in items if (line := _store_fixture_misuse(item, item.fixturenames))]
    if wrong:
        raise pytest.UsageError("tests that build a toy dataset or a store must be marked @pytest.mark.slow "
                                "(docs/development.md, \"Test tiers\"):\n  " + "\n  ".join(wrong))


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    item.config.stash[_RUNNING] = item


@pytest.hookimpl(tryfirst=True)
def pytest_fixture_setup(fixturedef, request):
    # request.getfixturevalue(name) escapes the collection check above; this catches it when it runs
    item = request.config.stash.get(_RUNNING, None)
    if item is not None and (line := _store_fixture_misuse(item, [fixturedef.argname])):
        pytest.fail(f"{line}: mark it @pytest.mark.slow (docs/development.md, \"Test tiers\")", pytrace=False)


@pytest.fixture(scope="session")
def mano_dir(tmp_path_factory):
    from hoidata.toy.hand import write_toy_mano

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


@pytest.fixture(scope="session")
def tiny_dexycb(tmp_path_factory):
    """A tiny toy DexYCB (1 subject, 2 sequences: right and left hand, 1 camera, 8 frames) with mano/ and models/."""
    from hoidata.toy.dexycb import ToyDexYCBSize, write_toy_dexycb
    from hoidata.toy.make import write_assets

    root = tmp_path_factory.mktemp("tiny_dexycb")
    mano_dir, models_dir = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=2, serials=(0,), frames=8)
    write_toy_dexycb(root, mano_dir, models_dir, size, workers=1, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_store(tiny_dexycb, tmp_path_factory):
    """A built store of the tiny toy DexYCB train split: 128 px crops, 256 + 128 SDF rows, one shard.

    Right and left (mirrored) hands; for model, augmentation and trainer tests.
    """
    return _build_tiny_store(tiny_dexycb, tmp_path_factory.mktemp("tiny_store") / "store", records_per_shard=64)


@pytest.fixture(scope="session")
def tiny_region_store(tiny_dexycb, tmp_path_factory):
    """The tiny toy DexYCB train split as upstream-region records (``frame.jpg`` in place of ``img.jpg``), 5 records
    per shard (4 shards, the last one short); read-only."""
    return _build_tiny_store(tiny_dexycb, tmp_path_factory.mktemp("tiny_region_store") / "store", records_per_shard=5,
                             more=['record.upstream_region=["train"]'])


def _build_tiny_store(tiny_dexycb, out, records_per_shard: int, more=()):
    """The tiny toy DexYCB's train split built into ``out``: 128 px crops, 256 + 128 SDF rows (``more``: further
    overrides)."""
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    overrides = ['dataset.splits=["train"]', "record.crop_size=128", "record.sdf_samples_hand=256", "record.sdf_samples_object=128",
                 f"store.records_per_shard={records_per_shard}", *more]
    build_store(load_build_config("toy", overrides), tiny_dexycb, tiny_dexycb / "mano", tiny_dexycb / "models",
                out, workers=1, part=(0, 1), progress=False)
    return out


@pytest.fixture(scope="session")
def dexycb_8cam(tmp_path_factory):
    """A toy DexYCB with all eight cameras, as the toolkit enumerates them: 1 subject, 3 train sequences (right,
    left, right), 2 frames; frame 1 of the third sequence is invalid (joint_3d -1) in every camera."""
    from hoidata.toy.dexycb import ToyDexYCBSize, write_toy_dexycb
    from hoidata.toy.make import write_assets

    root = tmp_path_factory.mktemp("dexycb_8cam")
    mano_dir, models_dir = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=3, serials=tuple(range(8)), frames=2, invalid_frame=1)
    write_toy_dexycb(root, mano_dir, models_dir, size, workers=1, progress=False)
    return root


@pytest.fixture(scope="session")
def dexycb_s0(tmp_path_factory):
    """A toy DexYCB with s0 train and test (and val): subjects 1 and 3, 5 sequences each (right, left, right,
    left, right; the fifth is val for subject 1 and test for subject 3), 1 camera, 6 frames: approach frames
    0-1 (hand not yet on the object), then a lift-and-turn; frame 4 of the third sequence is invalid."""
    from hoidata.toy.dexycb import ToyDexYCBSize, write_toy_dexycb
    from hoidata.toy.make import write_assets

    root = tmp_path_factory.mktemp("dexycb_s0")
    mano_dir, models_dir = write_assets(root)
    size = ToyDexYCBSize(subjects=(0, 2), sequences=5, serials=(0,), frames=6, invalid_frame=4)
    write_toy_dexycb(root, mano_dir, models_dir, size, workers=2, progress=False)
    return root


@pytest.fixture(scope="session")
def ho3d_small(tmp_path_factory):
    """A toy HO-3D v2: 2 training sequences and 1 evaluation sequence of 3 frames."""
    from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d
    from hoidata.toy.make import write_assets

    root = tmp_path_factory.mktemp("ho3d_small")
    mano_dir, models_dir = write_assets(root)
    write_toy_ho3d(root, mano_dir, models_dir, ToyHO3DSize(train_sequences=2, eval_sequences=1, frames=3),
                   progress=False)
    return root


@pytest.fixture(scope="session")
def ho3d_small_eval_store(ho3d_small, tmp_path_factory):
    """The evaluation split of ``ho3d_small`` built into a store of ``eval`` records (64 px crops); read-only."""
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    out = tmp_path_factory.mktemp("ho3d_small_eval") / "store"
    build_store(load_build_config("ho3d_eval", ["record.crop_size=64"]), ho3d_small, ho3d_small / "mano",
                ho3d_small / "models", out, progress=False)
    return out


@pytest.fixture(scope="session")
def tiny_store_two_shards(tiny_dexycb, tmp_path_factory):
    """The tiny toy DexYCB train split in 2 shards of 8 records (128 px crops): for 2-process (DDP) tests."""
    return _build_tiny_store(tiny_dexycb, tmp_path_factory.mktemp("tiny_store_two_shards") / "store",
                             records_per_shard=8)


@pytest.fixture(scope="session")
def untrained_run(tmp_path_factory, mano_dir):
    """A run folder holding an untrained tiny HOISDF's checkpoint (for evaluation plumbing tests)."""
    import torch

    from hoidata.hand import load_mano
    from hoisdf.config import load_train_config
    from hoisdf.model import build_model
    from hoisdf.training.checkpoint import save_checkpoint

    cfg = load_train_config(None, ["model.depth=18", "model.image_size=64", "model.hand_queries=32", "model.object_queries=16",
                                   "model.grid_resolution=16", "model.hand_layers=1", "model.decoder_layers=1",
                                   "model.object_layers=1"])
    torch.manual_seed(0)
    run = tmp_path_factory.mktemp("run")
    save_checkpoint(run / "checkpoints" / "last.pt", {"model": build_model(cfg.model, load_mano(mano_dir)).state_dict(),
                                                      "config": cfg.as_dict(), "progress": {}})
    return run
