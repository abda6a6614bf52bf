"""A toy UmeTrack hand profile for ``__hand_shapes.json__``'s ``umetrack`` entry.

HOT3D's official reader (hand_tracking_toolkit, ``dataset.SampleDecoder``) builds an UmeTrack hand model from this
entry for every clip it opens, so a clip without a well-formed one cannot be read there at all. The fields are the
reader's: ``joint_rotation_axes`` (22, 3), ``joint_rest_positions`` (22, 3, millimetres), ``joint_frame_index``,
``joint_parent``, ``joint_first_child``, ``joint_next_sibling`` (22 each), ``landmark_rest_positions`` (21, 3,
millimetres), ``landmark_rest_bone_weights`` and ``landmark_rest_bone_indices`` (21, 2). Joints 0-19 are four
degrees of freedom per finger (thumb to pinky: two at the finger's base, then one per further joint), 20 the wrist
and 21 the root; frames are 0 root, 1 wrist and three per finger (the toolkit's 17). Landmarks are in the
toolkit's canonical order (five tips, the wrist, then the finger joints) plus the palm centre.

This is not a fitted UmeTrack hand: the rest positions are the toy MANO hand's rest joints, relative to its wrist,
so the toolkit's UmeTrack forward kinematics runs on the toy, but only MANO poses are used by this project.
"""

from __future__ import annotations

import numpy as np

N_DOF = 20
TIPS = (4, 8, 12, 16, 20)  # DexYCB joint order: wrist, then four joints (base to tip) per finger, thumb first


def _finger_chain(finger: int) -> list[int]:
    """DexYCB joint indices of one finger, base to tip."""
    return [1 + 4 * finger + k for k in range(4)]


def umetrack_profile(rest_joints: np.ndarray) -> dict:
    """The ``umetrack`` entry for a hand whose rest joints (21, 3) in metres (DexYCB order) are given."""
    rest = (np.asarray(rest_joints, float) - rest_joints[0]) * 1000.0  # millimetres about the wrist
    positions = np.zeros((22, 3))
    axes = np.zeros((22, 3))
    frame_index = np.zeros(22, int)
    parent, first_child, next_sibling = (np.full(22, -1) for _ in range(3))
    for finger in range(5):
        chain = _finger_chain(finger)
        for k in range(4):
            j = 4 * finger + k
            positions[j] = rest[chain[max(k - 1, 0)]]  # two degrees of freedom at the base, one per later joint
            axes[j] = (0.0, 1.0, 0.0) if k == 0 else (0.0, 0.0, 1.0)  # spread, then flexion
            frame_index[j] = 2 + 3 * finger + max(k - 1, 0)
            parent[j] = 20 if k == 0 else j - 1
            first_child[j] = j + 1 if k < 3 else -1
        next_sibling[4 * finger] = 4 * (finger + 1) if finger < 4 else -1
    frame_index[20], frame_index[21] = 1, 0
    parent[20], first_child[20], first_child[21] = 21, 0, 20
    landmarks, frames = [], []
    for finger in range(5):  # the tips: the last frame of each finger
        landmarks.append(rest[TIPS[finger]])
        frames.append(4 + 3 * finger)
    landmarks.append(rest[0])
    frames.append(1)
    for finger in range(5):  # the thumb's two inner joints; three joints of every other finger
        chain = _finger_chain(finger)
        for k in ((1, 2) if finger == 0 else (0, 1, 2)):
            landmarks.append(rest[chain[k]])
            frames.append(1 if k == 0 else 2 + 3 * finger + (k - 1) if finger else 1 + 3 * finger + k)
    landmarks.append(rest[[_finger_chain(f)[0] for f in range(1, 5)]].mean(0))  # the palm centre
    frames.append(1)
    indices = np.stack([np.array(frames), np.zeros(len(frames), int)], 1)
    weights = np.stack([np.ones(len(frames)), np.zeros(len(frames))], 1)
    return {"joint_rotation_axes": axes.tolist(), "joint_rest_positions": positions.tolist(),
            "joint_frame_index": frame_index.tolist(), "joint_parent": parent.tolist(),
            "joint_first_child": first_child.tolist(), "joint_next_sibling": next_sibling.tolist(),
            "landmark_rest_positions": np.array(landmarks).tolist(), "landmark_rest_bone_weights": weights.tolist(),
            "landmark_rest_bone_indices": indices.tolist()}
