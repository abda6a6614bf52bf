"""HOISDF training losses: one method per term, each multiplied by its weight; every term is returned for logging.

Terms and weights follow the reference code (docs/upstream.md, "Losses"). Deep supervision: MANO terms
average over all decoder layers, voting terms over all hand-encoder layers, object terms over all
object-encoder layers (the layer axis L of the model outputs).
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from hoidata.geometry.rotation import axis_angle_to_matrix, matrix_to_axis_angle
from hoidata.hand.model import TIP_VERTICES
from hoisdf.config import LossWeights
from hoisdf.model.heads import wrist_centred_mano


def mirrored_shape_mano(mano) -> nn.Module:
    """A copy of the right MANO layer with the x part of the shape directions negated.

    DexYCB labels left hands with MANO_LEFT as shipped (without the shapedirs fix); a left hand mirrored to
    a right hand is then the right model with ``shapedirs[:, 0]`` negated, not the right model itself
    (identical for betas = 0). Its fingertip joints are the left model's (manopth picks vertex 445, not 444,
    for the left middle tip). Ground truth of ``mirrored`` records is computed with this layer.
    """
    twin = copy.deepcopy(mano)
    twin.shapedirs[:, 0] = -twin.shapedirs[:, 0]
    twin.tip_vertices = TIP_VERTICES[(mano.tips, "left")]
    return twin


def hand_targets(mano, mirrored_mano, batch: dict) -> dict[str, torch.Tensor]:
    """Wrist-centred ground-truth MANO ``verts`` (B, 778, 3), ``joints`` (B, 21, 3) and ``rotations`` (B, 16, 3, 3).

    Records flagged ``mirrored`` use ``mirrored_mano`` (see :func:`mirrored_shape_mano`).
    """
    pose, betas = batch["mano_pose"].float(), batch["mano_betas"].float()
    B = pose.shape[0]
    rotations = axis_angle_to_matrix(pose.view(B, 16, 3))
    with torch.no_grad():
        verts, joints = wrist_centred_mano(mano, rotations, betas)
        mirrored = batch.get("mirrored")
        if mirrored is not None and bool(mirrored.any()):
            m_verts, m_joints = wrist_centred_mano(mirrored_mano, rotations, betas)
            flag = mirrored.to(verts.device)[:, None, None]
            verts, joints = torch.where(flag, m_verts, verts), torch.where(flag, m_joints, joints)
    return {"verts": verts, "joints": joints, "rotations": rotations}


class HOISDFLoss(nn.Module):
    """``forward(outputs, batch) -> (total, terms)``: ``terms`` maps each name to its weighted value."""

    def __init__(self, weights: LossWeights, mano, sdf_scale: float = 3.1, sdf_clamp: float = 0.15,
                 cls_dist: float = 0.04, mirrored_mano: nn.Module | None = None):
        super().__init__()
        self.weights = {name: getattr(weights, name) for name in weights.TERMS}
        if weights.left_hands == "right_layer":  # upstream: the right layer with the left hand's betas
            mirrored_mano = mano
        self._mano = [mano, mirrored_mano if mirrored_mano is not None else mirrored_shape_mano(mano)]
        self.synthetic_zero_betas = weights.synthetic_betas == "zeros"
        self.scale, self.clamp, self.cls_dist = sdf_scale, sdf_clamp, cls_dist

    def forward(self, out: dict, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        device = batch["img"].device
        for layer in self._mano:
            if layer.v_template.device != device:
                layer.to(device)
        gt = self.targets(batch) if "rotations" in out or "betas" in out else {}
        terms = {}
        for name, fn in self._terms(out):
            terms[name] = self.weights[name] * fn(out, batch, gt)
        total = torch.stack(list(terms.values())).sum()
        return total, terms

    def _terms(self, out: dict):
        yield "heatmap", self.heatmap
        yield "hand_seg", self.hand_seg
        yield "obj_seg", self.obj_seg
        if "hand_sdf" in out:
            yield "sdf_hand", self.sdf_hand
        if "obj_sdf" in out:
            yield "sdf_obj", self.sdf_obj
        if "vote_joints" in out:
            yield from (("joint_vote", self.joint_vote), ("joint_cls", self.joint_cls), ("joint_all", self.joint_all))
        if "rotations" in out:
            yield from (("mano_verts", self.mano_verts), ("mano_joints", self.mano_joints),
                        ("mano_pose", self.mano_pose))
        if "betas" in out:
            yield "mano_shape", self.mano_shape
            if "rotations" not in out:
                yield "shape_reg", self.shape_reg
        yield "obj_rot", self.obj_rot
        yield "obj_trans", self.obj_trans

    # --- targets --------------------------------------------------------------------------------------------
    def targets(self, batch: dict) -> dict[str, torch.Tensor]:
        return hand_targets(self._mano[0], self._mano[1], batch)

    @staticmethod
    def root_relative_joints(batch: dict) -> torch.Tensor:
        """Ground-truth joints 1..20 relative to the hand root, (B, 20, 3) metres."""
        return (batch["joints_3d"] - batch["hand_root"][:, None])[:, 1:]

    # --- 2D ----------------------------------------------------------------------------------------------------
    def heatmap(self, out, batch, gt):
        return F.mse_loss(out["heatmap"].float(), 255.0 * batch["heatmap"].float())

    def hand_seg(self, out, batch, gt):
        return F.binary_cross_entropy_with_logits(out["hand_mask_logits"].float(), batch["seg"][:, 0:1].float())

    def obj_seg(self, out, batch, gt):
        return F.binary_cross_entropy_with_logits(out["obj_mask_logits"].float(), batch["seg"][:, 1:2].float())

    # --- fields ------------------------------------------------------------------------------------------------
    def _sdf(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return F.l1_loss(pred.float(), (target.float() * self.scale).clamp(-self.clamp, self.clamp))

    def sdf_hand(self, out, batch, gt):
        return self._sdf(out["hand_sdf"], batch["hand_sdf"])

    def sdf_obj(self, out, batch, gt):
        return self._sdf(out["obj_sdf"], batch["obj_sdf"])

    # --- voting ------------------------------------------------------------------------------------------------
    def _labels(self, out, batch) -> torch.Tensor:
        """(B, N, 20) float: query point within cls_dist of the joint."""
        joints = self.root_relative_joints(batch)
        return (torch.cdist(out["hand_query"].float(), joints.float()) < self.cls_dist).float()

    def joint_vote(self, out, batch, gt):
        labels = self._labels(out, batch)  # (B, N, J)
        votes = (out["hand_query"][None, :, :, None] + out["vote_offsets"].float()) * 1000.0  # (L, B, N, J, 3) mm
        target = self.root_relative_joints(batch)[None, :, None] * 1000.0
        err = F.smooth_l1_loss(votes, target.expand_as(votes), reduction="none", beta=1.0)
        # upstream: sum over samples, points and joints / number of labelled (sample, point, joint) pairs,
        # then the mean over layers and coordinates (the three coordinates are averaged once, here)
        return (err * labels[None, ..., None]).sum((1, 2, 3)).div(labels.sum().clamp_min(1.0)).mean()

    def joint_cls(self, out, batch, gt):
        logits = out["vote_logits"].float()
        return F.binary_cross_entropy_with_logits(logits, self._labels(out, batch)[None].expand_as(logits))

    def joint_all(self, out, batch, gt):
        pred = out["vote_joints"].float() * 1000.0
        target = self.root_relative_joints(batch)[None].float() * 1000.0
        return F.smooth_l1_loss(pred, target.expand_as(pred), beta=1.0)

    # --- MANO --------------------------------------------------------------------------------------------------
    @staticmethod
    def _layers_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return F.mse_loss(pred.float(), target[None].float().expand_as(pred))

    def mano_verts(self, out, batch, gt):
        return self._layers_mse(out["mano_verts"], gt["verts"])

    def mano_joints(self, out, batch, gt):
        return self._layers_mse(out["mano_joints"], gt["joints"])

    def mano_pose(self, out, batch, gt):
        return self._layers_mse(out["rotations"], gt["rotations"])

    def mano_shape(self, out, batch, gt):
        target = batch["mano_betas"]
        if self.synthetic_zero_betas and "is_synthetic" in batch:  # upstream's rendered frames: MANO params all 0
            target = torch.where(batch["is_synthetic"].to(target.device)[:, None], torch.zeros_like(target), target)
        return self._layers_mse(out["betas"], target)

    def shape_reg(self, out, batch, gt):
        return out["betas"].float().pow(2).mean()

    # --- object ------------------------------------------------------------------------------------------------
    def obj_rot(self, out, batch, gt):
        target = matrix_to_axis_angle(batch["object_pose"][:, :3, :3].float())  # (B, 3)
        pred = out["obj_rot_points"].float()
        return F.smooth_l1_loss(pred, target[None, :, None].expand_as(pred), beta=1.0)

    def obj_trans(self, out, batch, gt):
        target = (batch["object_pose"][:, :3, 3] - batch["obj_center"]).float()
        pred = out["obj_trans_points"].float()
        return F.smooth_l1_loss(pred, target[None, :, None].expand_as(pred), beta=1.0)
