"""Build :class:`hoisdf.model.HOISDF` from :class:`hoisdf.config.ModelSettings`: every setting string is read
here, once, and becomes a part (a module, a class or a function); the model itself compares no strings.

Construction order is fixed: it decides the random initial weights for a seed and the parameter order of the
state dict and of the optimizer.
"""

from __future__ import annotations

from hoisdf.model import heads as H
from hoisdf.model import parts as P
from hoisdf.model.backbone import DECODERS, ResNetUNet
from hoisdf.model.encoding import PIXEL_CONVENTIONS
from hoisdf.model.hoisdf import HOISDF, POINT_DIM
from hoisdf.model.layers import MLP
from hoisdf.model.regressors import REGRESSORS
from hoisdf.model.sampling import ABSOLUTE, GRADIENT, RANDOM, SIGNED, grid_points
from hoisdf.model.sdf_decoder import SDFDecoder, init_sdf_decoder_weights
from hoisdf.model.stages import DensityWidths, PixelFeatures, PoseStage, SDFFields
from hoisdf.model.transformer import TokenEncoder, init_transformer_weights

TRAINING_ROWS = {"absolute": P.near_surface_rows, "gradient": P.near_surface_rows, "signed": P.inside_mesh_rows,
                 "random": P.random_box_rows}
"""``model.sampling`` -> the training-row variant of the query sampler."""
RANKINGS = {"absolute": (ABSOLUTE, ABSOLUTE), "gradient": (ABSOLUTE, GRADIENT), "signed": (SIGNED, SIGNED),
            "random": (RANDOM, RANDOM)}
"""``model.sampling`` -> the field-guided ranking (in training mode, in evaluation mode): "gradient" ranks as
"absolute" in training and steps onto the surface along the full field gradient at inference only."""
CROSS_FIELDS = {"sdf": P.cross_sdf, "image": P.cross_image, "target": P.cross_target, "none": None}
"""``model.cross_field`` -> the cross-field variant (None: no cross tokens)."""
OBJECT_ROTATIONS = {"chordal": H.chordal_mean, "axis_angle": H.axis_angle_mean}
"""``model.object_rotation`` -> the rotation mean of the per-point predictions."""
DENSITY_SIGNS = {"paper": -1.0, "code": 1.0}
"""``model.density_sign`` -> the sign inside the density's sigmoid."""
RAW_6D = {"offset": False, "raw": True}
"""``model.rot6d`` -> whether the MANO head predicts the raw 6D code (the reference) instead of an identity offset."""
REUSE_RANKING_SDF = {"fresh": False, "ranking": True}
"""``model.field_density`` -> whether field-guided tokens take the ranking pass's SDF (the reference, with its dropout
mask) instead of a second decoder pass."""
PROJECT_BETA = {"clamp": False, "project": True}
"""``model.beta_floor`` -> whether the density widths themselves are projected onto [beta_min, inf) at each use
(the reference, ``beta.data.copy_(max(beta.data, 2e-3))``) instead of clamped in the forward only."""
BOXES = {"gt": lambda camera, threshold: P.ground_truth_boxes, "predicted": P.PredictedBoxes}
"""``model.test_boxes`` -> (camera, mask threshold) -> the source of the inference boxes."""


def choose(table: dict, s, key: str):
    """``table[s.<key>]``; a value outside the table is a ValueError naming ``model.<key>`` (for settings that did
    not come through :mod:`hoisdf.config`, which checks the same choices)."""
    value = getattr(s, key)
    if value not in table:
        raise ValueError(f"model.{key} must be one of {tuple(table)}, got {value!r}")
    return table[value]


def token_features(s):
    """The ``model.feature_augmentation`` variant (:mod:`hoisdf.model.parts`) of settings ``s``."""
    sign = choose(DENSITY_SIGNS, s, "density_sign")
    # projected widths are at the floor or above when used: no clamp (whose gradient at the floor itself is zero)
    floor = None if choose(PROJECT_BETA, s, "beta_floor") else s.beta_min
    variants = {"none": P.PlainFeatures(), "density": P.DensityScaled(sign, floor),
                "density_concat": P.Concatenated(True, sign, floor),
                "distance_concat": P.Concatenated(False, sign, floor)}
    return choose(variants, s, "feature_augmentation")


