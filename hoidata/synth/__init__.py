"""Synthetic hand-object interaction: physical contact checks and grasp synthesis.

Public entry points::

    from hoidata.synth import synthesize_grasp, penetration_depth, HandObjectCollision
    grasp = synthesize_grasp(mano, obj_vertices, obj_faces, np.random.default_rng(0))
    out = mano(torch.as_tensor(grasp.pose)[None], torch.as_tensor(grasp.betas)[None],
               torch.as_tensor(grasp.transl)[None])   # the hand in the object's frame, metres
"""

from hoidata.synth.closing import (
                                   CONTACT_JOINTS,
                                   FINGER_JOINTS,
                                   FINGERS,
                                   close_fingers,
                                   finger_basis,
)
from hoidata.synth.contact import (
                                   HandObjectCollision,
                                   mesh_bvh,
                                   object_in_hand_depth,
                                   penetration_depth,
                                   signed_distance,
                                   surface_samples,
)
from hoidata.synth.grasp import Grasp, evaluate_grasp, palm_frame, synthesize_grasp

__all__ = [
    "FINGERS", "FINGER_JOINTS", "CONTACT_JOINTS", "close_fingers", "finger_basis",
    "HandObjectCollision", "penetration_depth", "object_in_hand_depth", "signed_distance", "mesh_bvh", "surface_samples",
    "Grasp", "synthesize_grasp", "evaluate_grasp", "palm_frame",
]
