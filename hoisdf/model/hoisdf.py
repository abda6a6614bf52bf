"""HOISDF: image -> global hand and object SDFs -> field-guided query points -> transformers -> poses.

Data flow of :meth:`HOISDF.forward` (B batch, Nh / No hand / object query points, S input size):

1. ``ResNetUNet``: image (B, 3, S, S) -> feature pyramid (5 levels) + 2D heads (heatmap, hand and object
   mask logits at S/2).
2. Pixel-aligned features of any camera-frame point: its projection samples every pyramid level.
   ``sdf_in`` (-> sdf_features, 256) feeds the SDF decoders, ``token_in`` (-> d_model - 33) the transformer tokens.
3. SDF decoders (hand, object): scaled SDF (metric x ``sdf_scale``) clamped to +-``sdf_clamp``.
4. Query points: near-surface ground-truth rows + noise ("gt", training) or the grid points of smallest
   |SDF| inside the 2D boxes ("field").
5. Tokens [xyz (3), Fourier (30), feature x density] for own and cross fields; a hand transformer
   (encoder + MANO-query decoder) and an object transformer (encoder); heads (MANO, voting, object).

The model is eight keyword parts (:func:`hoisdf.model.build_model` builds them): the backbone, the density widths,
the pixel features, the SDF fields, the query sampler, the inference boxes, the pose stage (:mod:`hoisdf.model.stages`)
and MANO. The variants of the paper's ablations (query sampling, feature augmentation, cross field, hand regressor,
inference boxes) and the conventions (pixels, rotation mean, density sign) are objects inside those parts
(:mod:`hoisdf.model.parts`, :mod:`hoisdf.model.regressors`); nothing in :mod:`hoisdf.model` compares a setting
string.

Outputs are metres; hand outputs are relative to the (given) hand root, the object translation is
absolute (camera frame).
"""

from __future__ import annotations

import torch
from torch import nn

from hoisdf.model.encoding import project_pyramid
from hoisdf.model.precision import full
from hoisdf.model.sampling import jitter

POINT_DIM = 33  # xyz (3) + Fourier code (30) of every token
POINT_MODES = {"gt": True, "field": False}  # forward(points=...): ground-truth guided?
STATE_RENAMES = {
    "sdf_in.": "features.sdf_in.", "token_in.": "features.token_in.", "hand_sdf.": "fields.hand_sdf.",
    "obj_sdf.": "fields.obj_sdf.", "hand_beta": "widths.hand_beta", "obj_beta": "widths.obj_beta",
    "hand_encoder.": "pose.hand_encoder.", "obj_encoder.": "pose.obj_encoder.",
    "hand_decoder.": "pose.regressor.hand_decoder.", "mano_head.": "pose.regressor.mano_head.",
    "vote_head.": "pose.regressor.vote_head.", "shape_head.": "pose.regressor.shape_head.",
    "obj_head.": "pose.obj_head."}
"""State-dict prefixes of the flat model (run folders before the model was grouped into stages) -> today's."""


def renamed_state(state: dict) -> dict:
    """A state dict with the flat model's keys (:data:`STATE_RENAMES`) renamed to today's; today's keys unchanged.
    The order of the entries is kept (it is the parameter order both layouts share)."""
    def rename(key: str) -> str:
        for old, new in STATE_RENAMES.items():
            if key == old or (old.endswith(".") and key.startswith(old)):
                return new + key[len(old):]
        return key
    return {rename(key): value for key, value in state.items()}


