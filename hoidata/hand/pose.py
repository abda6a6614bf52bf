"""Exact conversions between MANO pose conventions. Pure functions on numpy arrays or torch tensors.

- *full axis-angle, flat hand mean* (the project's convention, HO-3D ``handPose``): 48 values, the
  45 finger values used as they are;
- *mean-relative* (MANO's ``flat_hand_mean=False``): the 45 finger values are offsets from
  ``hands_mean``, the relaxed mean pose of the MANO scans;
- *PCA* (DexYCB ``pose_m[:, :48]``): 3 global values, then coefficients of the rows of
  ``hands_components`` in the mean-relative convention. With all 45 components the map is invertible.
"""

from __future__ import annotations


def _cat(a, b):
    if hasattr(a, "new_tensor"):
        import torch

        return torch.cat([a, b], dim=-1)
    import numpy as np

    return np.concatenate([a, b], axis=-1)


def _like(ref, x):
    """x as the array type, dtype and device of ref."""
    if hasattr(ref, "new_tensor"):
        import torch

        return torch.as_tensor(x, dtype=ref.dtype, device=ref.device)
    import numpy as np

    return np.asarray(x, dtype=ref.dtype)


def pca_to_axis_angle(pose_pca, hands_components, hands_mean):
    """PCA pose (..., 3 + n) with n <= 45 coefficients -> full flat-hand-mean axis-angle (..., 48).

    full = [global, hands_mean + coeffs @ hands_components[:n]], as the DexYCB toolkit's manopth layer
    (``flat_hand_mean=False, use_pca=True``) computes it internally.
    """
    n = pose_pca.shape[-1] - 3
    if not 0 < n <= 45:
        raise ValueError(f"PCA pose must hold 3 global values and 1..45 coefficients, got {pose_pca.shape[-1]} values")
    comps = _like(pose_pca, hands_components)[:n]
    fingers = pose_pca[..., 3:] @ comps + _like(pose_pca, hands_mean)
    return _cat(pose_pca[..., :3], fingers)


def axis_angle_to_pca(pose, hands_components, hands_mean):
    """Full flat-hand-mean axis-angle (..., 48) -> PCA pose (..., 48) with all 45 coefficients.

    Inverse of :func:`pca_to_axis_angle`; solves with the full basis, so it does not assume the basis
    is orthonormal.
    """
    comps = _like(pose, hands_components)
    rel = pose[..., 3:] - _like(pose, hands_mean)
    if hasattr(pose, "new_tensor"):
        import torch

        coeffs = torch.linalg.solve(comps.T, rel.unsqueeze(-1)).squeeze(-1)
    else:
        import numpy as np

        coeffs = np.linalg.solve(comps.T, rel[..., None])[..., 0]
    return _cat(pose[..., :3], coeffs)


def flat_to_mean_relative(pose, hands_mean):
    """Flat-hand-mean pose (..., 48) -> MANO mean-relative pose (..., 48) (finger values minus the mean)."""
    return _cat(pose[..., :3], pose[..., 3:] - _like(pose, hands_mean))


def mean_relative_to_flat(pose, hands_mean):
    """MANO mean-relative pose (..., 48) -> flat-hand-mean pose (..., 48)."""
    return _cat(pose[..., :3], pose[..., 3:] + _like(pose, hands_mean))


def change_frame(pose, transl, rest_wrist, rotation, translation):
    """Express a MANO pose in another frame x' = rotation @ x + translation (numpy, float64).

    MANO rotates about the rest wrist joint J0 and adds ``transl`` afterwards, so a rigid change of
    frame changes the global rotation *and* the translation: with R_g' = R R_g,
    transl' = R (J0 + transl) + t - J0. J0 depends on the shape: pass the rest wrist of these betas
    (``MANO.rest_joints(betas)[:, 0]``).

    Args:
        pose: (..., 48) axis-angle, joint 0 global; only the first 3 values change.
        transl: (..., 3) MANO translation, metres.
        rest_wrist: (..., 3) rest-pose wrist joint J0 for the betas in use.
        rotation: (3, 3) proper rotation; translation: (3,) metres.

    Returns:
        (pose', transl') with the same shapes.
    """
    import numpy as np
    from scipy.spatial.transform import Rotation

    pose = np.array(pose, dtype=np.float64)
    glob = Rotation.from_rotvec(pose[..., :3].reshape(-1, 3)).as_matrix()
    pose[..., :3] = Rotation.from_matrix(rotation @ glob).as_rotvec().reshape(pose[..., :3].shape)
    new_transl = (np.asarray(rest_wrist) + transl) @ np.asarray(rotation).T + translation - rest_wrist
    return pose, new_transl
