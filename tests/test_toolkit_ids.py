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
from hoidata.errors import DataError

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


@pytest.mark.slow
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
        assert len(frames) + len(invalid) == len(ref) == 3 * 8 * 2 and len(invalid) == 8


@pytest.mark.slow
def test_strided_setting_keeps_the_ids_of_the_full_enumeration(tiny_dexycb):
    full = {f.frame_id: f.sample_index for f in _reader(tiny_dexycb, "train").frames()}
    subset = list(_reader(tiny_dexycb, "train", "dexycb").frames())  # right hands, every 5th frame
    assert subset and all(full[f.frame_id] == f.sample_index for f in subset)


@pytest.mark.slow
def test_toolkit_split_offsets(tiny_dexycb):
    enum = toolkit_split(tiny_dexycb, "s0", "train")
    seqs = sorted(p.name for p in (tiny_dexycb / SUBJECTS[0]).iterdir())
    assert enum.sample_index(SUBJECTS[0], seqs[1], SERIALS[0], 0) == 8 * 8  # after 8 cameras x 8 frames
    assert enum.sample_index(SUBJECTS[0], seqs[0], SERIALS[7], 7) == 63
    assert toolkit_split(tiny_dexycb, "s0", "test").size == 0  # subject 0 has no test sequences


@pytest.mark.slow
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


# ---------------------------------------------------------------- the HPE result file, as hpe_eval.py takes it

def hpe_eval(root, split: str, res_file) -> dict:
    """dex-ycb-toolkit's ``HPEEvaluator(f's0_{split}').evaluate(res_file)``, restated (dex_ycb_toolkit/hpe_eval.py with
    FreiHAND's EvalUtil and align_w_scale): ground truth from every sample's label file, skipping joint_3d all -1;
    the result file parsed line by line; every ground-truth id must be in it."""
    import numpy as np
    from scipy.linalg import orthogonal_procrustes

    gt = {}
    for (subject, seq, serial, f), i in sorted(reference_ids(root, split).items(), key=lambda kv: kv[1]):
        label = np.load(root / subject / seq / serial / f"labels_{f:06d}.npz")
        joint_3d = label["joint_3d"].reshape(21, 3)
        if np.all(joint_3d == -1):
            continue
        joint_3d *= 1000  # float32, in place, as the toolkit
        gt[i] = joint_3d.astype(np.float64)
    res = {}
    with open(res_file) as f:
        for line in f:
            elems = line.split(",")
            if len(elems) != 64:
                raise ValueError(f"a line does not have 64 comma-seperated elements: {line}")
            res[int(elems[0])] = np.array(elems[1:], dtype=np.float64).reshape(21, 3)

    def align_w_scale(mtx1, mtx2):
        t1, t2 = mtx1.mean(0), mtx2.mean(0)
        a, b = mtx1 - t1, mtx2 - t2
        s1, s2 = np.linalg.norm(a) + 1e-8, np.linalg.norm(b) + 1e-8
        r, s = orthogonal_procrustes(a / s1, b / s2)
        return np.dot(b / s2, r.T) * s * s1 + t1

    dists = {"absolute": [], "root-relative": [], "procrustes": []}  # per sample: (21,) distances
    for i, kpt_gt in gt.items():
        assert i in res, f"missing image id in result file: {i}"
        pred = res[i]
        dists["absolute"].append(np.linalg.norm(kpt_gt - pred, axis=1))
        dists["root-relative"].append(np.linalg.norm((kpt_gt - kpt_gt[0]) - (pred - pred[0]), axis=1))
        dists["procrustes"].append(np.linalg.norm(kpt_gt - align_w_scale(kpt_gt, pred), axis=1))
    thresholds = np.linspace(0.0, 50.0, 100)
    out = {}
    for name, d in dists.items():
        per_kp = np.stack(d).T  # (21, N): EvalUtil's per-keypoint lists
        pck = (per_kp[:, :, None] <= thresholds).mean(1)
        aucs = np.trapezoid(pck, thresholds, axis=1) / np.trapezoid(np.ones_like(thresholds), thresholds)
        out[name] = {"mpjpe": float(per_kp.mean(1).mean()), "auc": float(aucs.mean())}
    return out


@pytest.fixture(scope="module")
def store_8cam(dexycb_8cam, tmp_path_factory):
    """Every valid frame of the 8-camera toy's s0_train (dexycb_full selection), small records."""
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    out = tmp_path_factory.mktemp("store_8cam") / "store"
    overrides = ['dataset.splits=["train"]', "record.crop_size=64", "record.sdf_samples_hand=64", "record.sdf_samples_object=32"]
    build_store(load_build_config("toy", overrides), dexycb_8cam, dexycb_8cam / "mano", dexycb_8cam / "models", out,
                progress=False)
    return out