class HOISDF(nn.Module):
    """The full model, composed of parts that :func:`hoisdf.model.build_model` builds from the settings.

    Args (keyword only):
        mano: the project's right-hand MANO layer, used by the MANO head and the IK variant; kept out of the state
            dict (its data is licensed and belongs to the user, not to checkpoints).
        backbone: image (B, 3, S, S) -> (feature pyramid, 2D maps (B, 3, S/2, S/2)); ``channels`` per level.
        widths: the learned density widths of the hand and object tokens (:class:`hoisdf.model.stages.DensityWidths`).
        features: pixel-aligned features of points and their maps into the decoders and the tokens
            (:class:`hoisdf.model.stages.PixelFeatures`).
        fields: the hand and object SDF decoders (:class:`hoisdf.model.stages.SDFFields`).
        sampler: the query sampler (:class:`hoisdf.model.parts.QuerySampler`).
        boxes: (batch, 2D maps) -> (hand box, object box) (B, 4) that filter the inference grid.
        pose: tokens -> transformers -> hand regressor and object head (:class:`hoisdf.model.stages.PoseStage`).
    """

    def __init__(self, *, mano, backbone: nn.Module, widths, features, fields, sampler, boxes, pose):
        super().__init__()
        self._mano = [mano]  # a list: not a registered submodule, so not in state_dict()
        self.boxes = boxes
        # registration order = parameter order (the optimizer state of checkpoints): the flat model's, whose widths
        # were its own parameters (first), then backbone, sdf_in, token_in, SDF decoders, encoders, hand heads, obj_head
        self.sampler, self.widths = sampler, widths
        self.backbone, self.features, self.fields, self.pose = backbone, features, fields, pose

    @property
    def mano(self):
        return self._mano[0]

    @property
    def grid(self) -> torch.Tensor:
        """(G, 3) scaled inference lattice."""
        return self.sampler.grid

    @property
    def fixed_shape(self) -> bool:
        """Whether field-guided sampling decodes the whole grid (static shapes; set it on ``sampler``)."""
        return self.sampler.fixed_shape

    @property
    def scale(self) -> float:
        """metres -> scaled units (``sdf_scale``)."""
        return self.fields.scale

    @property
    def clamp(self) -> float:
        """SDF clamp, scaled units."""
        return self.fields.clamp

    # --- fields -------------------------------------------------------------------------------------------
    def _sdf_fn(self, decoder, pyramid, K, center, detach=True, clamp=True):
        """camera points (B, M, 3) -> scaled SDF (B, M) of ``decoder`` (clamped unless ``clamp=False``), for a few
        hundred points.

        ``detach=False``: a function of the points through both the point code and the image features (the
        full field gradient)."""
        def fn(points_cam):
            feature = self.features.sdf_in(self.features.sample(pyramid, points_cam, K, detach))
            return self.fields.field(decoder, feature, (points_cam - center[:, None]) * self.scale, clamp)
        return fn

    def _grid_sdf_fn(self, decoder, projected, K, center):
        """As :meth:`_sdf_fn` (unclamped) for many points: ``sdf_in``'s first layer was applied to the pyramid
        (exact)."""
        first, rest = self.features.sdf_in.layers[0], self.features.sdf_in.layers[1:]

        def fn(points_cam):
            feature = rest(self.features.camera.projected(projected, points_cam, K, first.bias))
            return self.fields.field(decoder, feature, (points_cam - center[:, None]) * self.scale, clamp=False)
        return fn

    # --- query points -------------------------------------------------------------------------------------
    def _training_points(self, batch, K, root, center, boxes, generator):
        """Scaled ground-truth guided points of the sampling variant (see :class:`~hoisdf.model.parts.QuerySampler`)."""
        return self.sampler.training_points(batch, K, root, center, boxes, generator)

    def _field_points(self, pyramid, K, root, center, boxes, generator):
        """Scaled field-guided points, ranked by the unclamped SDF (as the reference: clamping would tie every
        point beyond the clamp)."""
        hand_sdf, obj_sdf = self.fields.hand_sdf, self.fields.obj_sdf
        newton = (None, None)
        if self.sampler.uses_newton():
            newton = (self._sdf_fn(hand_sdf, pyramid, K, root, detach=False),
                      self._sdf_fn(obj_sdf, pyramid, K, center, detach=False))
        if self.features.project_grid:
            projected = project_pyramid(pyramid, self.features.sdf_in.layers[0])
            fns = (self._grid_sdf_fn(hand_sdf, projected, K, root), self._grid_sdf_fn(obj_sdf, projected, K, center))
        else:
            fns = (self._sdf_fn(hand_sdf, pyramid, K, root, clamp=False),
                   self._sdf_fn(obj_sdf, pyramid, K, center, clamp=False))
        return self.sampler.field_points(K, root, center, boxes, fns, newton, generator)

    def _query_points(self, batch, pyramid, K, root, center, boxes, mode, noise, generator):
        """Scaled query points (hand rel. root (B, Nh, 3), object rel. centre (B, No, 3)); ``mode``: "gt"
        (training rows + uniform noise of half-width ``noise``) or "field"."""
        return self._queries(batch, pyramid, K, root, center, boxes, mode, noise, generator)[:2]

    def _queries(self, batch, pyramid, K, root, center, boxes, mode, noise, generator):
        """As :meth:`_query_points`, and the points' SDFs (B, Nh), (B, No) from the ranking pass (None: "gt"
        points, or not the sampler's ``reuse_ranking_sdf``)."""
        if mode not in POINT_MODES:
            raise ValueError(f"points must be one of {tuple(POINT_MODES)}, got {mode!r}")
        if POINT_MODES[mode]:
            hand, obj = self._training_points(batch, K, root, center, boxes, generator)
            return jitter(hand, noise, generator), jitter(obj, noise, generator), None
        (hand, obj), ranked = self._field_points(pyramid, K, root, center, boxes, generator)
        return hand, obj, (ranked if self.sampler.reuse_ranking_sdf else None)

    # --- forward ------------------------------------------------------------------------------------------
    def forward(self, batch: dict, points: str = "field", noise: float = 0.0,
                generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """Run the model on an augmented batch (see :mod:`hoisdf.data.augment`).

        Uses ``img``, ``K``, ``hand_root``, ``obj_center``, boxes; with ``points="gt"`` also the near rows
        ``hand_near_points`` / ``obj_near_points`` (+ uniform noise of half-width ``noise``, scaled units);
        if present, ``hand_points`` / ``obj_points`` get SDF predictions for the SDF loss.
        See :data:`OUTPUTS` for the returned tensors.
        """
        mano = self.mano
        if mano.v_template.device != batch["img"].device:
            mano.to(batch["img"].device)
        K, root, center = batch["K"], batch["hand_root"], batch["obj_center"]
        pyramid, maps = self.backbone(batch["img"])
        out = {"heatmap": maps[:, 0:1], "hand_mask_logits": maps[:, 1:2], "obj_mask_logits": maps[:, 2:3]}
        if "hand_points" in batch:
            out["hand_sdf"] = self._sdf_fn(self.fields.hand_sdf, pyramid, K, root)(batch["hand_points"] + root[:, None])
        if "obj_points" in batch:
            out["obj_sdf"] = self._sdf_fn(self.fields.obj_sdf, pyramid, K, center)(batch["obj_points"] + root[:, None])
        hp, op, ranked = self._queries(batch, pyramid, K, root, center, self.boxes(batch, maps), points, noise,
                                       generator)
        out.update(self._pose(pyramid, K, root, center, hp, op, ranked))
        return out

    def _pose(self, pyramid, K, root, center, hp, op, ranked=None) -> dict[str, torch.Tensor]:
        fields, features = self.fields, self.features
        hand_cam, obj_cam = hp / self.scale + root[:, None], op / self.scale + center[:, None]
        f_hand, f_obj = features.sample(pyramid, hand_cam, K), features.sample(pyramid, obj_cam, K)
        sdf_in_h, sdf_in_o = features.sdf_in(f_hand), features.sdf_in(f_obj)
        tok_h, tok_o = features.token_in(f_hand), features.token_in(f_obj)
        hand_in_obj, obj_in_hand = (hand_cam - center[:, None]), (obj_cam - root[:, None])
        with torch.no_grad():
            if ranked is None:
                d_h = fields.field(fields.hand_sdf, sdf_in_h, hp)
                d_o = fields.field(fields.obj_sdf, sdf_in_o, op)
            else:  # the ranking pass's values, clamped as the field's
                d_h, d_o = (full(d).clamp(-self.clamp, self.clamp) for d in ranked)
            d_ho = fields.field(fields.obj_sdf, sdf_in_h, hand_in_obj * self.scale)  # hand points, object field
            d_oh = fields.field(fields.hand_sdf, sdf_in_o, obj_in_hand * self.scale)  # object points, hand field
        out = {"hand_query": hp / self.scale, "hand_query_sdf": d_h / self.scale,
               "obj_query": op / self.scale, "obj_query_sdf": d_o / self.scale}
        out.update(self.pose((tok_h, tok_o), (d_h, d_o, d_ho, d_oh), self.widths(),
                             (hp / self.scale, op / self.scale, hand_in_obj, obj_in_hand), center, self.mano))
        return out


OUTPUTS = """
heatmap (B,1,S/2,S/2) raw summed joint heatmap (target scale 0..255); hand_mask_logits, obj_mask_logits (B,1,S/2,S/2)
hand_sdf (B,n) / obj_sdf (B,n): scaled SDF at the batch's hand_points / obj_points (when given)
hand_query (B,Nh,3) m rel. root, hand_query_sdf (B,Nh) m; obj_query (B,No,3) m rel. obj_center, obj_query_sdf (B,No) m
vote_offsets (L,B,Nh,20,3), vote_logits (L,B,Nh,20), vote_joints (L,B,20,3)   [not with pose_regressor=mano_only]
rotations (L,B,16,3,3), betas (L,B,10), mano_verts (L,B,778,3), mano_joints (L,B,21,3)   [mano, mano_only]
betas (L,B,10), ik_pose (B,48)   [ik]
joints (B,21,3), verts (B,778,3) [not voting]: final hand, m, relative to the hand root (DexYCB joint order)
obj_rot_points, obj_trans_points (L,B,No,3): per-point object rotation (axis-angle) and translation rel. obj_center
obj_rotation (B,3,3), obj_translation (B,3): the object pose, model -> camera, metres
"""
