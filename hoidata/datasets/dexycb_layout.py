"""DexYCB's on-disk layout: subjects, serials, the toolkit's setups s0-s3, and readers of its files.

Layout (docs/conventions.md, "The datasets on disk", DexYCB): ``ROOT/<subject>/<sequence>/{meta.yml, <serial>/...}``
with ``labels_%06d.npz`` and ``color_%06d.jpg`` per camera and frame, ``ROOT/calibration/`` for
intrinsics and MANO betas, ``ROOT/models/<ycb name>/textured_simple.obj``. Every reader checks what it
reads and raises :class:`~hoidata.errors.DataError` naming the file and the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.objects import YCB_CLASSES
from hoidata.reading import npz_array, npz_header, open_npz, read_yaml
from hoidata.shapes import numbers

SUBJECTS = [
    "20200709-subject-01", "20200813-subject-02", "20200820-subject-03", "20200903-subject-04",
    "20200908-subject-05", "20200918-subject-06", "20200928-subject-07", "20201002-subject-08",
    "20201015-subject-09", "20201022-subject-10",
]


SERIALS = ["836212060125", "839512060362", "840412060917", "841412060263",
           "932122060857", "932122060861", "932122061900", "932122062010"]


IMAGE_SIZE = (640, 480)


SEQUENCES_PER_SUBJECT = 100


SPLITS = ("train", "val", "test")


def split_members(setup: str, split: str) -> tuple[list[int], list[int], callable]:
    """Subjects, serials and a sequence-index predicate of a toolkit setup (``dex_ycb.py``).

    Returns (subject indices into SUBJECTS, serial indices into SERIALS, f(sequence index) -> bool).
    """
    if split not in SPLITS:
        raise ValueError(f"unknown DexYCB split {split!r}; expected one of {SPLITS}")
    all_subj, all_cam = list(range(10)), list(range(8))
    every = lambda i: True  # noqa: E731
    table = {
        "s0": {"train": (all_subj, all_cam, lambda i: i % 5 != 4),
               "val": ([0, 1], all_cam, lambda i: i % 5 == 4),
               "test": (list(range(2, 10)), all_cam, lambda i: i % 5 == 4)},
        "s1": {"train": ([0, 1, 2, 3, 4, 5, 9], all_cam, every), "val": ([6], all_cam, every),
               "test": ([7, 8], all_cam, every)},
        "s2": {"train": (all_subj, [0, 1, 2, 3, 4, 5], every), "val": (all_subj, [6], every),
               "test": (all_subj, [7], every)},
        "s3": {"train": (all_subj, all_cam, lambda i: i // 5 not in (3, 7, 11, 15, 19)),
               "val": (all_subj, all_cam, lambda i: i // 5 in (3, 19)),
               "test": (all_subj, all_cam, lambda i: i // 5 in (7, 11, 15))},
    }
    if setup not in table:
        raise ValueError(f"unknown DexYCB setup {setup!r}; expected one of {sorted(table)}")
    return table[setup][split]


@dataclass(frozen=True)
class ToolkitSplit:
    """The dex-ycb-toolkit's sample enumeration of one split (``DexYCBDataset.__init__``, e.g. ``s0_train``).

    The toolkit numbers the samples of a split sequence by sequence (subjects in order, each subject's sorted
    sequence folders at the split's positions), then camera (the split's serials, in ``SERIALS`` order), then
    frame: ``index = first[sequence] + c * num_frames + f``. Every selected camera and frame counts, whether
    or not a reader later keeps it, so these are the ids of result files and published frame lists.
    """

    name: str  # '<setup>_<split>', the toolkit's get_dataset name
    serials: tuple[str, ...]  # the split's cameras, toolkit order
    first: dict  # '<subject>/<sequence folder>' -> (index of its first sample, num_frames)
    size: int  # len(get_dataset(name))

    def sample_index(self, subject: str, sequence: str, serial: str, frame: int) -> int:
        """The toolkit's index of one sample; ValueError if the sequence, camera or frame is not in the split."""
        start, frames = self.first.get(f"{subject}/{sequence}", (None, 0))
        if start is None or serial not in self.serials or not 0 <= frame < frames:
            raise ValueError(f"{subject}/{sequence}/{serial} frame {frame} is not a sample of {self.name}")
        return start + self.serials.index(serial) * frames + frame


def toolkit_split(root: Path, setup: str, split: str) -> ToolkitSplit:
    """Enumerate a split as the toolkit does, from each selected sequence's ``meta.yml`` (``num_frames``).

    A subject folder that is missing adds nothing (the toolkit would stop; the reader's
    ``complete_subjects`` check reports it). Raises DataError naming an unreadable ``meta.yml``: every
    later id depends on it.
    """
    subjects, cams, keep = split_members(setup, split)
    first, total = {}, 0
    for s in subjects:
        for i, seq_dir in enumerate(list_sequences(Path(root), SUBJECTS[s])):
            if not keep(i):
                continue
            path = seq_dir / "meta.yml"
            frames = _read_yaml(path, ("num_frames",))["num_frames"]
            if not isinstance(frames, int) or isinstance(frames, bool) or frames < 0:
                raise DataError(path, "num_frames", f"expected a non-negative integer, got {frames!r}")
            first[f"{SUBJECTS[s]}/{seq_dir.name}"] = (total, frames)
            total += len(cams) * frames
    return ToolkitSplit(f"{setup}_{split}", tuple(SERIALS[c] for c in cams), first, total)


