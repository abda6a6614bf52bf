"""The records floor: what every recipe that writes or reads records borrows.

:mod:`~hoidata.records.settings` (the ``[dataset]`` ``[record]`` ``[store]`` sections of ``pipelines/<name>.toml``),
:mod:`~hoidata.records.records` (one frame -> one record), :mod:`~hoidata.records.upstream` (upstream HOISDF's crops
and frame regions), :mod:`~hoidata.records.worker` (a process's MANO layers, objects and renderers; one shard of
records), :mod:`~hoidata.records.store_writer` (build.json, which shards are done, the skips files and the index),
:mod:`~hoidata.records.fingerprint` (the inputs a resumed build must find unchanged) and
:mod:`~hoidata.records.inputs` (readable checks of the MANO files and object folders a build reads)."""

from hoidata.records import fingerprint
from hoidata.records.fingerprint import build_inputs
from hoidata.records.records import (
    ObjectAsset,
    RecordSettings,
    build_eval_record,
    build_record,
    frame_seed,
    mirror_frame,
    posed_hand,
    posed_object,
)
from hoidata.records.settings import (
    BUILD_SECTIONS,
    BuildConfig,
    DatasetConfig,
    StoreConfig,
    load_build_config,
    stated_count_warnings,
)
from hoidata.records.store_writer import (
    StoreTask,
    StoreWriter,
    describe_skips,
    extra_name,
    read_shard_skips,
    skip_dict,
    skip_groups,
)
from hoidata.records.upstream import CropPolicy
from hoidata.records.worker import RecordWorker, RecordWorkerSpec, ShardJob, load_object_asset

__all__ = ["BUILD_SECTIONS", "BuildConfig", "CropPolicy", "DatasetConfig", "ObjectAsset", "RecordSettings",
           "RecordWorker", "RecordWorkerSpec", "ShardJob", "StoreConfig", "StoreTask", "StoreWriter",
           "build_eval_record", "build_inputs", "build_record", "describe_skips", "extra_name", "fingerprint",
           "frame_seed", "load_build_config", "load_object_asset", "mirror_frame", "posed_hand", "posed_object",
           "read_shard_skips", "skip_dict", "skip_groups", "stated_count_warnings"]
