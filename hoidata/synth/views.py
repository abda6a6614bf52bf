"""Perturbing a grasp and choosing a new view of it: pure numpy functions for render-synthetic.

Follows the one public description of HO-3D-style synthesis (ArtiBoost; docs/upstream.md,
"HO-3D-style synthesis (ArtiBoost)"): viewpoints uniform over the sphere (u = cos(polar) uniform in
[-1, 1], azimuth uniform), an in-plane roll uniform in [0, 2 pi), and the point midway between the object
centre and the hand's middle knuckle placed on the optical axis at a depth uniform in [0.45, 0.55] m;
per-joint noise on the rotation angle of each finger joint, and a small translation noise on the hand.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# HO-3D v2's cameras (camMat of its sequences): about 614-617 px focal length, principal point near
# the centre of the 640x480 image.
HO3D_SIZE = (640, 480)


def ho3d_intrinsics(rng: np.random.Generator) -> np.ndarray:
    """K (3, 3) like HO-3D's cameras, slightly different per render."""
    f = rng.uniform(610.0, 620.0)
    return np.array([[f, 0.0, 320.0 + rng.uniform(-8.0, 8.0)], [0.0, f, 240.0 + rng.uniform(-6.0, 6.0)], [0.0, 0.0, 1.0]])


def sample_view_rotation(rng: np.random.Generator) -> np.ndarray:
    """Rotation (3, 3) object -> camera: a uniform direction on the sphere, then an in-plane roll."""
    u, theta, roll = rng.uniform(-1.0, 1.0), rng.uniform(0.0, 2 * np.pi), rng.uniform(0.0, 2 * np.pi)
    s = np.sqrt(1.0 - u * u)
    view_dir = np.array([s * np.cos(theta), s * np.sin(theta), u])  # from the object towards the camera
    z = -view_dir  # the camera looks back at the object along its +z
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    look = np.stack([x, y, z])  # rows: camera axes in object coordinates
    return Rotation.from_rotvec([0.0, 0.0, roll]).as_matrix() @ look


def place_on_axis(rotation: np.ndarray, centre: np.ndarray, depth: float) -> np.ndarray:
    """Translation t (3,) so that `centre` (object frame) lands at (0, 0, depth) in the camera."""
    return np.array([0.0, 0.0, depth]) - rotation @ centre


def perturb_pose(pose: np.ndarray, rng: np.random.Generator, angle_sigma: float = 0.1) -> np.ndarray:
    """Add N(0, angle_sigma) rad to the rotation angle of each finger joint (pose (48,), joint 0 kept).

    A joint at rest (angle ~0) has no axis to lengthen; it gets a random axis instead.
    """
    out = np.array(pose, dtype=np.float64)
    joints = out[3:].reshape(15, 3)
    angles = np.linalg.norm(joints, axis=1)
    axes = np.where(angles[:, None] > 1e-6, joints / np.maximum(angles, 1e-12)[:, None], 0.0)
    random_axes = rng.normal(size=(15, 3))
    random_axes /= np.linalg.norm(random_axes, axis=1, keepdims=True)
    axes = np.where(angles[:, None] > 1e-6, axes, random_axes)
    noise = rng.normal(0.0, angle_sigma, size=15)
    out[3:] = (axes * (angles + noise)[:, None]).reshape(45)
    return out
