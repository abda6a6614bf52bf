"""Every HOISDF loss term against a small example whose value is written out by hand (numpy, not the loss code).

The definitions are upstream's (docs/upstream.md, "Losses"; ``common/nets/loss.py`` of amathislab/HOISDF):
in particular the joint-vote term sums the masked SmoothL1 over samples, points and joints, divides by the number
of labelled (sample, point, joint) pairs and only then averages over layers and coordinates.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hoisdf.config import LossWeights
from hoisdf.training.losses import HOISDFLoss


@pytest.fixture(scope="module")
def loss(mano_dir):
    from hoidata.hand import load_mano

    return HOISDFLoss(LossWeights(), load_mano(mano_dir, side="right"), sdf_scale=3.1, sdf_clamp=0.15, cls_dist=0.04)


def smooth_l1(x: np.ndarray) -> np.ndarray:
    """SmoothL1 with beta = 1, written out: 0.5 x^2 below 1, |x| - 0.5 above."""
    a = np.abs(x)
    return np.where(a < 1.0, 0.5 * a * a, a - 0.5)


def t(x) -> torch.Tensor:
    return torch.tensor(np.asarray(x, dtype=np.float32))


def test_heatmap_is_the_mse_against_255_times_the_target(loss):
    out = {"heatmap": t([[[[1.0, 2.0], [3.0, 4.0]]]])}
    batch = {"heatmap": t([[[[0.0, 1.0 / 255.0], [0.0, 0.0]]]])}
    # target 255 x heatmap = [[0, 1], [0, 0]]; errors 1, 1, 3, 4
    assert float(loss.heatmap(out, batch, {})) == pytest.approx((1 + 1 + 9 + 16) / 4, rel=1e-6)


def test_segmentation_terms_are_bce_with_logits_on_their_own_channel(loss):
    seg = torch.zeros(1, 4, 1, 2, dtype=torch.bool)
    seg[0, 0, 0, 0] = True  # hand: [1, 0]
    seg[0, 1, 0, 1] = True  # object: [0, 1]
    out = {"hand_mask_logits": t([[[[0.0, 2.0]]]]), "obj_mask_logits": t([[[[0.0, 2.0]]]])}
    hand = (math.log(2.0) + math.log1p(math.exp(2.0))) / 2  # -log s(0), -log(1 - s(2))
    obj = (math.log(2.0) + math.log1p(math.exp(-2.0))) / 2  # -log(1 - s(0)), -log s(2)
    assert float(loss.hand_seg(out, {"seg": seg}, {})) == pytest.approx(hand, rel=1e-6)
    assert float(loss.obj_seg(out, {"seg": seg}, {})) == pytest.approx(obj, rel=1e-6)


def test_sdf_terms_are_l1_against_the_scaled_clamped_target(loss):
    pred = t([[0.1, -0.2, 0.05]])  # scaled units (the model clamps its own output)
    target = t([[0.01, -0.1, 0.02]])  # metres: x3.1 = 0.031, -0.31 -> clamped -0.15, 0.062
    expected = (abs(0.1 - 0.031) + abs(-0.2 + 0.15) + abs(0.05 - 0.062)) / 3
    out, batch = {"hand_sdf": pred, "obj_sdf": pred}, {"hand_sdf": target, "obj_sdf": target}
    assert float(loss.sdf_hand(out, batch, {})) == pytest.approx(expected, rel=1e-5)
    assert float(loss.sdf_obj(out, batch, {})) == pytest.approx(expected, rel=1e-5)


def _voting_case():
    """1 sample, 2 query points, 20 voted joints, 2 encoder layers; three labelled point-joint pairs."""
    joints = np.ones((21, 3)) + np.arange(21)[:, None] * 0.01  # far from both points ...
    joints[0] = 0.0  # ... except the wrist (origin), joints 1 and 2 near point 0 and joint 3 near point 1
    joints[1], joints[2], joints[3] = (0.01, 0.0, 0.0), (0.0, 0.03, 0.0), (0.06, 0.01, 0.0)
    points = np.array([[0.0, 0.0, 0.0], [0.06, 0.0, 0.0]])
    labelled = {(0, 0), (0, 1), (1, 2)}  # (point, voted joint index = joint - 1) with distance < 4 cm
    rng = np.random.default_rng(0)
    delta = rng.uniform(-3.0, 3.0, size=(2, 2, 20, 3))  # vote error in mm per (layer, point, joint, xyz)
    target = joints[1:]  # (20, 3) root-relative (root = wrist = origin)
    offsets = target[None, None] - points[None, :, None] + delta / 1000.0  # (L, N, J, 3) metres
    logits = rng.normal(size=(2, 2, 20))
    vote_joints = target[None] + rng.uniform(-3.0, 3.0, size=(2, 20, 3)) / 1000.0
    out = {"hand_query": t(points[None]), "vote_offsets": t(offsets[:, None]), "vote_logits": t(logits[:, None]),
           "vote_joints": t(vote_joints[:, None])}
    batch = {"joints_3d": t(joints[None]), "hand_root": t(np.zeros((1, 3)))}
    return out, batch, labelled, delta, logits, (vote_joints - target[None]) * 1000.0


def test_joint_vote_divides_by_the_labelled_pairs_then_averages_layers_and_coordinates(loss):
    out, batch, labelled, delta, _, _ = _voting_case()
    per_layer_coord = np.zeros((2, 3))
    for layer in range(2):
        for point, joint in labelled:
            per_layer_coord[layer] += smooth_l1(delta[layer, point, joint])
    expected = (per_layer_coord / len(labelled)).mean()  # upstream: / 3 pairs, then the mean over 2 x 3
    assert float(loss.joint_vote(out, batch, {})) == pytest.approx(expected, rel=1e-3)


def test_joint_cls_is_bce_against_the_4cm_labels_on_every_layer(loss):
    out, batch, labelled, _, logits, _ = _voting_case()
    labels = np.zeros((2, 20))
    for point, joint in labelled:
        labels[point, joint] = 1.0
    p = 1.0 / (1.0 + np.exp(-logits))
    expected = -(labels[None] * np.log(p) + (1 - labels[None]) * np.log(1 - p)).mean()
    assert float(loss.joint_cls(out, batch, {})) == pytest.approx(expected, rel=1e-5)


def test_joint_all_is_smooth_l1_in_mm_of_the_aggregated_joints(loss):
    out, batch, _, _, _, err_mm = _voting_case()
    assert float(loss.joint_all(out, batch, {})) == pytest.approx(smooth_l1(err_mm).mean(), rel=1e-3)


def test_mano_terms_are_mse_over_every_decoder_layer(loss):
    gt = {"verts": t([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]]), "joints": t([[[0.0, 0.0, 0.0]]]),
          "rotations": t(np.eye(3)[None, None])}
    out = {"mano_verts": t([[[[0.0, 0.0, 0.1], [0.1, 0.0, 0.0]]], [[[0.0, 0.0, 0.0], [0.1, 0.2, 0.0]]]]),
           "mano_joints": t([[[[0.1, 0.2, 0.2]]], [[[0.0, 0.0, 0.0]]]]),
           "rotations": t(np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0])])[:, None, None]),
           "betas": t([[[1.0, 2.0] + [0.0] * 8], [[0.0] * 10]])}
    batch = {"mano_betas": t([[1.0] + [0.0] * 9])}
    assert float(loss.mano_verts(out, batch, gt)) == pytest.approx((0.01 + 0.04) / 12, rel=1e-5)
    assert float(loss.mano_joints(out, batch, gt)) == pytest.approx((0.01 + 0.04 + 0.04) / 6, rel=1e-5)
    assert float(loss.mano_pose(out, batch, gt)) == pytest.approx((4 + 4) / 18, rel=1e-6)  # two -1 vs 1 entries
    assert float(loss.mano_shape(out, batch, gt)) == pytest.approx((0 + 4 + 1) / 20, rel=1e-6)
    assert float(loss.shape_reg(out, batch, gt)) == pytest.approx((1 + 4) / 20, rel=1e-6)


def test_object_terms_are_smooth_l1_of_the_per_point_predictions(loss):
    angle = 0.3  # about z: axis-angle (0, 0, 0.3)
    pose = np.eye(4)
    pose[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    pose[:3, 3] = (0.1, -0.05, 0.6)
    center = np.array([0.1, -0.05, 0.5])  # target translation = pose t - centre = (0, 0, 0.1)
    rot = np.array([[0.5, 0.0, angle - 2.0], [0.0, 0.2, angle]])  # (N=2, 3)
    trans = np.array([[0.0, 0.0, 0.1], [1.5, 0.0, 0.1]])
    out = {"obj_rot_points": t(rot[None, None]), "obj_trans_points": t(trans[None, None])}
    batch = {"object_pose": t(pose[None]), "obj_center": t(center[None])}
    rot_expected = (0.125 + 0 + 1.5 + 0 + 0.02 + 0) / 6
    trans_expected = (0 + 0 + 0 + 1.0 + 0 + 0) / 6
    assert float(loss.obj_rot(out, batch, {})) == pytest.approx(rot_expected, rel=1e-4)
    assert float(loss.obj_trans(out, batch, {})) == pytest.approx(trans_expected, abs=1e-6)


def test_forward_weights_each_term_and_sums_them(loss, monkeypatch):
    out, batch, *_ = _voting_case()
    gt = {"verts": torch.zeros(1, 2, 3), "joints": torch.zeros(1, 21, 3), "rotations": torch.eye(3).expand(1, 16, 3, 3)}
    out.update({"heatmap": torch.ones(1, 1, 2, 2), "hand_mask_logits": torch.zeros(1, 1, 2, 2),
                "obj_mask_logits": torch.zeros(1, 1, 2, 2), "hand_sdf": torch.full((1, 3), 0.1),
                "obj_sdf": torch.full((1, 3), -0.1), "mano_verts": torch.full((2, 1, 2, 3), 0.01),
                "mano_joints": torch.full((2, 1, 21, 3), 0.02), "rotations": torch.eye(3).expand(2, 1, 16, 3, 3),
                "betas": torch.ones(2, 1, 10), "obj_rot_points": torch.ones(1, 1, 2, 3),
                "obj_trans_points": torch.ones(1, 1, 2, 3)})
    batch.update({"img": torch.zeros(1, 3, 4, 4), "heatmap": torch.zeros(1, 1, 2, 2),
                  "seg": torch.zeros(1, 4, 2, 2, dtype=torch.bool), "hand_sdf": torch.zeros(1, 3),
                  "obj_sdf": torch.zeros(1, 3), "mano_betas": torch.zeros(1, 10), "object_pose": torch.eye(4)[None],
                  "obj_center": torch.zeros(1, 3)})
    monkeypatch.setattr(loss, "targets", lambda b: gt)
    total, terms = loss(out, batch)
    names = [n for n in LossWeights.TERMS if n != "shape_reg"]  # shape_reg: IK variant only
    assert sorted(terms) == sorted(names)
    for name in names:
        raw = float(getattr(loss, name)(out, batch, gt))
        assert float(terms[name]) == pytest.approx(getattr(LossWeights(), name) * raw, rel=1e-6), name
    assert float(total) == pytest.approx(sum(float(v) for v in terms.values()), rel=1e-6)
    assert float(terms["mano_verts"]) == pytest.approx(1e4 * 1e-4, rel=1e-4)  # 1e4 x MSE of 1 cm
