"""ARCTIC's metrics (hoisdf.scoring.arctic_metrics) on hand-made inputs, the torch-free .pt reader, and
hoisdf check arctic's one line per broken file (on a copy of the stored toy submission)."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from hoisdf.scoring import arctic_metrics as am
from hoisdf.scoring.arctic_files import check_submission, read_reference
from hoisdf.scoring.torch_files import read_pt

GOLDEN = Path(__file__).parent / "golden" / "arctic"
FOLDER = "s03_espressomachine_grab_01_0"


def test_matrix_to_axis_angle_inverts_rodrigues_and_keeps_pytorch3d_scaling():
    from hoidata.geometry.rotation import matrix_to_axis_angle_as_pytorch3d as convert

    def matrix_to_axis_angle(m):
        return convert(torch.as_tensor(m)).numpy()

    mats = Rotation.random(200, random_state=1).as_matrix()
    out = matrix_to_axis_angle(mats)
    assert np.allclose(Rotation.from_rotvec(out).as_matrix(), mats, atol=1e-9)
    assert (np.linalg.norm(out, axis=1) > np.pi).any()  # like PyTorch3D, the quaternion's sign is kept as it comes
    assert np.allclose(matrix_to_axis_angle(np.eye(3)), 0)
    # a matrix that is no rotation: the chosen candidate quaternion is not unit, its norm scales the vector
    m = Rotation.from_rotvec([0.3, 0.0, 0.0]).as_matrix() * 1.01
    out = matrix_to_axis_angle(m)
    assert out[1] == out[2] == 0 and not np.isclose(out[0], 0.3)


def test_nanmean_is_nan_only_where_every_value_is():
    out = am.nanmean(np.array([[1.0, np.nan], [np.nan, np.nan]]), axis=1)
    assert out[0] == 1.0 and np.isnan(out[1])


def _contact(frames, spans, verts=778):
    dist = np.full((frames, verts), 0.05)
    for v, (a, b) in spans.items():
        dist[a:b, v] = 0.001
    return dist


def test_windows_close_only_when_contact_ends_and_need_fifteen_frames():
    dist = _contact(40, {0: (2, 20), 1: (5, 15), 2: (30, 40), 3: (0, 16)})
    idx = np.zeros((40, 778), np.int64)
    windows, stops = am.find_windows(dist, idx, np.zeros((1, 3)))
    assert [w[:3] for w in windows] == [(2, 19, 0), (0, 15, 3)]  # 1: 10 frames; 2: still in contact at the end
    assert stops == 1  # vertex 3's window starts at the first frame: ARCTIC's own check fails there


def test_windows_skip_sliding_contacts_and_take_the_smallest_of_tied_vertices():
    dist = _contact(30, {0: (1, 17), 1: (1, 17)})
    idx = np.zeros((30, 778), np.int64)
    idx[1:9, 0], idx[9:17, 0] = 5, 4  # 8 and 8 frames: a tie
    idx[1:17, 1] = np.arange(16) % 3 + 6  # three object vertices far apart: the finger slides
    vo0 = np.zeros((10, 3))
    vo0[6:9] = [[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]]
    windows, _ = am.find_windows(dist, idx, vo0)
    assert windows == [(1, 16, 0, 4)]


def test_motion_deviation_is_zero_for_a_rigid_grasp_and_skips_invalid_frames():
    t = np.arange(20)[:, None] * np.array([0.01, 0.0, 0.0])
    hand, obj = t[:, None] + np.zeros((1, 778, 3)), t[:, None] + np.zeros((1, 10, 3))
    valid = np.ones(20)
    assert am.motion_deviation([(0, 19, 3, 2)], hand, obj, valid)[0] == 0
    hand2 = hand.copy()
    hand2[:, 3, 1] = np.arange(20) * 0.002  # 2 mm a frame across the object
    valid[5:10] = 0
    assert am.motion_deviation([(0, 19, 3, 2)], hand2, obj, valid)[0] == pytest.approx(2.0)


def test_acceleration_error_is_central_difference_at_30_fps():
    gt = np.zeros((5, 1, 3))
    pred = gt.copy()
    pred[2, 0, 0] = 0.001  # one frame 1 mm off: (1, -2, 1) stencil x 900
    assert np.allclose(am.error_accel(gt, pred), [0.9, 1.8, 0.9])


def test_torch_files_read_what_torch_saves():
    for value in (torch.randn(4, 16, 3, 3).half(), torch.randn(7), torch.arange(5)):
        buf = io.BytesIO()
        torch.save(value, buf)
        got = read_pt("x.pt", buf.getvalue())
        assert got.torch_dtype == str(value.dtype).split(".")[1] and np.array_equal(np.asarray(got), value.numpy())


@pytest.fixture
def submission(tmp_path):
    dst = tmp_path / "pose_p2_test"
    shutil.copytree(GOLDEN / "pose" / "pose_p2_test", dst)
    return dst


def _preds(sub: Path) -> Path:
    return sub / "eval" / FOLDER / "preds"


def test_the_stored_toy_submission_passes_with_notes_for_what_the_server_tolerates(submission):
    problems, notes, preds = check_submission(submission, "pose", "p2", read_reference(GOLDEN / "pose" / "gt"))
    assert problems == [] and len(preds[FOLDER]["pred.object.radian"]) == 44
    assert len(notes) == 1 and "trims" in notes[0]  # 47 frames predicted, 44 in the ground truth
    problems, notes, _ = check_submission(submission, "pose", "p2")  # no ground truth: its own image names count
    assert problems == [] and "meta_info.imgname.pt" in notes[0]


@pytest.mark.parametrize("key,breakage,words", [
    ("pred.object.rot", "missing", "missing"),
    ("pred.mano.pose.r", lambda t: t.reshape(len(t), 144), "shape"),
    ("pred.mano.beta.l", lambda t: torch.where(torch.arange(len(t))[:, None] == 4, torch.nan, t), "NaN"),
    ("pred.mano.cam_t.r", lambda t: t[:40], "40 frames, the ground truth has 44"),
    ("pred.mano.pose.l", lambda t: t.double(), "float64"),
    ("pred.object.radian", lambda t: t.numpy(), "torch tensors is expected"),
    ("pred.mano.beta.r", lambda t: t.long(), "int64"),
])
def test_each_broken_file_gets_one_line_naming_file_and_key(submission, key, breakage, words):
    path = _preds(submission) / f"{key}.pt"
    if breakage == "missing":
        path.unlink()
    else:
        torch.save(breakage(torch.load(path)), path)
    problems, _, preds = check_submission(submission, "pose", "p2", read_reference(GOLDEN / "pose" / "gt"))
    assert len(problems) == 1 and str(path) in problems[0] and repr(key) in problems[0] and words in problems[0]
    assert FOLDER not in preds


def test_a_missing_sequence_folder_and_a_zip_without_eval_are_named(submission, tmp_path):
    shutil.rmtree(submission / "eval" / FOLDER)
    (submission / "eval" / "s03_other_01_0" / "preds").mkdir(parents=True)
    (submission / "eval" / "s03_other_01_0" / "preds" / "pred.object.rot.pt").write_bytes(b"")
    problems, notes, _ = check_submission(submission, "pose", "p2", read_reference(GOLDEN / "pose" / "gt"))
    assert len(problems) == 1 and FOLDER in problems[0] and "missing" in problems[0]
    assert any("not in the ground truth" in n for n in notes)
    from hoidata.errors import DataError

    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no eval/ folder"):
        check_submission(tmp_path / "empty", "pose", "p2")


def test_check_command_exit_codes(submission, capsys):
    from hoisdf.cli import main

    gt = str(GOLDEN / "pose" / "gt")
    assert main(["check", "arctic", "--pred", str(submission), "--gt", gt]) == 0
    (_preds(submission) / "pred.mano.beta.r.pt").unlink()
    assert main(["check", "arctic", "--pred", str(submission), "--gt", gt]) == 1
    out = capsys.readouterr().out
    assert "problem:" in out and "pred.mano.beta.r" in out
