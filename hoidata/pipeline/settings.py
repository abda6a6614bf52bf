"""Build settings: ``pipelines/<name>.toml`` -> typed dataclasses, with ``section.key=value`` overrides.

The resolved config is saved in every store's index. Nothing else reads TOML: the pipeline gets
these dataclasses and passes explicit values on.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import ClassVar

import tomllib

from hoidata.datasets.dexycb import DexYCBSetting
from hoidata.errors import DataError
from hoidata.geometry.sdf import BACKENDS as SDF_BACKENDS
from hoidata.pipeline.records import RecordSettings

# A checkout's pipelines/ folder; an installed wheel carries the same files as the regular package hoidata.presets
# (pipelines/__init__.py makes it one; setup.py maps the folder to that name).
CHECKOUT_PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"


def pipelines_dir():
    """Where the named pipelines live: the checkout's ``pipelines/`` when there is one, else the installed copy.

    The installed copy is reached through ``importlib.resources`` and returned as its Traversable (a ``Path`` for
    an ordinary install, something else for a zipped or namespace one): callers only use ``joinpath``,
    ``is_file``, ``read_text`` and ``str``, which every Traversable has. ``Path(str(...))`` would break on the
    others (a namespace package's ``MultiplexedPath`` prints as ``MultiplexedPath('...')``).
    """
    if CHECKOUT_PIPELINES.is_dir():
        return CHECKOUT_PIPELINES
    from importlib.resources import files

    return files("hoidata.presets")


@dataclass(frozen=True)
class DatasetConfig:
    name: str = "dexycb"  # reader: 'dexycb' | 'ho3d'
    version: str = "v2"  # HO-3D release: 'v2' (PNG frames) | 'v3' (JPEG frames, its own lists; --dataset ho3d_v3)
    setting: str = "dexycb"  # a name for the frame selection (recorded)
    setup: str = "s0"  # DexYCB toolkit setup: s0 (seen), s1 (unseen subjects), s2 (unseen views), s3 (unseen objects)
    splits: tuple[str, ...] = ("train", "test")  # splits to build (DexYCB: train/val/test; HO-3D: train/evaluation)
    sides: tuple[str, ...] = ("right",)  # hands to keep: 'right', 'left' (left hands are mirrored to right ones)
    frame_stride: int = 1  # keep every n-th frame of each camera (DexYCB's papers use 5)
    proximity_mm: float = -1.0  # negative: no proximity filter
    proximity_splits: tuple[str, ...] = ("train", "val", "test")  # splits on which the proximity filter applies
    complete_subjects: bool = True  # DexYCB: require 100 sequences per subject (see DexYCBSetting)
    fix_left_shapedirs: bool = False  # DexYCB: its labels use MANO_LEFT without the shapedirs fix
    frame_list: str = ""  # DexYCB: a JSON list of toolkit sample ids (gSDF's format) to build exactly; one split
    proximity_to: str = "hand_vertices"  # DexYCB: 'hand_vertices' (MANO mesh, gSDF) or 'hand_joints' (ArtiBoost)
    box_splits: tuple[str, ...] = ("train", "val", "test")  # DexYCB: splits where HandOccNet's hand box rule applies
    motion_deg: float = -1.0  # DexYCB: keep frames whose object turned more than this since frame 0 (negative: off)
    motion_m: float = -1.0  # DexYCB: ... or moved more than this many metres (negative: off)
    # DexYCB: {split: frames} the setting selects on the full dataset; a complete build that differs warns
    expected_frames: dict = field(default_factory=dict)
    LIMITS: ClassVar[dict] = {"frame_stride": (">= 1",)}  # proximity_mm: any number (negative: off)

    def dexycb_setting(self) -> DexYCBSetting:
        return DexYCBSetting(name=self.setting, setup=self.setup, sides=tuple(self.sides), frame_stride=self.frame_stride,
                             proximity_mm=None if self.proximity_mm < 0 else self.proximity_mm,
                             proximity_splits=tuple(self.proximity_splits), mirror_left="left" in self.sides,
                             complete_subjects=self.complete_subjects, fix_left_shapedirs=self.fix_left_shapedirs,
                             proximity_to=self.proximity_to, box_splits=tuple(self.box_splits),
                             motion_deg=None if self.motion_deg < 0 else self.motion_deg,
                             motion_m=None if self.motion_m < 0 else self.motion_m)


@dataclass(frozen=True)
class StoreConfig:
    records_per_shard: int = 256  # records per shard-%06d.tar (the unit of parallel work and of resume)
    LIMITS: ClassVar[dict] = {"records_per_shard": (">= 1",)}


@dataclass(frozen=True)
class BuildConfig:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    record: RecordSettings = field(default_factory=RecordSettings)
    store: StoreConfig = field(default_factory=StoreConfig)

    def as_dict(self) -> dict:
        return asdict(self)


_SCALARS = {"bool": (bool,), "int": (int,), "float": (int, float), "str": (str,)}
_WORDS = {"bool": "true or false", "int": "an integer", "float": "a number", "str": "a string"}


def value_problem(annotation: str, value) -> str | None:
    """Why ``value`` does not fit a settings field annotated ``annotation`` (None when it fits).

    Understands the annotations the settings dataclasses use: bool, int, float (an int is accepted), str, and
    tuples of them, either ``tuple[T, ...]`` or a fixed ``tuple[T, T]``; others are not checked. A bool is
    not an int here.
    """
    if annotation in _SCALARS:
        ok = isinstance(value, _SCALARS[annotation]) and (annotation == "bool" or not isinstance(value, bool))
        if ok and annotation == "float" and not math.isfinite(value):
            return f"must be a finite number, got {value!r}"
        return None if ok else f"must be {_WORDS[annotation]}, got {value!r}"
    if annotation.startswith("tuple[") and annotation.endswith("]"):
        items = [a.strip() for a in annotation[6:-1].split(",")]
        if not isinstance(value, (list, tuple)):
            return f"must be a list ({annotation}), got {value!r}"
        if items[-1] != "..." and len(value) != len(items):
            return f"must hold {len(items)} values ({annotation}), got {len(value)}"
        for v in value:
            problem = value_problem(items[0], v)
            if problem:
                return f"every item {problem}"
    return None


def limit_problem(rules: tuple[str, ...], value) -> str | None:
    """Why ``value`` (a number or a list of numbers) breaks one of ``rules`` such as (">= 1",) or ("> 0", "<= 1")."""
    ops = {">": lambda a, b: a > b, ">=": lambda a, b: a >= b, "<": lambda a, b: a < b, "<=": lambda a, b: a <= b}
    for item in value if isinstance(value, (list, tuple)) else [value]:
        for rule in rules:
            op, bound = rule.split()
            if not ops[op](item, float(bound)):
                return f"must be {' and '.join(rules)}{' (every item)' if isinstance(value, (list, tuple)) else ''}, got {value!r}"
    return None


def section(cls, values: dict, path: Path, name: str):
    """``cls(**values)`` after checking every key is a field of ``cls``, every value fits its annotation and the
    range the class declares for it (``LIMITS``: field -> rules like (">= 1",); the defaults obey them too)."""
    known = {f.name: f for f in fields(cls)}
    limits = getattr(cls, "LIMITS", {})
    kwargs = {}
    for key, value in values.items():
        if key not in known:
            raise DataError(path, f"{name}.{key}", f"unknown setting; expected one of {sorted(known)}")
        problem = value_problem(known[key].type, value) or (key in limits and limit_problem(limits[key], value))
        if problem:
            raise DataError(path, f"{name}.{key}", problem)
        kwargs[key] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)


def resolve_pipeline(name_or_path: str) -> Path:
    """'dexycb' -> pipelines/dexycb.toml (a Traversable of the installed presets outside a checkout, see
    :func:`pipelines_dir`); a path is used as it is."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = pipelines_dir().joinpath(f"{name_or_path}.toml")
    if not path.is_file():
        raise DataError(path, None, "pipeline config not found")
    return path


TRAIN_SECTIONS = ("model", "train", "augment", "loss")  # read by hoisdf.config, ignored by the build


def apply_overrides(data: dict, overrides: list[str], path: Path) -> dict:
    """Set ``section.key=value`` items (values parsed as TOML, else kept as bare strings) in ``data``; returns it."""
    for item in overrides:
        key, sep, raw = item.partition("=")
        section_name, dot, name = key.partition(".")
        if not sep or not dot:
            raise DataError(path, item, "overrides look like section.key=value, e.g. record.n_hand=2048")
        try:
            data.setdefault(section_name, {})[name] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            data.setdefault(section_name, {})[name] = raw  # a bare string
    unknown = set(data) - {"dataset", "record", "store", *TRAIN_SECTIONS}
    if unknown:
        raise DataError(path, sorted(unknown)[0], "unknown section")
    return data


def read_pipeline(name_or_path: str, overrides: list[str] = ()) -> tuple[Path, dict]:
    """A pipeline TOML as a dict of sections with ``section.key=value`` overrides applied."""
    path = resolve_pipeline(name_or_path)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise DataError(path, None, f"invalid TOML: {e}") from e
    return path, apply_overrides(data, overrides, path)


BUILD_SECTIONS = ("dataset", "record", "store")  # read by the build, ignored by training


def refuse_unused(overrides: list[str], used: tuple[str, ...], command: str, user: str, path: Path) -> None:
    """An override of a section this command does not read is an error, not silently ignored."""
    for item in overrides:
        section_name = item.partition("=")[0].partition(".")[0]
        if section_name not in used and section_name in (*BUILD_SECTIONS, *TRAIN_SECTIONS):
            raise DataError(path, item.partition("=")[0], f"{command} does not use [{section_name}] settings "
                                                          f"({user} reads them); leave this override out")


def origin(path: Path, overrides, *keys: str) -> str:
    """Who set ``keys`` (``section.key``), for an error about them: the pipeline file, and the command line's
    overrides of them where there are any (an error caused by an override does not blame the file alone)."""
    given = [item for item in overrides if item.partition("=")[0].strip() in keys]
    return f"{path} with the command line's {' '.join(given)}" if given else str(path)


def load_build_config(name_or_path: str, overrides: list[str] = ()) -> BuildConfig:
    """Read a pipeline TOML and apply ``section.key=value`` overrides (values parsed as TOML); overrides of the
    training sections are an error (the build does not use them)."""
    refuse_unused(list(overrides), BUILD_SECTIONS, "build-sdf", "python -m hoisdf.train", resolve_pipeline(name_or_path))
    path, data = read_pipeline(name_or_path, overrides)
    record = section(RecordSettings, data.get("record", {}), path, "record")
    dataset = section(DatasetConfig, data.get("dataset", {}), path, "dataset")
    if dataset.name not in ("dexycb", "ho3d"):
        raise DataError(origin(path, overrides, "dataset.name"), "dataset.name",
                        f"unknown dataset {dataset.name!r}; expected 'dexycb' or 'ho3d'")
    if dataset.version not in ("v2", "v3"):
        raise DataError(origin(path, overrides, "dataset.version"), "dataset.version",
                        f"unknown HO-3D version {dataset.version!r}; expected 'v2' or 'v3'")
    if dataset.frame_list and (dataset.name != "dexycb" or len(dataset.splits) != 1):
        where = origin(path, overrides, "dataset.frame_list", "dataset.splits", "dataset.name")
        raise DataError(where, "dataset.frame_list", "a frame list holds the toolkit ids of one DexYCB split: set "
                                                     'dataset.splits to that split, e.g. dataset.splits=["test"]')
    _check_selection(dataset, path)
    if record.sdf_backend not in SDF_BACKENDS:
        raise DataError(path, "record.sdf_backend", f"unknown backend {record.sdf_backend!r}; expected one of {SDF_BACKENDS}")
    _check_crop(record, dataset, path)
    return BuildConfig(dataset,
                       replace(record, sigmas=tuple(record.sigmas)),
                       section(StoreConfig, data.get("store", {}), path, "store"))


def _check_crop(record: RecordSettings, dataset: DatasetConfig, path: Path) -> None:
    """record.crop names a crop; upstream's HO-3D test crop exists for its evaluation split only (its training
    split has no upstream test crop to reproduce)."""
    from hoidata.pipeline.upstream_records import CROPS

    if record.crop not in CROPS:
        raise DataError(path, "record.crop", f"expected one of {CROPS}, got {record.crop!r}")
    odd = sorted(set(record.crop_splits) & set(dataset.splits) - {"evaluation"})
    if record.crop == "upstream" and dataset.name == "ho3d" and odd:
        raise DataError(path, "record.crop_splits", f"upstream's HO-3D test crop exists for the evaluation split "
                                                    f"only, not for {odd}")


def _check_selection(dataset: DatasetConfig, path: Path) -> None:
    """The DexYCB rule names and the stated counts: DataError naming the key."""
    from hoidata.datasets.dexycb_selection import PROXIMITY_TARGETS

    if dataset.proximity_to not in PROXIMITY_TARGETS:
        raise DataError(path, "dataset.proximity_to", f"expected one of {PROXIMITY_TARGETS}, got {dataset.proximity_to!r}")
    expected = dataset.expected_frames
    if not isinstance(expected, dict) or not all(isinstance(k, str) and value_problem("int", v) is None and v >= 0
                                                 for k, v in expected.items()):
        raise DataError(path, "dataset.expected_frames", f"expected a table of split = frame count, got {expected!r}")


def stated_count_warnings(dataset: DatasetConfig, frame_splits) -> list[str]:
    """Lines for the splits whose selected frame count (``frame_splits``: the split of every selected frame)
    differs from ``dataset.expected_frames``; only a DexYCB read of the setting's rules that requires complete
    subjects (the full dataset) is compared, since any other read (a subset, a frame list) differs by design."""
    from collections import Counter

    from hoidata.datasets.dexycb_selection import count_warnings

    if dataset.name != "dexycb" or not dataset.complete_subjects or not dataset.expected_frames or dataset.frame_list:
        return []
    return count_warnings(dataset.expected_frames, dict(Counter(frame_splits)), dataset.setting, "its pipeline TOML")
