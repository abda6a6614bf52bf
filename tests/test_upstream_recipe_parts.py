"""The pieces the upstream recipe selects beside the model keys: validation as upstream's main/train.py runs it
(schedule, PA-MJE), the left hands' MANO targets from the right layer, and zero shape targets for rendered frames."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from hoisdf.scoring.metrics import pa_mje as reference_pa_mje
from hoisdf.config import LossWeights
from hoisdf.training.losses import HOISDFLoss, hand_targets, mirrored_shape_mano
from hoisdf.training.trainer import validates_after


def test_upstream_validation_schedule_is_every_5_epochs_then_every_epoch_from_field_sampling():
    # main/train.py:164-169: after 0-based epoch e, when e % save_gap == 0, save_gap 5 before point_sampling_epoch
    after = [e for e in range(70) if validates_after(e, "upstream", 1, 40)]
    assert after == [0, 5, 10, 15, 20, 25, 30, 35, *range(40, 70)]
    assert [e for e in range(12) if validates_after(e, "upstream", 1, 4)] == [0, *range(4, 12)]


def test_the_every_schedule_is_the_one_before():
    assert [e for e in range(6) if validates_after(e, "every", 1, 40)] == list(range(6))
    assert [e for e in range(9) if validates_after(e, "every", 3, 40)] == [2, 5, 8]  # epochs 3, 6, 9 counted from 1
    assert not any(validates_after(e, "every", 0, 40) for e in range(9))


def _joints(seed: int, n: int = 6) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=0.05, size=(n, 21, 3))


def test_validation_pa_mje_is_the_similarity_alignment_with_a_proper_rotation():
    """The trainer's validation PA-MJE is hoisdf.scoring.metrics.pa_mje without reflections (upstream's
    ``rigid_align``, common/metrics.py:188-210; equal to it within 4.3e-16 on 200 pairs run in scratch)."""
    import inspect

    from hoisdf.training import trainer

    assert trainer.pa_mje is reference_pa_mje and "reflection=False" in inspect.getsource(trainer.Trainer)
    gt = _joints(0)
    rot = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))
    pred = 1.3 * gt @ rot.T + 0.2 + 0.002 * _joints(2)
    assert reference_pa_mje(pred, gt, reflection=False).max() < 0.003  # the similarity is undone
    mirror = pred * np.array([-1.0, 1.0, 1.0])  # upstream forbids the reflection: a mirror image keeps its error
    assert (reference_pa_mje(mirror, gt, reflection=True) < reference_pa_mje(mirror, gt, reflection=False)).all()


def _mano_batch(mano, mirrored: list[bool], synthetic: list[bool] | None = None) -> dict:
    g = torch.Generator().manual_seed(0)
    n = len(mirrored)
    batch = {"mano_pose": 0.3 * torch.randn(n, 48, generator=g), "mano_betas": torch.randn(n, 10, generator=g),
             "mirrored": torch.tensor(mirrored), "img": torch.zeros(n, 3, 4, 4)}
    if synthetic is not None:
        batch["is_synthetic"] = torch.tensor(synthetic)
    return batch


def test_left_hands_right_layer_takes_the_right_layer_with_the_left_betas(mano_dir):
    from hoidata.hand import load_mano

    mano = load_mano(mano_dir, side="right")
    batch = _mano_batch(mano, [True, False])
    right = hand_targets(mano, mano, batch)
    mirrored = hand_targets(mano, mirrored_shape_mano(mano), batch)
    assert not torch.allclose(right["verts"][0], mirrored["verts"][0])  # the two definitions differ for a left hand
    default = HOISDFLoss(LossWeights(), mano).targets(batch)
    upstream = HOISDFLoss(replace(LossWeights(), left_hands="right_layer"), mano).targets(batch)
    for key in ("verts", "joints"):
        torch.testing.assert_close(default[key], mirrored[key])
        torch.testing.assert_close(upstream[key], right[key])
        torch.testing.assert_close(upstream[key][1], default[key][1])  # a right hand is the same either way


def test_synthetic_betas_zeros_supervises_rendered_frames_towards_zero(mano_dir):
    from hoidata.hand import load_mano

    mano = load_mano(mano_dir, side="right")
    batch = _mano_batch(mano, [False, False], synthetic=[True, False])
    out = {"betas": torch.zeros(1, 2, 10)}
    default = HOISDFLoss(LossWeights(), mano).mano_shape(out, batch, {})
    zeros = HOISDFLoss(replace(LossWeights(), synthetic_betas="zeros"), mano).mano_shape(out, batch, {})
    assert float(default) == pytest.approx(float(batch["mano_betas"].pow(2).mean()), rel=1e-6)
    assert float(zeros) == pytest.approx(float(batch["mano_betas"][1].pow(2).sum() / 20), rel=1e-6)


def test_two_stores_of_weight_1_under_the_global_shuffle_are_upstreams_concatenation():
    """ho3d_render: upstream appends every rendered frame to the real ones and shuffles the whole (data/ho3d.py:195-263,
    DataLoader(shuffle=True)). Weight 1 for both stores: each record of both once per epoch, in one uniform
    permutation (a rendered record is as likely at any position as a real one)."""
    from hoisdf.data.global_shuffle import epoch_plan

    sizes = [30, 12]
    positions = []
    for epoch in range(400):
        plan = epoch_plan(sizes, [1.0, 1.0], sum(sizes), seed=0, epoch=epoch)
        assert sorted(map(tuple, plan.tolist())) == [(s, r) for s in range(2) for r in range(sizes[s])]
        positions.append(np.flatnonzero(plan[:, 0] == 1).mean())
    # the mean position of the 12 rendered records is (42 - 1) / 2 under a uniform permutation; its standard error
    # over 400 epochs is about 0.17
    assert abs(np.mean(positions) - 20.5) < 1.0
