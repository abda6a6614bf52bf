"""DexYCB reader: the toolkit's layout, setups s0-s3, and the settings the papers train on.

Layout (docs/conventions.md, "The datasets on disk", DexYCB): ``ROOT/<subject>/<sequence>/{meta.yml, <serial>/...}``
with ``labels_%06d.npz`` and ``color_%06d.jpg`` per camera and frame, ``ROOT/calibration/`` for
intrinsics and MANO betas, ``ROOT/models/<ycb name>/textured_simple.obj``.

Samples are ordered as in the toolkit: sequence, then camera, then frame. A sequence's index (which
decides its split) is its position among the subject's sorted sequence folders, exactly as the
toolkit computes it; the real dataset has 100 per subject.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from hoidata.datasets.dexycb_frames import sequence_frames
from hoidata.datasets.dexycb_layout import (
    SEQUENCES_PER_SUBJECT,
    SUBJECTS,
    ToolkitSplit,
    list_sequences,
    read_meta,
    split_members,
    toolkit_split,
)
from hoidata.datasets.frame import Frame, Skip
from hoidata.errors import DataError


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
    proximity_to: str = "hand_vertices"  # the MANO vertices (gSDF) or 'hand_joints', the 21 labels (ArtiBoost)
    # the HandOccNet/HOISDF hand box rule (dexycb_selection.hand_box_ok) applies in these splits
    box_splits: tuple[str, ...] = ()
    # keep a frame only if the grasped object turned more than motion_deg or moved more than motion_m since the
    # camera's frame 0 (UniHOPE's grasping label); None: no motion rule
    motion_deg: float | None = None
    motion_m: float | None = None
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
                                 proximity_mm=None, mirror_left=True, box_splits=("train", "val", "test")),
}


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
        frame_ids: read exactly these toolkit sample ids (a published frame list,
            :mod:`hoidata.datasets.frame_list`) instead of the setting's sides, frame stride and proximity rules;
            listed left hands are mirrored.

    Every frame carries ``sample_index``, its index in the toolkit's enumeration of the split
    (:class:`~hoidata.datasets.dexycb_layout.ToolkitSplit`, in ``toolkit`` after :meth:`frames` started);
    frames this setting leaves out still count. If a ``meta.yml`` cannot be read the ids are unknown:
    ``toolkit`` is None and every frame gets -1 (in 'skip' mode; 'raise' stops).
    """

    root: Path
    mano_dir: Path
    split: str
    setting: DexYCBSetting = SETTINGS["dexycb"]
    models_dir: Path | None = None
    on_error: str = "raise"
    skipped: list[Skip] = field(default_factory=list)
    frame_ids: frozenset[int] | None = None
    toolkit: ToolkitSplit | None = field(default=None, init=False)

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
        try:
            self.toolkit = toolkit_split(self.root, self.setting.setup, self.split)
        except DataError as e:
            if self.frame_ids is not None:  # a frame list cannot be resolved without the ids
                raise
            self._fail(DataError(e.path, e.field, f"{e.problem}; the toolkit's sample ids are unknown"), "toolkit ids")
        for s, i, seq_dir in self.sequences():
            try:
                meta = read_meta(seq_dir)
            except DataError as e:
                self._fail(e, f"{SUBJECTS[s]}_{seq_dir.name}")
                continue
            yield from sequence_frames(self, s, i, seq_dir, meta)

    def published_ids(self, frames) -> list[int]:
        """Each of ``frames``' (this reader's) toolkit sample index: the id of result files and frame lists."""
        return [f.sample_index for f in frames]

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

