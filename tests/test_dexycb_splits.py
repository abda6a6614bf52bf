"""DexYCB setups s0-s3 over the real index space (10 subjects x 100 sequences x 8 cameras)."""

from __future__ import annotations

import pytest

from hoidata.datasets.dexycb_layout import split_members


def _cells(setup, split):
    subjects, serials, keep = split_members(setup, split)
    return {(s, i, c) for s in subjects for i in range(100) if keep(i) for c in serials}


@pytest.mark.parametrize("setup", ["s0", "s1", "s2", "s3"])
def test_splits_partition_or_cover_the_dataset(setup):
    train, val, test = (_cells(setup, split) for split in ("train", "val", "test"))
    assert not (train & val) and not (train & test) and not (val & test)
    everything = {(s, i, c) for s in range(10) for i in range(100) for c in range(8)}
    union = train | val | test
    if setup == "s0":  # s0 test/val take the 5th trial of subjects 0-1 (val) and 2-9 (test)
        assert union == everything
    assert union <= everything


def test_split_sizes_in_sequence_cameras():
    expected = {  # (sequence, camera) pairs per split, from the toolkit's rules
        ("s0", "train"): 10 * 80 * 8, ("s0", "val"): 2 * 20 * 8, ("s0", "test"): 8 * 20 * 8,
        ("s1", "train"): 7 * 100 * 8, ("s1", "val"): 1 * 100 * 8, ("s1", "test"): 2 * 100 * 8,
        ("s2", "train"): 10 * 100 * 6, ("s2", "val"): 10 * 100, ("s2", "test"): 10 * 100,
        ("s3", "train"): 10 * 75 * 8, ("s3", "val"): 10 * 10 * 8, ("s3", "test"): 10 * 15 * 8,
    }
    for (setup, split), n in expected.items():
        assert len(_cells(setup, split)) == n, (setup, split)


def test_s3_holds_out_grasped_objects():
    _, _, keep_val = split_members("s3", "val")
    assert [i for i in range(100) if keep_val(i)] == list(range(15, 20)) + list(range(95, 100))


def test_unknown_setup_or_split():
    with pytest.raises(ValueError, match="unknown DexYCB setup 's9'"):
        split_members("s9", "train")
    with pytest.raises(ValueError, match="unknown DexYCB split 'dev'"):
        split_members("s0", "dev")
