"""Prediction heads on transformer outputs: MANO (6D rotations + shape), joint voting, object pose.

All heads keep the layer axis L of the deep-supervised transformer outputs in front: (L, B, ...).
"""

from __future__ import annotations

import torch
from torch import nn

from hoidata.geometry.rotation import axis_angle_to_matrix, rot6d_to_matrix
from hoisdf.model.encoding import CENTERS
from hoisdf.model.layers import MLP
from hoisdf.model.precision import full_precision

N_JOINTS = 21
N_VOTED = 20  # joint 0 (the wrist, the origin of root-relative coordinates) is not voted


def wrist_centred_mano(mano, rotations: torch.Tensor, betas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """MANO from per-joint rotations (N, 16, 3, 3) and betas (N, 10) -> (verts (N, 778, 3), joints (N, 21, 3)),
    both relative to the wrist joint (metres). Runs in float32 even under autocast (bf16 skinning errs by mm)."""
    with torch.autocast(device_type=rotations.device.type, enabled=False):
        out = mano(rotations.float(), betas.float())
    root = out.joints[:, :1]
    return out.vertices - root, out.joints - root


class ManoHead(nn.Module):
    """Decoder queries (L, B, 17, D): 16 rotation queries (MANO joint order) + 1 shape query -> MANO.

    The 6D rotations are predicted as offsets from the identity's 6D code, so an untrained head starts at
    the flat hand instead of random rotations (the reference predicts the raw 6D code; same expressiveness,
    much faster early training). :meth:`predict_raw_6d` switches to the reference's raw code (``model.rot6d =
    "raw"``): the same function for weights whose last bias is larger by the identity's code, but weight decay
    then pulls the code towards zero, not towards the identity.

    Returns ``rotations`` (L, B, 16, 3, 3), ``betas`` (L, B, 10), ``verts`` (L, B, 778, 3) and ``joints``
    (L, B, 21, 3, DexYCB order), wrist-centred metres.
    """

    def __init__(self, d_model: int):
        super().__init__()
        self.pose = MLP(d_model, [d_model, d_model], 6, full_precision_out=True)
        self.shape = MLP(d_model, [d_model, d_model], 10, full_precision_out=True)
        self.register_buffer("identity_6d", torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]), persistent=False)

    def predict_raw_6d(self) -> None:
        """Predict the raw 6D code (the reference's head) instead of an offset from the identity's code."""
        self.identity_6d.zero_()

    def forward(self, queries: torch.Tensor, mano) -> dict[str, torch.Tensor]:
        L, B = queries.shape[:2]
        code = self.pose(queries[:, :, :16])  # (L, B, 16, 6), full precision
        rotations = rot6d_to_matrix(code + self.identity_6d.to(code.dtype))
        betas = self.shape(queries[:, :, 16])
        verts, joints = wrist_centred_mano(mano, rotations.flatten(0, 1).float(), betas.flatten(0, 1).float())
        return {"rotations": rotations, "betas": betas,
                "verts": verts.view(L, B, *verts.shape[1:]), "joints": joints.view(L, B, *joints.shape[1:])}


class ShapeHead(nn.Module):
    """One decoder query (L, B, 1, D) -> betas (L, B, 10) (the inverse-kinematics variant)."""

    def __init__(self, d_model: int):
        super().__init__()
        self.shape = MLP(d_model, [d_model, d_model], 10, full_precision_out=True)

    def forward(self, queries: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"betas": self.shape(queries[:, :, 0])}


