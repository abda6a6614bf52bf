"""Inverse kinematics: 21 hand joints + MANO betas -> MANO pose (the "MANO shape + IK" variant).

Upstream's solver: docs/upstream.md, "The inverse-kinematics regressor".

Method (batched, after gSDF / upstream ``ik_solver_mano``):

1. Template joints: the MANO forward at zero pose with the given betas (21 joints, tips included), wrist-relative.
2. Global rotation: Kabsch/SVD aligning the template's five wrist->MCP vectors to the target's (no centring:
   the wrist is the pivot), with the reflection fix (det = +1). Upstream skips reflected samples instead.
3. Along each finger chain (all five fingers at once, one level at a time), the local rotation of a joint is the
   minimal rotation (axis = cross product, angle = atan2(|cross|, dot)) taking the template bone to the vector
   from the joint's *reconstructed* position (the template bones posed so far) to the target child joint,
   expressed in the parent's accumulated frame, as upstream's ``ik_solver_mano`` aims it; the accumulated frame
   and the reconstructed position are updated with it. Aiming along the target bone instead ignores the
   position error accumulated up the chain: with the toy MANO, 256 random poses, 3 mm joint noise and betas off
   by N(0, 0.5) it left 7.02 mm mean joint error against 6.29 mm (N(0, 1): 8.64 vs 7.64 mm).

The twist of each bone about its own axis is not observable from joints, so the minimal-rotation solution
reproduces the joint positions (exactly for the 16 MANO joints when the palm is rigid), not the pose itself.
Units: metres; output in the flat-hand-mean axis-angle convention of :class:`hoidata.hand.MANO`.
"""

from __future__ import annotations

import math

import torch

from hoidata.geometry.rotation import axis_angle_to_matrix, matrix_to_axis_angle
from hoidata.hand.model import MANO_TO_DEXYCB
from hoisdf.model.precision import full_precision

# DexYCB order: 0 wrist, then thumb, index, middle, ring, little with 4 joints each (MCP, PIP, DIP, tip).
MCP_DEXYCB = [1, 5, 9, 13, 17]


def kabsch_rotation(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Rotation R (B, 3, 3) minimising sum_i |R s_i - t_i|^2 for vectors (B, N, 3) (no centring), det(R) = +1."""
    h = source.transpose(1, 2) @ target  # (B, 3, 3) = sum_i s_i t_i^T
    u, _, vh = torch.linalg.svd(h)
    v = vh.transpose(1, 2)
    sign = torch.sign(torch.linalg.det(v @ u.transpose(1, 2)))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    fix = torch.ones(h.shape[0], 3, dtype=h.dtype, device=h.device)
    fix = torch.cat([fix[:, :2], sign[:, None]], dim=1)
    return v @ torch.diag_embed(fix) @ u.transpose(1, 2)


def minimal_rotation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Axis-angle (..., 3) of the smallest rotation turning direction ``a`` (..., 3) into direction ``b``.

    Angle = atan2(|a x b|, a . b) in [0, pi]; for (nearly) opposite vectors the axis is any unit vector
    perpendicular to ``a``. Zero-length inputs give the zero rotation.
    """
    tiny = torch.finfo(a.dtype).tiny
    a = a / a.norm(dim=-1, keepdim=True).clamp_min(tiny)
    b = b / b.norm(dim=-1, keepdim=True).clamp_min(tiny)
    cross = torch.linalg.cross(a, b, dim=-1)
    s = cross.norm(dim=-1, keepdim=True)
    c = (a * b).sum(-1, keepdim=True)
    angle = torch.atan2(s, c)
    aa = cross * (angle / s.clamp_min(tiny))
    # Opposite directions: the cross product carries no reliable axis; rotate by pi about a perpendicular.
    opposite = (c < 0) & (s < math.sqrt(torch.finfo(a.dtype).eps))
    basis = torch.eye(3, dtype=a.dtype, device=a.device)[a.abs().argmin(dim=-1)]
    perp = torch.linalg.cross(a, basis, dim=-1)
    perp = perp / perp.norm(dim=-1, keepdim=True).clamp_min(tiny)
    return torch.where(opposite, perp * angle, aa)


@full_precision
def solve_ik(joints: torch.Tensor, betas: torch.Tensor, mano) -> torch.Tensor:
    """MANO pose reproducing 21 target joints with the given shape.

    Args:
        joints: (B, 21, 3) metres, DexYCB order, root-relative (the wrist is subtracted again here anyway).
        betas: (B, 10) MANO shape used for the template (e.g. the network's predicted betas).
        mano: the project's MANO layer (:func:`hoidata.hand.load_mano`); called once at zero pose.

    Returns:
        pose: (B, 48) flat-hand-mean axis-angle in MANO joint order (joint 0 = global rotation), dtype/device
        of ``joints``. ``mano(pose, betas).joints`` minus its wrist reproduces ``joints`` minus its wrist.
    """
    if joints.ndim != 3 or joints.shape[1:] != (21, 3):
        raise ValueError(f"joints: expected (B, 21, 3), got {tuple(joints.shape)}")
    batch = joints.shape[0]
    zero = torch.zeros(batch, 48, dtype=joints.dtype, device=joints.device)
    template = mano(zero, betas).joints.to(joints)
    template = template - template[:, :1]
    target = joints - joints[:, :1]

    pose = joints.new_zeros(batch, 16, 3)
    rot_global = kabsch_rotation(template[:, MCP_DEXYCB], target[:, MCP_DEXYCB])
    pose[:, 0] = matrix_to_axis_angle(rot_global)

    frame = rot_global[:, None].expand(batch, 5, 3, 3)  # accumulated rotation of each finger's parent joint
    position = (rot_global[:, None] @ template[:, MCP_DEXYCB, :, None])[..., 0]  # reconstructed MCPs (B, 5, 3)
    for level in range(3):  # MCP, PIP, DIP of all five fingers at once
        joint_ids = [m + level for m in MCP_DEXYCB]
        child_ids = [j + 1 for j in joint_ids]
        bone_template = template[:, child_ids] - template[:, joint_ids]  # (B, 5, 3) rest frame
        aim = target[:, child_ids] - position  # (B, 5, 3) world frame: reconstructed joint -> target child
        local_target = (frame.transpose(-1, -2) @ aim[..., None])[..., 0]
        aa = minimal_rotation(bone_template, local_target)
        pose[:, [MANO_TO_DEXYCB[j] for j in joint_ids]] = aa
        frame = frame @ axis_angle_to_matrix(aa)
        position = position + (frame @ bone_template[..., None])[..., 0]
    return pose.reshape(batch, 48)