def query_sampler(s) -> P.QuerySampler:
    """The query sampler of settings ``s`` (:data:`TRAINING_ROWS`, :data:`RANKINGS`)."""
    train, evaluation = choose(RANKINGS, s, "sampling")
    return P.QuerySampler(grid_points(s.grid_resolution, s.sheared_grid), s.hand_queries, s.object_queries,
                          s.sdf_scale, s.chunk, s.fixed_shape, choose(TRAINING_ROWS, s, "sampling"), train, evaluation,
                          choose(REUSE_RANKING_SDF, s, "field_density"))


def build_model(settings, mano) -> HOISDF:
    """HOISDF from a ModelSettings dataclass (:mod:`hoisdf.config` validates it on loading) and the MANO layer
    (None: no MANO outputs can be computed, e.g. to read a state dict)."""
    s = settings
    camera = P.Camera(s.image_size, choose(PIXEL_CONVENTIONS, s, "pixel_convention"))
    features = token_features(s)
    sampler = query_sampler(s)
    backbone = ResNetUNet(s.depth, choose(DECODERS, s, "decoder"), s.weights or None, s.freeze_bn_affine,
                          s.normalize_input, s.channels_last)
    feat = sum(backbone.channels)
    sdf_in = MLP(feat, [2 * s.sdf_features], s.sdf_features, relu_last=True)
    # sampling the projected maps reads levels x width channels instead of sum(C): a gain for the big decoder
    # (3968 vs 5 x 512; 2x faster on the CPU, bench/bench_grid_features.py), a loss for the small one (992)
    project_grid = feat > len(backbone.channels) * 2 * s.sdf_features
    token_in = MLP(feat, s.token_hidden, s.d_model - POINT_DIM - features.extra, relu_last=True)
    hand_sdf = SDFDecoder(s.sdf_features, 6 * s.n_freq, s.sdf_hidden, dropout=s.sdf_dropout)
    obj_sdf = SDFDecoder(s.sdf_features, 6 * s.n_freq, s.sdf_hidden, dropout=s.sdf_dropout)
    hand_encoder = TokenEncoder(s.hand_layers, s.d_model, s.heads, s.ff, s.dropout)
    obj_encoder = TokenEncoder(s.object_layers, s.d_model, s.heads, s.ff, s.dropout)
    regressor = choose(REGRESSORS, s, "pose_regressor")(s.d_model, s.decoder_layers, s.heads, s.ff, s.dropout)
    obj_head = H.ObjectHead(s.d_model)
    for module in (hand_encoder, obj_encoder, *regressor.transformers()):
        init_transformer_weights(module)
    if choose(RAW_6D, s, "rot6d"):
        regressor.predict_raw_6d()
    boxes = choose(BOXES, s, "test_boxes")(camera, s.mask_threshold)
    object_rotation = choose(OBJECT_ROTATIONS, s, "object_rotation")
    # upstream's training init of the SDF decoders (zero biases, N(0, 0.01) output layer), drawn last so that every
    # other module keeps the weights a seed gave it before this was wired
    for decoder in (hand_sdf, obj_sdf):
        init_sdf_decoder_weights(decoder)
    widths = DensityWidths(s.beta_init if features.learns_beta else None,
                           s.beta_min if choose(PROJECT_BETA, s, "beta_floor") else None)
    pose = PoseStage(features, choose(CROSS_FIELDS, s, "cross_field"), hand_encoder, obj_encoder, regressor, obj_head,
                     object_rotation, s.sdf_scale, s.n_freq)
    return HOISDF(mano=mano, backbone=backbone, widths=widths,
                  features=PixelFeatures(camera, sdf_in, token_in, project_grid),
                  fields=SDFFields(hand_sdf, obj_sdf, s.sdf_scale, s.sdf_clamp, s.n_freq), sampler=sampler, boxes=boxes,
                  pose=pose)