def vote_joints(points: torch.Tensor, offsets: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """Joints (L, B, J, 3) = sum over points of softmax_points(logits) * (point + offset).

    points (B, N, 3) metric, root-relative; offsets (L, B, N, J, 3); logits (L, B, N, J).
    """
    weights = torch.softmax(logits.float(), dim=2)
    votes = points[None, :, :, None, :] + offsets.float()
    return (weights[..., None] * votes).sum(dim=2)


class VoteHead(nn.Module):
    """Hand-encoder tokens (L, B, N, D) -> per-point offsets to 20 joints and joint-membership logits."""

    def __init__(self, d_model: int):
        super().__init__()
        self.vote = MLP(d_model, [d_model, d_model, d_model], N_VOTED * 3, full_precision_out=True)
        self.cls = MLP(d_model, [d_model, d_model], N_VOTED, full_precision_out=True)

    def forward(self, tokens: torch.Tensor, points: torch.Tensor) -> dict[str, torch.Tensor]:
        """tokens (L, B, N, D), points (B, N, 3) -> offsets (L,B,N,20,3), logits (L,B,N,20), joints (L,B,20,3)."""
        offsets = self.vote(tokens).unflatten(-1, (N_VOTED, 3))
        logits = self.cls(tokens)
        return {"offsets": offsets, "logits": logits, "joints": vote_joints(points, offsets, logits)}


def with_root(voted: torch.Tensor) -> torch.Tensor:
    """(..., 20, 3) voted joints -> (..., 21, 3) with the wrist (zeros, root-relative) in front."""
    return torch.cat([torch.zeros_like(voted[..., :1, :]), voted], dim=-2)


@full_precision
def chordal_mean(axis_angles: torch.Tensor) -> torch.Tensor:
    """Per-point rotation predictions (B, N, 3) axis-angle -> (B, 3, 3): the rotation closest (Frobenius) to the mean
    of the rotation matrices (SVD projection)."""
    mean = axis_angle_to_matrix(axis_angles.float()).mean(dim=1)
    u, _, vh = torch.linalg.svd(mean)
    fix = torch.ones_like(mean[:, 0])
    fix[:, 2] = torch.sign(torch.linalg.det(u @ vh))
    return u @ torch.diag_embed(fix) @ vh


@full_precision
def axis_angle_mean(axis_angles: torch.Tensor) -> torch.Tensor:
    """Per-point rotation predictions (B, N, 3) axis-angle -> (B, 3, 3): the reference code's mean of the axis-angle
    vectors (only valid for tightly clustered ones)."""
    return axis_angle_to_matrix(axis_angles.float().mean(dim=1))


class ObjectHead(nn.Module):
    """Object-encoder tokens (L, B, N, D) -> per-point axis-angle rotation and translation (metres, relative
    to the object pseudo-centre), each (L, B, N, 3)."""

    def __init__(self, d_model: int):
        super().__init__()
        self.rot = MLP(d_model, [d_model, d_model], 3, full_precision_out=True)
        self.trans = MLP(d_model, [d_model, d_model], 3, full_precision_out=True)

    def forward(self, tokens: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"rot": self.rot(tokens), "trans": self.trans(tokens)}


def density(sdf: torch.Tensor, beta: torch.Tensor, sign: float, beta_min: float | None) -> torch.Tensor:
    """Volume density sigmoid(sign * d / beta) / beta of scaled SDF values; beta floored at beta_min (None: as it is,
    for widths projected onto the floor in place, ``model.beta_floor = "project"``)."""
    b = beta if beta_min is None else beta.clamp(min=beta_min)
    return torch.sigmoid(sign * sdf / b) / b


def masks_to_boxes(prob: torch.Tensor, threshold: float, image_size: int, convention=CENTERS) -> torch.Tensor:
    """Predicted masks (B, h, w) in [0, 1] -> boxes (B, 4) x1, y1, x2, y2 in input-image pixels.

    A mask pixel (j, i) at resolution h covers input pixels around (i + 0.5) * s - 0.5 with s = image_size / w
    (:data:`~hoisdf.model.encoding.CENTERS`), or around i * s' with s' = (image_size - 1) / (w - 1)
    (:data:`~hoisdf.model.encoding.UPSTREAM`: the released code's align_corners=True pixels, see
    :func:`hoisdf.model.encoding.pixel_to_grid`); the box spans the covered area (half a mask pixel beyond the
    outer on-pixels). An empty mask gives the whole image.
    """
    B, h, w = prob.shape
    on = prob > threshold
    cols, rows = on.any(dim=1), on.any(dim=2)  # (B, w), (B, h)
    idx_c = torch.arange(w, device=prob.device).expand(B, w)
    idx_r = torch.arange(h, device=prob.device).expand(B, h)
    big = max(h, w) + 1
    x1 = torch.where(cols, idx_c, big).amin(1)
    x2 = torch.where(cols, idx_c, -1).amax(1)
    y1 = torch.where(rows, idx_r, big).amin(1)
    y2 = torch.where(rows, idx_r, -1).amax(1)
    box = torch.stack([x1, y1, x2 + 1, y2 + 1], dim=1).float()
    box = convention.mask_box(box, image_size, w)
    whole = torch.tensor([-0.5, -0.5, image_size - 0.5, image_size - 0.5], device=prob.device)
    return torch.where(on.flatten(1).any(1)[:, None], box, whole)

