"""The one way every pipeline opens a dataset: a reader by name, and the frames of several splits.

``build-sdf``, ``export``, ``render-synthetic``'s grasp source and ``make-toy``'s summary all read datasets
through :func:`open_reader` (one split) or :func:`read_splits` (the splits of a build, with a published frame
list's check), so they cannot drift apart: the DexYCB proximity filter reads the same models folder as the
stage that samples SDFs and renders masks, because both take it from the caller's one ``models_dir``.
Parameters are plain values (a dataset name, folders, a :class:`DexYCBSetting`), never a config object.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from hoidata.datasets.frame import Frame, Skip
from hoidata.errors import DataError

DATASETS = ("dexycb", "ho3d", "hot3d_clips")  # the readers open_reader knows, by the name a pipeline's dataset.name gives


def open_reader(dataset: str, root, mano_dir, split: str, *, models_dir=None, dexycb=None, version: str = "v2",
                frame_ids=None, on_error: str = "skip"):
    """A reader of one split: a DexYCBReader, an HO3DReader or a HOT3DClipsReader (iterate ``frames()``, then read
    ``skipped``).

    Args:
        dataset: 'dexycb' | 'ho3d' | 'hot3d_clips' (a pipeline's ``dataset.name``); anything else is a DataError
            naming ``dataset.name``.
        root: the dataset folder.
        mano_dir: folder with MANO_RIGHT.pkl / MANO_LEFT.pkl (pose bases, HO-3D's rest wrist, the proximity filter).
        split: the split's name ('train' | 'val' | 'test' for DexYCB; 'train' | 'evaluation' for HO-3D; 'train' |
            'val' for HOT3D-Clips).
        models_dir: the YCB models folder the DexYCB proximity filter reads; None means ``root/models``. Give
            the folder the SDF and mask stage uses (a command's ``--models``).
        dexycb: DexYCB only: the :class:`~hoidata.datasets.dexycb.DexYCBSetting` (None: the ``dexycb`` preset).
        version: HO-3D only: 'v2' | 'v3'.
        frame_ids: DexYCB only: read exactly these toolkit sample ids (a published frame list).
        on_error: 'skip' records malformed files in ``reader.skipped``; 'raise' stops at the first one.
    """
    if dataset == "dexycb":
        from hoidata.datasets.dexycb import SETTINGS, DexYCBReader

        return DexYCBReader(root, mano_dir, split, SETTINGS["dexycb"] if dexycb is None else dexycb, models_dir,
                            on_error=on_error, frame_ids=None if frame_ids is None else frozenset(frame_ids))
    if dataset == "ho3d":
        if frame_ids is not None:  # HO-3D has no published id lists; the ids would silently be ignored
            raise DataError(None, "dataset.frame_list", "frame lists hold DexYCB toolkit ids; HO-3D has none")
        from hoidata.datasets.ho3d import HO3DReader

        return HO3DReader(root, mano_dir, split, on_error=on_error, version=version)
    if dataset == "hot3d_clips":
        if frame_ids is not None:
            raise DataError(None, "dataset.frame_list", "frame lists hold DexYCB toolkit ids; HOT3D-Clips has none")
        from hoidata.datasets.hot3d import HOT3DClipsReader

        return HOT3DClipsReader(root, mano_dir, split, on_error=on_error)
    raise DataError(None, "dataset.name", f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")


@dataclass
class SplitFrames:
    """What :func:`read_splits` read: frames in reader order (split by split), the readers' skips, and per frame
    its id in the split's published enumeration (``ids``: DexYCB's toolkit sample index, the result-file and
    frame-list id; HO-3D's line in ``<split>.txt``; the image ids of exported annotation files)."""

    frames: list[Frame] = field(default_factory=list)
    skips: list[Skip] = field(default_factory=list)
    ids: list[int] = field(default_factory=list)


def read_splits(dataset: str, root, mano_dir, splits, *, models_dir=None, dexycb=None, version: str = "v2",
                frame_list: str | Path = "", on_error: str = "skip") -> SplitFrames:
    """All frames of ``splits`` (in that order, each in reader order) through :func:`open_reader`.

    ``frame_list``: a published DexYCB frame list (:mod:`hoidata.datasets.frame_list`; "" for none). It holds
    the ids of one split, so it takes exactly one; every listed id must then be read or skipped with a reason
    (:func:`~hoidata.datasets.frame_list.check_listed`), else a DataError names the file and the ids. Frames
    without hand labels (HO-3D's evaluation split) are kept. The other parameters are :func:`open_reader`'s.
    """
    from hoidata.datasets.frame_list import check_listed, read_frame_list

    splits = tuple(splits)
    if len(set(splits)) != len(splits):  # each frame is read once: a repeated split would give duplicate records
        raise DataError(root, "dataset.splits", f"names a split more than once: {list(splits)}")
    if frame_list and len(splits) != 1:
        raise DataError(frame_list, "dataset.frame_list", f"a frame list holds the ids of one split, not {splits}")
    listed = read_frame_list(frame_list) if frame_list else None
    out = SplitFrames()
    for split in splits:
        reader = open_reader(dataset, root, mano_dir, split, models_dir=models_dir, dexycb=dexycb, version=version,
                             frame_ids=listed, on_error=on_error)
        got = list(reader.frames())
        if listed is not None:  # every listed id must be a frame of the dataset
            check_listed(frame_list, listed, got, reader.skipped, reader.toolkit)
        out.frames += got
        out.skips += reader.skipped
        out.ids += reader.published_ids(got)
    return out
