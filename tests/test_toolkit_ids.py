"""DexYCB sample ids: every frame, record and index row carries the dex-ycb-toolkit's sample index of its split.

The reference enumeration below is written from the toolkit's ``DexYCBDataset.__init__`` (dex_ycb_toolkit/dex_ycb.py):
subjects of the split in order, each subject's sorted sequence folders at the split's positions, then for every
sequence its ``meta.yml`` ``num_frames`` frames for each of the split's cameras (camera outer, frame inner), whatever
cameras the sequence holds on disk and whichever frames a reader keeps.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import yaml

from hoidata.datasets.dexycb import SETTINGS, DexYCBReader
from hoidata.datasets.dexycb_frames import TOOLKIT_INVALID
from hoidata.datasets.dexycb_layout import SERIALS, SUBJECTS, toolkit_split

SPLIT_SUBJECTS = {"train": range(10), "val": (0, 1), "test": range(2, 10)}  # toolkit s0


def reference_ids(root, split: str) -> dict[tuple[str, str, str, int], int]:
    """(subject, sequence, serial, frame) -> the toolkit's index in s0_<split>, by counting samples one by one."""
    keep = (lambda i: i % 5 != 4) if split == "train" else (lambda i: i % 5 == 4)
    ids, n = {}, 0
    for s in SPLIT_SUBJECTS[split]:
        folder = root / SUBJECTS[s]
        if not folder.is_dir():
            continue
        for i, seq in enumerate(sorted(p.name for p in folder.iterdir() if p.is_dir())):
            if not keep(i):
                continue
            frames = yaml.safe_load((folder / seq / "meta.yml").read_text())["num_frames"]
            for serial in SERIALS:  # s0 uses all eight cameras, in this order
                for f in range(frames):
                    ids[(SUBJECTS[s], seq, serial, f)] = n
                    n += 1
    return ids


def _reader(root, split, setting="dexycb_full"):
    return DexYCBReader(root, root / "mano", split, replace(SETTINGS[setting], complete_subjects=False))


@pytest.mark.parametrize("toy", ["tiny_dexycb", "dexycb_8cam"])
def test_reader_frames_carry_the_toolkits_ids(toy, request):
    """tiny_dexycb has one camera of eight (the ids leave gaps); dexycb_8cam has invalid frames, whose skips keep
    their ids."""
    root = request.getfixturevalue(toy)
    ref = reference_ids(root, "train")
    reader = _reader(root, "train")
    frames = list(reader.frames())
    assert reader.toolkit.name == "s0_train" and reader.toolkit.size == len(ref)
    got = [f.sample_index for f in frames]
    for f in frames:
        src = f.source
        assert f.sample_index == ref[(src["subject"], src["sequence"], src["serial"], src["frame"])]
    assert len(set(got)) == len(got)
    invalid = [s for s in reader.skipped if s.reason == TOOLKIT_INVALID]
    assert all(s.sample_index == ref[_skip_source(s.frame_id)] for s in invalid)
    if toy == "tiny_dexycb":
        assert len(ref) == 2 * 8 * 8 and max(got) == 8 * 8 + 7  # sequence 2 starts after 8 cameras x 8 frames
    else:
        assert len(frames) + len(invalid) == len(ref) == 3 * 8 * 3 and len(invalid) == 8


def test_strided_setting_keeps_the_ids_of_the_full_enumeration(tiny_dexycb):
    full = {f.frame_id: f.sample_index for f in _reader(tiny_dexycb, "train").frames()}
    subset = list(_reader(tiny_dexycb, "train", "dexycb").frames())  # right hands, every 5th frame
    assert subset and all(full[f.frame_id] == f.sample_index for f in subset)


def test_toolkit_split_offsets(tiny_dexycb):
    enum = toolkit_split(tiny_dexycb, "s0", "train")
    seqs = sorted(p.name for p in (tiny_dexycb / SUBJECTS[0]).iterdir())
    assert enum.sample_index(SUBJECTS[0], seqs[1], SERIALS[0], 0) == 8 * 8  # after 8 cameras x 8 frames
    assert enum.sample_index(SUBJECTS[0], seqs[0], SERIALS[7], 7) == 63
    assert toolkit_split(tiny_dexycb, "s0", "test").size == 0  # subject 0 has no test sequences


def test_store_index_and_records_hold_the_ids(tiny_store, tiny_dexycb):
    from hoidata.store import iter_records, read_index

    index = read_index(tiny_store)
    ref = reference_ids(tiny_dexycb, "train")
    by_key = {}
    for rec in iter_records(sorted(tiny_store.glob("shard-*.tar"))):
        src = rec["meta.json"]["source"]
        assert rec["meta.json"]["sample_index"] == ref[(src["subject"], src["sequence"], src["serial"], src["frame"])]
        by_key[rec["__key__"]] = rec["meta.json"]["sample_index"]
    assert index.labels["sample_index"].tolist() == [by_key[k] for k in index.keys]
    assert index.provenance["toolkit_splits"] == {"train": {"name": "s0_train", "size": len(ref)}}
    skipped = [s for s in index.skipped if s["reason"] == TOOLKIT_INVALID]
    assert all(ref[_skip_source(s["frame_id"])] == s["sample_index"] for s in skipped)


def _skip_source(frame_id: str) -> tuple:
    """(subject, sequence, serial, frame) of a frame id ``<subject>_<sequence>_<serial>_<frame>``."""
    subject, rest = frame_id[:19], frame_id[20:]
    date, time, serial, frame = rest.split("_")
    return subject, f"{date}_{time}", serial, int(frame)
