"""Build settings: the ``[dataset]``, ``[record]`` and ``[store]`` sections of ``pipelines/<name>.toml`` -> typed
dataclasses, with ``section.key=value`` overrides.

Reading the file, the overrides and the per-key checks are :mod:`hoidata.sections` (shared with training); this
module holds the build's dataclasses and the checks across their keys. The resolved config is saved in every
store's index. Nothing else reads TOML: the pipeline gets these dataclasses and passes explicit values on.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import ClassVar

from hoidata.datasets.dexycb import DexYCBSetting
from hoidata.errors import DataError
from hoidata.geometry.sdf import BACKENDS as SDF_BACKENDS
from hoidata.records.records import RecordSettings
from hoidata.sections import (
    check_sections,
    origin,
    read_pipeline,
    refuse_unused,
    resolve_pipeline,
    section,
    section_names,
    value_problem,
)


@dataclass(frozen=True)
class DatasetConfig:
    name: str = "dexycb"  # reader: 'dexycb' | 'ho3d' | 'hot3d_clips'
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


BUILD_SECTIONS = section_names(BuildConfig)  # ("dataset", "record", "store"): what the build reads of a file


def load_build_config(name_or_path: str, overrides: list[str] = ()) -> BuildConfig:
    """Read a pipeline TOML (a name in ``pipelines/`` or a path) and apply ``section.key=value`` overrides (values
    parsed as TOML); an override of a section the build does not read is an error (:mod:`hoidata.sections`)."""
    refuse_unused(list(overrides), BUILD_SECTIONS, "build-sdf", resolve_pipeline(name_or_path))
    path, data = read_pipeline(name_or_path, overrides)
    check_sections(data, path, BUILD_SECTIONS, None)  # the file's other sections are their readers' to check
    record = section(RecordSettings, data.get("record", {}), path, "record", overrides)
    dataset = section(DatasetConfig, data.get("dataset", {}), path, "dataset", overrides)
    if dataset.name not in ("dexycb", "ho3d", "hot3d_clips"):
        raise DataError(origin(path, overrides, "dataset.name"), "dataset.name",
                        f"unknown dataset {dataset.name!r}; expected 'dexycb', 'ho3d' or 'hot3d_clips'")
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
    _check_supervision(record, dataset, path, overrides)
    return BuildConfig(dataset,
                       replace(record, sigmas=tuple(record.sigmas), upstream_region=tuple(record.upstream_region)),
                       section(StoreConfig, data.get("store", {}), path, "store", overrides))


def _check_crop(record: RecordSettings, dataset: DatasetConfig, path: Path) -> None:
    """record.crop names a crop; upstream's HO-3D test crop exists for its evaluation split only (its training
    split has no upstream test crop to reproduce)."""
    from hoidata.records.upstream import CROPS

    if record.crop not in CROPS:
        raise DataError(path, "record.crop", f"expected one of {CROPS}, got {record.crop!r}")
    odd = sorted(set(record.crop_splits) & set(dataset.splits) - {"evaluation"})
    if record.crop == "upstream" and dataset.name == "ho3d" and odd:
        raise DataError(path, "record.crop_splits", f"upstream's HO-3D test crop exists for the evaluation split "
                                                    f"only, not for {odd}")
    if record.upstream_region and dataset.name not in ("dexycb", "ho3d"):
        raise DataError(path, "record.upstream_region", f"upstream's training augmentation exists for DexYCB and "
                                                        f"HO-3D, not {dataset.name}")
    both = sorted(set(record.upstream_region) & set(record.crop_splits)) if record.crop == "upstream" else []
    if both:
        raise DataError(path, "record.upstream_region", f"splits {both} are upstream test crops (record.crop_splits); "
                                                        f"a record keeps one or the other")


SDF_POINTS = ("project", "deepsdf")  # record.sdf_points: the project's sets | the authors' AlignSDF/DeepSDF blocks
MASK_SOURCES = ("rendered", "dataset")  # record.masks: rendered from the meshes | the dataset's own masks


def _check_supervision(record: RecordSettings, dataset: DatasetConfig, path: Path, overrides) -> None:
    """record.sdf_points and record.masks name a choice; HOT3D-Clips has no hand masks to take as targets."""
    if record.sdf_points not in SDF_POINTS:
        raise DataError(origin(path, overrides, "record.sdf_points"), "record.sdf_points",
                        f"expected one of {SDF_POINTS}, got {record.sdf_points!r}")
    if record.masks not in MASK_SOURCES:
        raise DataError(origin(path, overrides, "record.masks"), "record.masks",
                        f"expected one of {MASK_SOURCES}, got {record.masks!r}")
    if record.masks == "dataset" and dataset.name == "hot3d_clips":
        raise DataError(origin(path, overrides, "record.masks", "dataset.name"), "record.masks", 'HOT3D-Clips has no hand masks (its own are amodal object masks): '
                                              'use record.masks = "rendered"')


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
