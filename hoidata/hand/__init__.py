"""The MANO hand: file loading, batched forward, pose conversions, closed mesh, part labels.

Public entry point::

    from hoidata.hand import load_mano
    mano = load_mano("path/to/mano", side="right")        # MANO_RIGHT.pkl, no chumpy needed
    out = mano(pose, betas, transl)                        # (B,48), (B,10), (B,3) tensors
    out.vertices, out.joints                               # (B,778,3), (B,21,3), metres
"""

from hoidata.hand.model import (
    DEXYCB_TO_MANO,
    MANO,
    MANO_PARENTS,
    MANO_TO_DEXYCB,
    TIP_VERTICES,
    ManoData,
    MANOOutput,
    load_mano,
    read_mano_file,
)
from hoidata.hand.pose import (
    axis_angle_to_pca,
    change_frame,
    flat_to_mean_relative,
    mean_relative_to_flat,
    pca_to_axis_angle,
)

__all__ = [
    "MANO", "MANOOutput", "ManoData", "load_mano", "read_mano_file", "MANO_PARENTS", "MANO_TO_DEXYCB",
    "DEXYCB_TO_MANO", "TIP_VERTICES", "pca_to_axis_angle", "axis_angle_to_pca", "flat_to_mean_relative",
    "mean_relative_to_flat", "change_frame",
]
