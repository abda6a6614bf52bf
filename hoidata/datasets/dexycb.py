"""DexYCB reader: the toolkit's layout, setups s0-s3, and the settings the papers train on.

Layout (``reference/datasets.md`` section 1): ``ROOT/<subject>/<sequence>/{meta.yml, <serial>/...}``
with ``labels_%06d.npz`` and ``color_%06d.jpg`` per camera and frame, ``ROOT/calibration/`` for
intrinsics and MANO betas, ``ROOT/models/<ycb name>/textured_simple.obj``.

Samples are ordered as in the toolkit: sequence, then camera, then frame. A sequence's index (which
decides its split) is its position among the subject's sorted sequence folders, exactly as the
toolkit computes it; the real dataset has 100 per subject.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import yaml

from hoidata.datasets.frame import Frame, Skip, box_from_points
from hoidata.errors import DataError
from hoidata.objects import YCB_CLASSES

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
class DexYCBSetting:
    """Which frames a setting keeps. Every field is recorded in the store's index.

    ``dexycb`` (the HOISDF/gSDF subset): s0, right hands, every 5th frame, hand within 5 mm of the
    grasped object. ``dexycb_full``: s0, both hands, every frame, left hands marked for mirroring.
    """

    name: str = "dexycb"
    setup: str = "s0"
    sides: tuple[str, ...] = ("right",)
    frame_stride: int = 5
    proximity_mm: float | None = 5.0  # keep a frame only if some object vertex is this close to the hand
    proximity_splits: tuple[str, ...] = ("train", "val", "test")
    mirror_left: bool = False
    # The toolkit indexes sequences by position and asserts 100 per subject: with a partial download,
    # sequences would silently change split. False accepts any count (toy data, deliberate subsets).
    complete_subjects: bool = True
    # DexYCB's labels were fitted with manopth's MANO_LEFT as shipped, without the shapedirs fix
    # (dex-ycb-toolkit#28): reproducing its joints and meshes needs the unfixed left model.
    fix_left_shapedirs: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


SETTINGS = {
    "dexycb": DexYCBSetting(),
    "dexycb_full": DexYCBSetting(name="dexycb_full", sides=("right", "left"), frame_stride=1,
                                 proximity_mm=None, mirror_left=True),
}


def _read_yaml(path: Path, required: tuple[str, ...]) -> dict:
    if not path.is_file():
        raise DataError(path, None, "file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise DataError(path, None, f"not valid YAML: {e}") from e
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
        fx, fy, cx, cy = (float(color[k]) for k in ("fx", "fy", "ppx", "ppy"))
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(path, "color", f"expected fx, fy, ppx, ppy: {e}") from e
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def read_betas(root: Path, calib: str) -> np.ndarray:
    """MANO betas (10,) of a subject and side from ``calibration/mano_<calib>/mano.yml``."""
    path = root / "calibration" / f"mano_{calib}" / "mano.yml"
    betas = np.asarray(_read_yaml(path, ("betas",))["betas"], dtype=np.float64)
    if betas.shape != (10,):
        raise DataError(path, "betas", f"expected 10 values, got shape {betas.shape}")
    return betas


LABEL_SHAPES = {"seg": (480, 640), "pose_m": (1, 51), "joint_3d": (1, 21, 3), "joint_2d": (1, 21, 2)}


def read_labels(path: Path, num_objects: int) -> dict[str, np.ndarray]:
    """A ``labels_%06d.npz`` with its keys and shapes checked (DataError naming file and key)."""
    if not path.is_file():
        raise DataError(path, None, "labels file not found")
    try:
        with np.load(path, allow_pickle=False) as npz:
            labels = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise DataError(path, None, f"cannot read npz (corrupt?): {e}") from e
    expected = dict(LABEL_SHAPES, pose_y=(num_objects, 3, 4))
    for key, shape in expected.items():
        if key not in labels:
            raise DataError(path, key, "missing key")
        if labels[key].shape != shape:
            raise DataError(path, key, f"expected shape {shape}, got {labels[key].shape}")
    return labels


def list_sequences(root: Path, subject: str) -> list[Path]:
    """A subject's sequence folders, sorted: the toolkit's sequence index is the position here."""
    subj_dir = root / subject
    if not subj_dir.is_dir():
        return []
    return sorted(p for p in subj_dir.iterdir() if p.is_dir())


@dataclass
class DexYCBReader:
    """Frames of one split of a DexYCB setting. Iterate with :meth:`frames`; skips land in ``skipped``.

    Args:
        root: the DexYCB folder (subjects, ``calibration/``, ``models/``).
        mano_dir: folder with MANO_RIGHT.pkl / MANO_LEFT.pkl (PCA bases, proximity filter).
        split: 'train' | 'val' | 'test'.
        setting: a :class:`DexYCBSetting` (see SETTINGS).
        models_dir: YCB models folder, default ``root/models`` (proximity filter only).
        on_error: 'raise' stops at the first malformed file; 'skip' records it in ``skipped``.
    """

    root: Path
    mano_dir: Path
    split: str
    setting: DexYCBSetting = SETTINGS["dexycb"]
    models_dir: Path | None = None
    on_error: str = "raise"
    skipped: list[Skip] = field(default_factory=list)

    def __post_init__(self):
        self.root, self.mano_dir = Path(self.root), Path(self.mano_dir)
        self.models_dir = Path(self.models_dir) if self.models_dir else self.root / "models"
        if not self.root.is_dir():
            raise DataError(self.root, None, "DexYCB root folder not found")
        self._subjects, self._serials, self._keep_seq = split_members(self.setting.setup, self.split)
        self._mano, self._objects = {}, {}

    def sequences(self) -> Iterator[tuple[int, int, Path]]:
        """(subject index, sequence index, folder) of every sequence in the split."""
        for s in self._subjects:
            sequences = list_sequences(self.root, SUBJECTS[s])
            if self.setting.complete_subjects and len(sequences) != SEQUENCES_PER_SUBJECT:
                raise DataError(self.root / SUBJECTS[s], None,
                                f"{len(sequences)} sequence folders, expected {SEQUENCES_PER_SUBJECT}: splits index "
                                "sequences by position, so a partial download would move sequences between splits "
                                "(set complete_subjects = false to read a subset anyway)")
            for i, seq_dir in enumerate(sequences):
                if self._keep_seq(i):
                    yield s, i, seq_dir

    def frames(self) -> Iterator[Frame]:
        from hoidata.datasets.dexycb_frames import sequence_frames

        for s, i, seq_dir in self.sequences():
            try:
                meta = read_meta(seq_dir)
            except DataError as e:
                self._fail(e, f"{SUBJECTS[s]}_{seq_dir.name}")
                continue
            yield from sequence_frames(self, s, i, seq_dir, meta)

    def _fail(self, error: DataError, frame_id: str) -> None:
        if self.on_error == "raise":
            raise error
        self.skipped.append(Skip(frame_id, str(error), error.path or ""))

    def mano(self, side: str):
        if side not in self._mano:
            import torch

            from hoidata.hand import load_mano

            fix = self.setting.fix_left_shapedirs or side == "right"
            self._mano[side] = load_mano(self.mano_dir, side=side, fix_left_shapedirs=fix, dtype=torch.float64)
        return self._mano[side]

    def object_vertices(self, name: str) -> np.ndarray:
        if name not in self._objects:
            from hoidata.objects import load_object_mesh, object_mesh_path

            self._objects[name] = np.asarray(load_object_mesh(object_mesh_path(self.models_dir, name)).vertices)
        return self._objects[name]


def object_name(class_id: int, path: Path) -> str:
    if int(class_id) not in YCB_CLASSES:
        raise DataError(path, "ycb_ids", f"unknown YCB class id {class_id}")
    return YCB_CLASSES[int(class_id)]


def hand_box_valid(joints_2d: np.ndarray, size=IMAGE_SIZE, expand: float = 1.5) -> bool:
    """The ``dexycb_full`` validity rule: the 1.5x box of the 2D joints has area and meets the image."""
    x1, y1, x2, y2 = box_from_points(joints_2d)
    w, h = (x2 - x1) * expand, (y2 - y1) * expand
    cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
    return bool(w > 1 and h > 1 and cx + w / 2 > 0 and cy + h / 2 > 0 and cx - w / 2 < size[0] and cy - h / 2 < size[1])


def label_path(seq_dir: Path, serial: str, frame: int) -> Path:
    return seq_dir / serial / f"labels_{frame:06d}.npz"


def color_path(seq_dir: Path, serial: str, frame: int) -> Path:
    return seq_dir / serial / f"color_{frame:06d}.jpg"


__all__ = ["SUBJECTS", "SERIALS", "SETTINGS", "DexYCBSetting", "DexYCBReader", "split_members",
           "read_meta", "read_intrinsics", "read_betas", "read_labels", "list_sequences", "IMAGE_SIZE"]
