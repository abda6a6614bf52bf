"""``hoidata make-toy``: the procedural hand, objects and toy datasets in the real layouts, in one call."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

LAYOUTS = ("dexycb", "ho3d", "ho3d_v3", "hot3d", "arctic")  # ho3d_v3: HO-3D v3's layout (hoidata/toy/ho3d.py); hot3d:
# clips; arctic: arctic_data/data (hoidata/toy/arctic.py)
# the toolkit's i % 5 == 4 rule puts a subject's 5th sequence in val or test: with fewer, s0/s1 val and test are empty
DEXYCB_SPLIT_SEQUENCES = 5
HOT3D_MAX_CLIPS = 90  # toy HOT3D clips: 1, 2 (train), 10 (val), then 3, 4, ... (multiples of 10 val; toy_clips)
HO3D_MAX_SEQUENCES = 3  # the toy HO-3D's training sequences: BB10, MC1, SM2 (hoidata/toy/ho3d.py, TRAIN_SEQUENCES)


def check_chain_size(sequences: int | None) -> None:
    """``hoidata toy-pipeline`` builds the toy DexYCB's train and test stores: a size that leaves its test split empty
    is refused before anything is written, naming the minimum (``None``: make-toy's default size, which works)."""
    if sequences is not None and sequences < DEXYCB_SPLIT_SEQUENCES:
        raise ValueError(f"--sequences {sequences}: the toy chain builds a train and a test store, and the toolkit "
                         f"puts a subject's 5th sequence in val or test, so fewer than {DEXYCB_SPLIT_SEQUENCES} leave "
                         f"the test split empty; give --sequences {DEXYCB_SPLIT_SEQUENCES} or more "
                         "(nothing was written)")


def empty_split_notes(rows: list[dict], layout: str, sequences: int | None) -> list[str]:
    """``note:`` lines for the splits of :func:`split_rows` that came out without frames at this size, naming the
    size that fills them, so a later ``build-sdf`` of such a split stopping with "no frames" is no surprise."""
    empty = [f"{r['setting']} {r['split']}" for r in rows if r["frames"] == 0]
    if not empty:
        return []
    why = (f": the toolkit puts a subject's 5th sequence in val or test, give --sequences {DEXYCB_SPLIT_SEQUENCES} "
           "or more" if layout == "dexycb" and sequences is not None and sequences < DEXYCB_SPLIT_SEQUENCES else
           ": make-toy's default size fills every split")
    return [f"note: no frames in {', '.join(empty)} at this size{why}"]


def write_assets(out: Path) -> tuple[Path, Path]:
    """Procedural MANO files in ``out/mano`` and YCB-layout objects in ``out/models``."""
    from hoidata.toy.hand import write_toy_mano
    from hoidata.toy.objects import write_toy_objects

    write_toy_mano(out / "mano")
    write_toy_objects(out / "models")
    return out / "mano", out / "models"


def make_toy(out: str | Path, layout: str, sequences: int | None = None, frames: int | None = None,
             seed: int = 0, progress: bool = True) -> dict:
    """Write a toy dataset in `layout` ('dexycb', 'ho3d', 'ho3d_v3', 'hot3d' or 'arctic') under `out`, with
    ``out/mano`` and ``out/models`` (ARCTIC: ``out/mano`` and its own object templates under ``out/meta``).

    `sequences` (per subject for DexYCB, training sequences for HO-3D, clips for HOT3D: the default's 1..3, then
    more, :func:`hoidata.toy.hot3d.toy_clips`; per subject for ARCTIC) and `frames` (per sequence and camera; per
    clip; ARCTIC: per sequence, more than 50) scale it; None keeps the default size. Returns what was written and
    how long it took.
    """
    from hoidata.toy.dexycb import ToyDexYCBSize, write_toy_dexycb
    from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d

    if layout not in LAYOUTS:
        raise ValueError(f"unknown toy layout {layout!r}; expected one of {LAYOUTS}")
    for name, value in (("sequences", sequences), ("frames", frames)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a whole number >= 1 (or None for the default size), got {value!r}")
    if layout in ("ho3d", "ho3d_v3") and sequences is not None and sequences > HO3D_MAX_SEQUENCES:
        raise ValueError(f"--sequences {sequences}: the toy HO-3D has {HO3D_MAX_SEQUENCES} training sequences (BB10, "
                         f"MC1, SM2); give 1 to {HO3D_MAX_SEQUENCES} (nothing was written)")
    if layout == "arctic" and frames is not None and frames <= 50:
        raise ValueError(f"--frames {frames}: ARCTIC's loader refuses sequences of 50 frames or fewer; give 51 or "
                         "more (nothing was written)")
    if layout == "hot3d" and sequences is not None and sequences > HOT3D_MAX_CLIPS:
        raise ValueError(f"--sequences {sequences}: the toy HOT3D-Clips writes 1 to {HOT3D_MAX_CLIPS} clips "
                         "(nothing was written)")
    out = Path(out)
    start = time.perf_counter()
    prepare_folder(out, {"layout": layout, "sequences": sequences, "frames": frames, "seed": seed})
    if layout == "arctic":  # ARCTIC's objects are its own templates (meta/object_vtemplates), not YCB models
        from hoidata.toy.arctic import ToyArcticSize, write_toy_arctic
        from hoidata.toy.hand import write_toy_mano

        write_toy_mano(out / "mano")
        size = ToyArcticSize()
        size = replace(size, sequences=sequences or size.sequences, frames=frames or size.frames)
        counts = write_toy_arctic(out, out / "mano", size, seed=seed, progress=progress)
        return {"layout": layout, "root": str(out), **counts, "seconds": round(time.perf_counter() - start, 1)}
    mano_dir, models_dir = write_assets(out)
    if layout == "hot3d":
        from hoidata.toy.hot3d import ToyHOT3DSize, toy_clips, write_toy_hot3d

        size = ToyHOT3DSize()
        size = replace(size, clips=toy_clips(sequences) if sequences else size.clips, frames=frames or size.frames)
        counts = write_toy_hot3d(out, mano_dir, models_dir, size, seed=seed, progress=progress)
    elif layout == "dexycb":
        size = ToyDexYCBSize()
        size = replace(size, sequences=sequences or size.sequences, frames=frames or size.frames)
        counts = write_toy_dexycb(out, mano_dir, models_dir, size, seed=seed, progress=progress)
    else:
        size = ToyHO3DSize()
        size = replace(size, train_sequences=sequences or size.train_sequences, frames=frames or size.frames)
        counts = write_toy_ho3d(out, mano_dir, models_dir, size, seed=seed, progress=progress,
                                version="v3" if layout == "ho3d_v3" else "v2")
    return {"layout": layout, "root": str(out), **counts, "seconds": round(time.perf_counter() - start, 1)}


MARKER = ".hoidata-toy.json"  # make-toy's mark on a folder it wrote (with the settings it wrote it with)


def prepare_folder(out: Path, settings: dict) -> None:
    """Make ``out`` ready for a fresh toy dataset: create it, or empty a folder make-toy wrote before (its
    marker file says so); any other non-empty folder is refused, so old and new files never mix."""
    import json
    import shutil

    from hoidata.errors import DataError

    if out.exists() and not out.is_dir():
        raise DataError(out, None, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not (out / MARKER).is_file():
            raise DataError(out, None, "the folder is not empty and was not written by make-toy: give an empty or "
                                       "new --out folder (nothing was changed)")
        for child in out.iterdir():  # an earlier toy dataset: replaced as a whole
            shutil.rmtree(child) if child.is_dir() and not child.is_symlink() else child.unlink()
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text(json.dumps(settings, sort_keys=True) + "\n")


def split_rows(root: str | Path, layout: str) -> list[dict]:
    """Frames and skips per split and setting, read back through the real readers."""
    from hoidata.datasets.dexycb import SETTINGS
    from hoidata.datasets.open import open_reader

    root, rows = Path(root), []
    if layout == "dexycb":
        for name, setting in SETTINGS.items():
            for split in ("train", "val", "test"):
                reader = open_reader("dexycb", root, root / "mano", split, on_error="raise",
                                     dexycb=replace(setting, complete_subjects=False))
                frames = list(reader.frames())
                rows.append({"setting": name, "split": split, "frames": len(frames),
                             "left_mirrored": sum(f.mirror for f in frames), "skipped": len(reader.skipped)})
    elif layout == "arctic":
        from hoidata.datasets.arctic_format import read_protocol, read_sequence

        for setup in ("p1", "p2"):
            for split, names in read_protocol(root, setup).items():
                frames = sum(read_sequence(root, *n.split("/")).frames for n in names)
                rows.append({"setting": f"arctic {setup}", "split": split, "sequences": len(names), "frames": frames})
    elif layout == "hot3d":
        for split in ("train", "val"):
            reader = open_reader("hot3d_clips", root, root / "mano", split, on_error="raise")
            frames = list(reader.frames())
            rows.append({"setting": layout, "split": split, "frames": len(frames),
                         "left_mirrored": sum(f.mirror for f in frames), "skipped": len(reader.skipped)})
    else:
        for split in ("train", "evaluation"):
            reader = open_reader("ho3d", root, root / "mano", split, on_error="raise",
                                 version="v3" if layout == "ho3d_v3" else "v2")
            rows.append({"setting": layout, "split": split, "frames": len(list(reader.frames())),
                         "skipped": len(reader.skipped)})
    return rows
