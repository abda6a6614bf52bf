"""hoisdf score arctic against ARCTIC's own evaluation code on the stored toy submission (tests/golden/arctic)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from hoisdf.scoring.cli import main as score_main

pytestmark = pytest.mark.slow  # poses 2 x 47 MANO hands per file set and computes the interaction fields

GOLDEN = Path(__file__).parent / "golden" / "arctic"
REL = 1e-6  # tests/golden/arctic/README.md: measured at most 8.1e-7 (float32 run), 1.1e-7 (float64 run)
# ARCTIC's evaluate_metrics.py on these files: (float32 run, float64 run)
POSE_P2 = {"aae": (3.148880958557129, 3.148881435394287), "mpjpe/ra/h": (7.730616092681885, 7.730617523193359),
           "mrrpe/r/l": (12.93377017974853, 12.933778022558428), "mrrpe/r/o": (14.739385604858398, 14.739382913222906),
           "success_rate/0.05": (95.85256427526474, 95.85256427526474),
           "cdev/ho": (18.690359115600586, 18.690361191406694), "mdev/h": (25.32394027709961, 25.323940291168732),
           "acc/h": (15.023524284362793, 15.023536424684469), "acc/o": (8.742682456970215, 8.742684495450188)}
FIELD_P2 = {"avg/ho": (3.0954067707061768, 3.095406721361523), "avg/oh": (2.9361472129821777, 2.9361472534580075),
            "acc/oh": (6.553152561187744, 6.553153057196553), "acc/ho": (6.9267377853393555, 6.926738218105288)}


@pytest.fixture(scope="module")
def mano(tmp_path_factory):
    from hoidata.toy.hand import write_toy_mano

    out = tmp_path_factory.mktemp("mano")
    write_toy_mano(out)
    return out


@pytest.mark.parametrize("task,golden", [("pose", POSE_P2), ("field", FIELD_P2)])
def test_scores_equal_arctic_evaluation_code(task, golden, mano, tmp_path):
    import json

    out = tmp_path / "scores.json"
    assert score_main(["arctic", "--pred", str(GOLDEN / task / f"{task}_p2_test"), "--gt", str(GOLDEN / task / "gt"),
                       "--meta", str(GOLDEN / "meta"), "--mano", str(mano), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    for key, values in golden.items():
        for value in values:
            assert result[key] == pytest.approx(value, rel=REL), key
    assert result["samples"] == 44 and result["folders"] == 1
    if task == "pose":
        assert result["contact_windows"] > 0 and result["hands_without_window"] == 0


def test_a_zip_of_the_submission_scores_the_same(mano, tmp_path):
    import json

    zipped = shutil.make_archive(str(tmp_path / "pose_p2_test"), "zip", root_dir=GOLDEN / "pose",
                                 base_dir="pose_p2_test")
    out = tmp_path / "scores.json"
    assert score_main(["arctic", "--pred", zipped, "--gt", str(GOLDEN / "pose" / "gt"), "--meta", str(GOLDEN / "meta"),
                       "--mano", str(mano), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["aae"] == pytest.approx(POSE_P2["aae"][1], rel=REL)
