"""MANO forward kinematics as pure tensor functions: no file I/O, no state, no parameters.

Every function works batched, on any device, in float32 or float64, and is differentiable. Shapes use
B for the batch, V for vertices (778 for MANO) and J for the kinematic joints (16 for MANO). Units are
whatever the model file uses (metres for MANO).

The model, following Romero et al. 2017 ("Embodied Hands"):

    v_shaped = v_template + shapedirs . betas
    J        = J_regressor . v_shaped
    v_posed  = v_shaped + posedirs . (R(theta)[1:] - I)
    v        = sum_j w_j G_j(theta, J) v_posed          (linear blend skinning)

where G_j are the world transforms of the joints, relative to their rest positions.
"""

from __future__ import annotations

import torch

from hoidata.geometry.rotation import axis_angle_to_matrix


def blend_shapes(betas: torch.Tensor, shapedirs: torch.Tensor) -> torch.Tensor:
    """Shape offsets: betas (B, S), shapedirs (V, 3, S) -> (B, V, 3)."""
    return torch.einsum("bs,vcs->bvc", betas, shapedirs)


def pose_features(rot_mats: torch.Tensor) -> torch.Tensor:
    """Pose blend-shape input: rotations (B, J, 3, 3) -> (B, (J-1)*9), R - I of the non-root joints."""
    eye = torch.eye(3, dtype=rot_mats.dtype, device=rot_mats.device)
    return (rot_mats[:, 1:] - eye).flatten(1)


def pose_offsets(rot_mats: torch.Tensor, posedirs: torch.Tensor) -> torch.Tensor:
    """Pose-corrective offsets: rotations (B, J, 3, 3), posedirs (V, 3, P) -> (B, V, 3)."""
    return torch.einsum("bp,vcp->bvc", pose_features(rot_mats), posedirs)


def vertices_to_joints(j_regressor: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Regress joints: j_regressor (J, V) dense, vertices (B, V, 3) -> (B, J, 3)."""
    return torch.einsum("jv,bvc->bjc", j_regressor, vertices)


def rigid_transform(rot_mats: torch.Tensor, joints: torch.Tensor, parents: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Chain local joint rotations along the kinematic tree.

    Args:
        rot_mats: (B, J, 3, 3) local rotation of each joint (joint 0 is the global rotation).
        joints: (B, J, 3) rest joint locations.
        parents: length J, parents[0] == -1, and parents[j] < j for every other joint.

    Returns:
        posed_joints: (B, J, 3) joint locations after posing.
        rel_transforms: (B, J, 4, 4) transforms that map a rest-pose point attached to joint j to its
            posed location (world transform with the rest joint location removed), as used by skinning.
    """
    rel_joints = joints.clone()
    rel_joints[:, 1:] = joints[:, 1:] - joints[:, parents[1:]]
    local = to_homogeneous(rot_mats, rel_joints)  # (B, J, 4, 4)
    world = [local[:, 0]]
    for j in range(1, len(parents)):
        world.append(world[parents[j]] @ local[:, j])
    world = torch.stack(world, dim=1)  # (B, J, 4, 4)
    posed_joints = world[:, :, :3, 3]
    # Subtract the rotated rest joint so the transform applies to rest-pose coordinates.
    shift = torch.einsum("bjik,bjk->bji", world[:, :, :3, :3], joints)
    rel = world.clone()
    rel[:, :, :3, 3] = posed_joints - shift
    return posed_joints, rel


def to_homogeneous(rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Rotations (..., 3, 3) and translations (..., 3) -> 4x4 transforms (..., 4, 4)."""
    top = torch.cat([rot, trans[..., None]], dim=-1)  # (..., 3, 4)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=rot.dtype, device=rot.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def skin(vertices: torch.Tensor, weights: torch.Tensor, rel_transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning: rest vertices (B, V, 3), weights (V, J), transforms (B, J, 4, 4) -> (B, V, 3)."""
    blended = torch.einsum("vj,bjik->bvik", weights, rel_transforms)  # (B, V, 4, 4)
    return torch.einsum("bvik,bvk->bvi", blended[..., :3, :3], vertices) + blended[..., :3, 3]


def lbs(
    pose: torch.Tensor,
    betas: torch.Tensor,
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    posedirs: torch.Tensor,
    j_regressor: torch.Tensor,
    parents: list[int],
    weights: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Full MANO forward in the model's own frame (no translation).

    Args:
        pose: (B, J*3) axis-angle per joint, joint 0 global, or (B, J, 3, 3) rotation matrices; the hand-mean
            offset must already be added.
        betas: (B, S) shape coefficients.
        v_template: (V, 3); shapedirs: (V, 3, S); posedirs: (V, 3, (J-1)*9); j_regressor: (J, V);
        parents: kinematic tree (length J); weights: (V, J) skinning weights.

    Returns:
        vertices (B, V, 3), joints (B, J, 3) posed, and rel_transforms (B, J, 4, 4).
    """
    batch = pose.shape[0]
    v_shaped = v_template[None] + blend_shapes(betas, shapedirs)
    rest_joints = vertices_to_joints(j_regressor, v_shaped)
    rot_mats = pose if pose.ndim == 4 else axis_angle_to_matrix(pose.reshape(batch, -1, 3))
    v_posed = v_shaped + pose_offsets(rot_mats, posedirs)
    joints, rel = rigid_transform(rot_mats, rest_joints, parents)
    return skin(v_posed, weights, rel), joints, rel
