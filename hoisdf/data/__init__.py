"""Data for training and evaluation: :mod:`hoisdf.data.loader` streams ``hoidata`` stores into batches,
:mod:`hoisdf.data.augment` turns a loader batch into the network's input on the batch's device."""

from hoisdf.data.loader import (
    MixedStores,
    StoreSpec,
    build_dataset,
    collate,
    make_loader,
    sample_sdf,
)

__all__ = ["MixedStores", "StoreSpec", "build_dataset", "collate", "make_loader", "sample_sdf"]
