"""Rigid transforms as HOT3D-Clips writes them: a unit quaternion (w, x, y, z) and a translation. Pure numpy.

The order is w first (docs/datasets.md, "HOT3D-Clips": the format's key is ``quaternion_wxyz`` and the official
reader reorders it before scipy, whose ``from_quat`` takes x, y, z, w).
"""

from __future__ import annotations

import numpy as np


def quaternion_wxyz_to_matrix(q) -> np.ndarray:
    """Quaternion (4,) (w, x, y, z), any non-zero norm -> rotation matrix (3, 3). A zero quaternion is a ValueError."""
    w, x, y, z = np.asarray(q, np.float64).reshape(4)
    n = w * w + x * x + y * y + z * z
    if not n > 0:
        raise ValueError("quaternion of zero length")
    s = 2.0 / n
    return np.array([
        [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
    ])


def matrix_to_quaternion_wxyz(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (4,) (w, x, y, z) with w >= 0."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(rot, np.float64)).as_quat()  # scipy: scalar last
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def se3_from_wxyz(quaternion_wxyz, translation_xyz) -> np.ndarray:
    """(4, 4) transform [R(q) | t] from a (w, x, y, z) quaternion and a (3,) translation (metres)."""
    out = np.eye(4)
    out[:3, :3] = quaternion_wxyz_to_matrix(quaternion_wxyz)
    out[:3, 3] = np.asarray(translation_xyz, np.float64).reshape(3)
    return out


def se3_to_wxyz(transform: np.ndarray) -> dict:
    """(4, 4) rigid transform -> ``{"quaternion_wxyz": [4], "translation_xyz": [3]}`` (HOT3D's JSON form)."""
    t = np.asarray(transform, np.float64)
    return {"quaternion_wxyz": matrix_to_quaternion_wxyz(t[:3, :3]).tolist(), "translation_xyz": t[:3, 3].tolist()}