def _read_yaml(path: Path, required: tuple[str, ...]) -> dict:
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise DataError(path, None, "expected a YAML mapping")
    for key in required:
        if key not in data:
            raise DataError(path, key, "missing key")
    return data


def read_meta(seq_dir: Path) -> dict:
    """A sequence's meta.yml, checked for the keys the reader uses."""
    keys = ("serials", "num_frames", "ycb_ids", "ycb_grasp_ind", "mano_sides", "mano_calib")
    path = seq_dir / "meta.yml"
    meta = _read_yaml(path, keys)
    for key in ("serials", "ycb_ids", "mano_sides", "mano_calib"):
        if not isinstance(meta[key], list) or not meta[key]:
            raise DataError(path, key, f"expected a non-empty list, got {meta[key]!r}")
    for key in ("num_frames", "ycb_grasp_ind"):
        if not isinstance(meta[key], int) or isinstance(meta[key], bool):
            raise DataError(path, key, f"expected an integer, got {meta[key]!r}")
    if not all(isinstance(c, int) for c in meta["ycb_ids"]):
        raise DataError(path, "ycb_ids", f"expected integer class ids, got {meta['ycb_ids']!r}")
    if not 0 <= meta["ycb_grasp_ind"] < len(meta["ycb_ids"]):
        raise DataError(path, "ycb_grasp_ind", f"{meta['ycb_grasp_ind']} is not an index into ycb_ids")
    if meta["mano_sides"][0] not in ("right", "left"):
        raise DataError(path, "mano_sides", f"expected 'right' or 'left', got {meta['mano_sides'][0]!r}")
    return meta


def read_intrinsics(root: Path, serial: str) -> np.ndarray:
    """K (3, 3) of a camera from ``calibration/intrinsics/<serial>_640x480.yml`` (key ``color``)."""
    path = root / "calibration" / "intrinsics" / f"{serial}_{IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}.yml"
    color = _read_yaml(path, ("color",))["color"]
    try:
        fx, fy, cx, cy = numbers([color[k] for k in ("fx", "fy", "ppx", "ppy")], path, "color", (4,))
    except (KeyError, TypeError) as e:
        raise DataError(path, "color", f"expected fx, fy, ppx, ppy: {e}") from e
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def read_betas(root: Path, calib: str) -> np.ndarray:
    """MANO betas (10,) of a subject and side from ``calibration/mano_<calib>/mano.yml``."""
    path = root / "calibration" / f"mano_{calib}" / "mano.yml"
    return numbers(_read_yaml(path, ("betas",))["betas"], path, "betas", (10,))


LABEL_SHAPES = {"seg": (480, 640), "pose_m": (1, 51), "joint_3d": (1, 21, 3), "joint_2d": (1, 21, 2)}


def read_labels(path: Path, num_objects: int, keys=None, check_rest: bool = True) -> dict[str, np.ndarray]:
    """A ``labels_%06d.npz`` with its keys and shapes checked (DataError naming file and key).

    ``keys``: decode only these members; every expected key must still be present, and (``check_rest``) the shape
    and dtype of the others are checked from their ``.npy`` headers (a few bytes, not the 300 kB ``seg`` image the
    frame readers need not decode). None: decode all of them."""
    expected = dict(LABEL_SHAPES, pose_y=(num_objects, 3, 4))
    with open_npz(path, "npz labels file") as npz:  # not found, cut short, not an npz: one line naming it
        names = set(npz.files)
        missing = [k for k in expected if k not in names]
        if missing:
            raise DataError(path, missing[0], "missing key")
        labels = {k: npz_array(npz, k, path) for k in (npz.files if keys is None else [k for k in keys if k in names])}
        found = {k: (v.shape, v.dtype) for k, v in labels.items()}
        if check_rest:
            found.update({k: npz_header(npz, k, path) for k in expected if k not in labels})
    for key, shape in expected.items():
        if key not in found:
            continue
        if found[key][0] != shape:
            raise DataError(path, key, f"expected shape {shape}, got {found[key][0]}")
        if found[key][1].kind not in "iuf":  # numbers, never booleans or strings
            raise DataError(path, key, f"expected numbers, got dtype {found[key][1]}")
    return labels


def list_sequences(root: Path, subject: str) -> list[Path]:
    """A subject's sequence folders, sorted: the toolkit's sequence index is the position here."""
    subj_dir = root / subject
    if not subj_dir.is_dir():
        return []
    return sorted(p for p in subj_dir.iterdir() if p.is_dir())


def object_name(class_id: int, path: Path) -> str:
    if int(class_id) not in YCB_CLASSES:
        raise DataError(path, "ycb_ids", f"unknown YCB class id {class_id}")
    return YCB_CLASSES[int(class_id)]


def label_path(seq_dir: Path, serial: str, frame: int) -> Path:
    return seq_dir / serial / f"labels_{frame:06d}.npz"


def color_path(seq_dir: Path, serial: str, frame: int) -> Path:
    return seq_dir / serial / f"color_{frame:06d}.jpg"
