"""Left <-> right mirroring: the one reflection every label goes through.

Mirroring is the reflection x -> -x in the camera (or model) frame, M = diag(-1, 1, 1). It maps a left
hand onto a right hand and back, and equals flipping the image horizontally when the principal point
moves to ``width - 1 - cx`` (image and intrinsics helpers join this module with the crop code).

What each quantity becomes under M:

- points (..., 3): x negated;
- rotation matrices R: M R M;
- axis-angle vectors r (axial vectors): det(M) M r = (r_x, -r_y, -r_z), so a MANO pose (48 values) is
  mirrored joint by joint, and the same holds for PCA hand-pose bases expressed in axis-angle;
- rigid transforms [R | t]: [M R M | M t];
- triangle meshes: vertices mirrored, each face's vertex order reversed (a reflection turns an outward
  winding inward).

Every function is its own inverse and works on numpy arrays and torch tensors.
"""

from __future__ import annotations


def _sign(x, pattern):
    """A sign vector broadcastable against x's last axis, as numpy or torch like x."""
    n = x.shape[-1]
    signs = [pattern[i % len(pattern)] for i in range(n)]
    if hasattr(x, "new_tensor"):
        return x.new_tensor(signs)
    import numpy as np

    return np.asarray(signs, dtype=x.dtype)


def mirror_points(points):
    """Points (..., 3) in metres -> mirrored points (..., 3)."""
    return points * _sign(points, (-1.0, 1.0, 1.0))


def mirror_mesh(vertices, faces):
    """(vertices (V, 3), faces (F, 3)) -> the mirror-image mesh, faces reversed so they stay outward wound."""
    flipped = faces.flip(-1) if hasattr(faces, "flip") else faces[:, ::-1].copy()
    return mirror_points(vertices), flipped


def mirror_axis_angle(pose):
    """Axis-angle vectors packed along the last axis (..., 3K) -> mirrored (..., 3K).

    Works for a single rotation (3), a MANO pose (48) and the 45 finger values or a PCA basis whose
    rows are 45-vectors of axis-angle components.
    """
    if pose.shape[-1] % 3:
        raise ValueError(f"axis-angle data must have a multiple of 3 values on its last axis, got {pose.shape}")
    return pose * _sign(pose, (1.0, -1.0, -1.0))


def mirror_rotation(rot):
    """Rotation matrices (..., 3, 3) -> M R M (..., 3, 3)."""
    row = _sign(rot, (-1.0, 1.0, 1.0))
    return rot * row[:, None] * row[None, :]


def mirror_transform(transform):
    """Rigid transforms (..., 4, 4) [R | t] -> [M R M | M t] (..., 4, 4)."""
    out = transform.clone() if hasattr(transform, "clone") else transform.copy()
    out[..., :3, :3] = mirror_rotation(transform[..., :3, :3])
    out[..., :3, 3] = mirror_points(transform[..., :3, 3])
    return out


def mirror_intrinsics(K, width: int):
    """Intrinsics (3, 3) of a horizontally flipped image of `width` pixels: cx -> width - 1 - cx.

    With points mirrored by :func:`mirror_points`, u' = fx (-x / z) + (W - 1 - cx) = W - 1 - u, which is
    exactly where ``image[:, ::-1]`` puts pixel u.
    """
    out = K.clone() if hasattr(K, "clone") else K.copy()
    out[..., 0, 2] = width - 1 - K[..., 0, 2]
    return out


def mirror_pixels(uv, width: int):
    """Pixel coordinates (..., 2) in a horizontally flipped image of `width` pixels."""
    out = uv.clone() if hasattr(uv, "clone") else uv.copy()
    out[..., 0] = width - 1 - uv[..., 0]
    return out