@pytest.mark.slow
def test_hpe_file_of_a_whole_split_is_accepted_by_the_toolkit(store_8cam, dexycb_8cam, untrained_run, mano_dir, tmp_path):
    import json

    from hoisdf.evaluate import evaluate

    result = evaluate(untrained_run, [store_8cam], mano_dir, tmp_path, batch_size=16, plausibility=0, progress=False,
                      workers=0)
    assert [p.name for p in tmp_path.glob("dexycb_hpe*")] == ["dexycb_hpe_s0_train.txt"]  # complete: no "_subset"
    official = hpe_eval(dexycb_8cam, "train", tmp_path / "dexycb_hpe_s0_train.txt")
    ours = json.loads((tmp_path / "metrics.json").read_text())["dexycb_hpe"]["dexycb_hpe_s0_train.txt"]
    assert ours["complete"] and ours["samples"] == result["samples"] == 3 * 8 * 2 - 8
    for name, row in official.items():
        assert ours[name]["mpjpe"] == pytest.approx(row["mpjpe"], rel=1e-12), name  # mm
        assert ours[name]["auc"] == pytest.approx(row["auc"], rel=1e-12), name
        assert 1.0 < row["mpjpe"] < 1000.0  # an untrained model: a real error, not a trivial 0
    overall = result["overall"]
    for name, key in (("absolute", "mje"), ("root-relative", "rr_mje"), ("procrustes", "pa_mje")):
        assert overall[key] == pytest.approx(official[name]["mpjpe"], abs=1e-3), key


@pytest.mark.slow
def test_hpe_file_of_a_subset_says_so(store_8cam, dexycb_8cam, untrained_run, mano_dir, tmp_path, capsys):
    from hoisdf.evaluate import evaluate

    evaluate(untrained_run, [store_8cam], mano_dir, tmp_path, limit=10, plausibility=0, progress=False, workers=0)
    printed = capsys.readouterr().out
    assert [p.name for p in tmp_path.glob("dexycb_hpe*")] == ["dexycb_hpe_s0_train_subset.txt"]
    assert printed.count("dexycb_hpe_s0_train_subset.txt: a subset of s0_train (30 of the split's 48") == 1
    with pytest.raises(AssertionError, match="missing image id in result file"):
        hpe_eval(dexycb_8cam, "train", tmp_path / "dexycb_hpe_s0_train_subset.txt")


# ---------------------------------------------------------------- dataset.frame_list: gSDF-style id lists

def _build_listed(root, out, ids, *extra):
    """Build the listed frames with the toy setting narrowed to right hands, every 5th frame, proximity on: the
    list must override all three."""
    import json

    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config

    listed = out.parent / f"{out.name}.json"
    listed.write_text(json.dumps([str(i).rjust(8, "0") for i in ids]))  # gSDF writes 8-digit strings
    overrides = ['dataset.splits=["train"]', 'dataset.sides=["right"]', "dataset.frame_stride=5",
                 "dataset.proximity_mm=5.0", f"dataset.frame_list={listed}", "record.crop_size=64",
                 "record.sdf_samples_hand=64", "record.sdf_samples_object=32", *extra]
    build_store(load_build_config("toy", overrides), root, root / "mano", root / "models", out, progress=False)
    return listed


@pytest.mark.slow
def test_frame_list_builds_exactly_the_listed_frames(tiny_dexycb, tmp_path):
    from hoidata.store import read_index

    ref = reference_ids(tiny_dexycb, "train")
    seqs = sorted(p.name for p in (tiny_dexycb / SUBJECTS[0]).iterdir())
    wanted = [ref[(SUBJECTS[0], seqs[0], SERIALS[0], f)] for f in (1, 3)]  # right hand, off the 5-frame stride
    wanted.append(ref[(SUBJECTS[0], seqs[1], SERIALS[0], 2)])  # a left hand: mirrored
    listed = _build_listed(tiny_dexycb, tmp_path / "store", wanted)
    index = read_index(tmp_path / "store")
    assert sorted(index.labels["sample_index"].tolist()) == sorted(wanted)
    assert index.labels["mirrored"].tolist() == [False, False, True]
    assert index.provenance["frame_list"]["ids"] == 3 and index.config["dataset"]["frame_list"] == str(listed)


@pytest.mark.slow
def test_frame_list_ids_missing_from_the_dataset_are_named(tiny_dexycb, tmp_path):
    ref = reference_ids(tiny_dexycb, "train")
    seqs = sorted(p.name for p in (tiny_dexycb / SUBJECTS[0]).iterdir())
    absent_camera = ref[(SUBJECTS[0], seqs[0], SERIALS[1], 0)]  # the toy has only the first camera
    with pytest.raises(DataError, match=r"2 listed ids are not frames of this dataset's s0_train \(128 samples; 1 past "
                                        rf"its end.*\[{absent_camera}, 1000000\]"):
        _build_listed(tiny_dexycb, tmp_path / "store", [0, absent_camera, 10 ** 6])
    assert not (tmp_path / "store").exists()  # nothing written


@pytest.mark.parametrize("content, match", [('["00000001", "x7"]', "item 1"), ("[3, 3]", "more than once: \\[3\\]"),
                                            ('{"ids": [1]}', "non-empty JSON list"), ("[1.5]", "item 0")])
def test_frame_list_bad_files(tmp_path, content, match):
    from hoidata.datasets.frame_list import read_frame_list

    path = tmp_path / "list.json"
    path.write_text(content)
    with pytest.raises(DataError, match=f"{path}.*{match}"):
        read_frame_list(path)


def test_frame_list_needs_one_dexycb_split():
    from hoidata.records.settings import load_build_config

    with pytest.raises(DataError, match="dataset.frame_list.*one DexYCB split"):
        load_build_config("dexycb", ["dataset.frame_list=train_s0_29k.json"])  # dexycb.toml builds train and test
