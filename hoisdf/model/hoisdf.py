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

The variants of the paper's ablations (query sampling, feature augmentation, cross field, hand regressor, inference
boxes) are parts that :func:`hoisdf.model.build_model` picks from the settings (:mod:`hoisdf.model.parts`,
:mod:`hoisdf.model.regressors`); the model composes them and compares no setting strings.

Outputs are metres; hand outputs are relative to the (given) hand root, the object translation is
absolute (camera frame).
"""

from __future__ import annotations

import torch
from torch import nn

from hoisdf.model.encoding import fourier_encode, project_pyramid
from hoisdf.model.precision import full
from hoisdf.model.sampling import jitter

POINT_DIM = 33  # xyz (3) + Fourier code (30) of every token
POINT_MODES = {"gt": True, "field": False}  # forward(points=...): ground-truth guided?


class HOISDF(nn.Module):
    """The full model, composed of parts that :func:`hoisdf.model.build_model` builds from the settings.

    Args:
        mano: the project's right-hand MANO layer, used by the MANO head and the IK variant; kept out of the state
            dict (its data is licensed and belongs to the user, not to checkpoints).
        backbone: image (B, 3, S, S) -> (feature pyramid, 2D maps (B, 3, S/2, S/2)); ``channels`` per level.
        sdf_in: pixel feature (B, N, C) -> SDF-decoder feature (B, N, sdf_features).
        token_in: pixel feature (B, N, C) -> token feature (B, N, d_model - 33 - token_features.extra).
        hand_sdf: the hand SDF decoder (:class:`hoisdf.model.sdf_decoder.SDFDecoder`).
        obj_sdf: the object SDF decoder.
        hand_encoder: the hand token encoder.
        obj_encoder: the object token encoder.
        hand_heads: name -> module of the hand regressor (registered under these names: the state-dict keys).
        obj_head: the object pose head.
        regressor: the hand regressor variant (:mod:`hoisdf.model.regressors`).
        sampler: the query sampler (:class:`hoisdf.model.parts.QuerySampler`).
        camera: pixel-aligned sampling (:class:`hoisdf.model.parts.Camera`).
        token_features: the feature-augmentation variant (:mod:`hoisdf.model.parts`).
        cross: the cross-field variant (None: no cross tokens).
        boxes: (batch, 2D maps) -> (hand box, object box) (B, 4) that filter the inference grid.
        object_rotation: per-point axis-angles (B, N, 3) -> object rotation (B, 3, 3).
        scale: metres -> scaled units.
        clamp: SDF clamp, scaled units.
        n_freq: Fourier frequencies per axis.
        beta_init: initial learned density width (scaled units; only if ``token_features.learns_beta``).
        project_grid: rank the grid through ``project_pyramid`` (exact; fewer channels to sample with a big decoder).
        beta_floor: None, or project the learned density widths onto [beta_floor, inf) in place at each forward
            (the reference's ``beta.data.copy_(max(beta.data, 2e-3))``).
        reuse_ranking_sdf: field-guided points carry into their tokens the SDF of the ranking pass (the reference:
            its dropout mask in training) instead of a second pass.
    """

    def __init__(self, mano, backbone, sdf_in, token_in, hand_sdf, obj_sdf, hand_encoder, obj_encoder,
                 hand_heads: dict, obj_head, regressor, sampler, camera, token_features, cross, boxes,
                 object_rotation, scale: float, clamp: float, n_freq: int, beta_init: float, project_grid: bool,
                 beta_floor: float | None = None, reuse_ranking_sdf: bool = False):
        super().__init__()
        self.beta_floor, self.reuse_ranking_sdf = beta_floor, reuse_ranking_sdf
        self._mano = [mano]  # a list: not a registered submodule, so not in state_dict()
        self.scale, self.clamp, self.n_freq, self.project_grid = scale, clamp, n_freq, project_grid
        self.camera, self.token_features, self.cross, self.regressor = camera, token_features, cross, regressor
        self.boxes, self.object_rotation = boxes, object_rotation
        self.sampler = sampler
        # registration order = state-dict and parameter order (checkpoints, optimizer state): keep it
        self.backbone, self.sdf_in, self.token_in = backbone, sdf_in, token_in
        self.hand_sdf, self.obj_sdf = hand_sdf, obj_sdf
        if token_features.learns_beta:
            self.hand_beta = nn.Parameter(torch.tensor(float(beta_init)))
            self.obj_beta = nn.Parameter(torch.tensor(float(beta_init)))
        self.hand_encoder, self.obj_encoder = hand_encoder, obj_encoder
        for name, module in hand_heads.items():
            self.add_module(name, module)
        self.obj_head = obj_head

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

    # --- fields -------------------------------------------------------------------------------------------
    def field(self, decoder, sdf_in: torch.Tensor, scaled: torch.Tensor, clamp: bool = True) -> torch.Tensor:
        """Scaled SDF (B, N) of a decoder at scaled points (B, N, 3) with their ``sdf_in`` features, clamped to
        +-``sdf_clamp`` (``clamp=False``: the raw value, which the grid ranking uses, as the reference)."""
        out = full(decoder(sdf_in, fourier_encode(scaled, self.n_freq), scaled))
        return out.clamp(-self.clamp, self.clamp) if clamp else out

    def _sdf_fn(self, decoder, pyramid, K, center, detach=True, clamp=True):
        """camera points (B, M, 3) -> scaled SDF (B, M) of ``decoder`` (clamped unless ``clamp=False``), for a few
        hundred points.

        ``detach=False``: a function of the points through both the point code and the image features (the
        full field gradient)."""
        def fn(points_cam):
            return self.field(decoder, self.sdf_in(self.camera.features(pyramid, points_cam, K, detach)),
                              (points_cam - center[:, None]) * self.scale, clamp)
        return fn

    def _grid_sdf_fn(self, decoder, projected, K, center):
        """As :meth:`_sdf_fn` (unclamped) for many points: ``sdf_in``'s first layer was applied to the pyramid
        (exact)."""
        first, rest = self.sdf_in.layers[0], self.sdf_in.layers[1:]

        def fn(points_cam):
            return self.field(decoder, rest(self.camera.projected(projected, points_cam, K, first.bias)),
                              (points_cam - center[:, None]) * self.scale, clamp=False)
        return fn

    def _token(self, offset: torch.Tensor, feat: torch.Tensor) -> torch.Tensor:
        return torch.cat([offset, fourier_encode(offset * self.scale, self.n_freq), feat], dim=-1)

    # --- query points -------------------------------------------------------------------------------------
    def _training_points(self, batch, K, root, center, boxes, generator):
        """Scaled ground-truth guided points of the sampling variant (see :class:`~hoisdf.model.parts.QuerySampler`)."""
        return self.sampler.training_points(batch, K, root, center, boxes, generator)

    def _field_points(self, pyramid, K, root, center, boxes, generator):
        """Scaled field-guided points, ranked by the unclamped SDF (as the reference: clamping would tie every
        point beyond the clamp)."""
        newton = (None, None)
        if self.sampler.uses_newton():
            newton = (self._sdf_fn(self.hand_sdf, pyramid, K, root, detach=False),
                      self._sdf_fn(self.obj_sdf, pyramid, K, center, detach=False))
        if self.project_grid:
            projected = project_pyramid(pyramid, self.sdf_in.layers[0])
            fns = (self._grid_sdf_fn(self.hand_sdf, projected, K, root),
                   self._grid_sdf_fn(self.obj_sdf, projected, K, center))
        else:
            fns = (self._sdf_fn(self.hand_sdf, pyramid, K, root, clamp=False),
                   self._sdf_fn(self.obj_sdf, pyramid, K, center, clamp=False))
        return self.sampler.field_points(K, root, center, boxes, fns, newton, generator)

    def _query_points(self, batch, pyramid, K, root, center, boxes, mode, noise, generator):
        """Scaled query points (hand rel. root (B, Nh, 3), object rel. centre (B, No, 3)); ``mode``: "gt"
        (training rows + uniform noise of half-width ``noise``) or "field"."""
        return self._queries(batch, pyramid, K, root, center, boxes, mode, noise, generator)[:2]

    def _queries(self, batch, pyramid, K, root, center, boxes, mode, noise, generator):
        """As :meth:`_query_points`, and the points' SDFs (B, Nh), (B, No) from the ranking pass (None: "gt"
        points, or not ``reuse_ranking_sdf``)."""
        if mode not in POINT_MODES:
            raise ValueError(f"points must be one of {tuple(POINT_MODES)}, got {mode!r}")
        if POINT_MODES[mode]:
            hand, obj = self._training_points(batch, K, root, center, boxes, generator)
            return jitter(hand, noise, generator), jitter(obj, noise, generator), None
        (hand, obj), ranked = self._field_points(pyramid, K, root, center, boxes, generator)
        return hand, obj, (ranked if self.reuse_ranking_sdf else None)

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
            out["hand_sdf"] = self._sdf_fn(self.hand_sdf, pyramid, K, root)(batch["hand_points"] + root[:, None])
        if "obj_points" in batch:
            out["obj_sdf"] = self._sdf_fn(self.obj_sdf, pyramid, K, center)(batch["obj_points"] + root[:, None])
        hp, op, ranked = self._queries(batch, pyramid, K, root, center, self.boxes(batch, maps), points, noise,
                                       generator)
        out.update(self._pose(pyramid, K, root, center, hp, op, ranked))
        return out

    def _pose(self, pyramid, K, root, center, hp, op, ranked=None) -> dict[str, torch.Tensor]:
        hand_cam, obj_cam = hp / self.scale + root[:, None], op / self.scale + center[:, None]
        f_hand, f_obj = self.camera.features(pyramid, hand_cam, K), self.camera.features(pyramid, obj_cam, K)
        sdf_in_h, sdf_in_o = self.sdf_in(f_hand), self.sdf_in(f_obj)
        tok_h, tok_o = self.token_in(f_hand), self.token_in(f_obj)
        hand_in_obj, obj_in_hand = (hand_cam - center[:, None]), (obj_cam - root[:, None])
        with torch.no_grad():
            if ranked is None:
                d_h = self.field(self.hand_sdf, sdf_in_h, hp)
                d_o = self.field(self.obj_sdf, sdf_in_o, op)
            else:  # the ranking pass's values, clamped as the field's
                d_h, d_o = (full(d).clamp(-self.clamp, self.clamp) for d in ranked)
            d_ho = self.field(self.obj_sdf, sdf_in_h, hand_in_obj * self.scale)  # hand points, object field
            d_oh = self.field(self.hand_sdf, sdf_in_o, obj_in_hand * self.scale)  # object points, hand field
        betas = getattr(self, "hand_beta", None), getattr(self, "obj_beta", None)
        if self.beta_floor is not None and betas[0] is not None:
            with torch.no_grad():
                for beta in betas:
                    beta.clamp_(min=self.beta_floor)
        hand_tokens = self._token(hp / self.scale, self.token_features(tok_h, d_h, betas[0]))
        obj_tokens = self._token(op / self.scale, self.token_features(tok_o, d_o, betas[1]))
        if self.cross is not None:
            (sdf_oh, beta_oh), (sdf_ho, beta_ho) = self.cross(d_h, d_o, d_ho, d_oh, *betas)
            obj_h = self._token(obj_in_hand, self.token_features(tok_o, sdf_oh, beta_oh)).detach()
            hand_o = self._token(hand_in_obj, self.token_features(tok_h, sdf_ho, beta_ho)).detach()
            hand_tokens, obj_tokens = torch.cat([hand_tokens, obj_h], 1), torch.cat([obj_tokens, hand_o], 1)
        inter_h, memory = self.hand_encoder(hand_tokens)
        inter_o, _ = self.obj_encoder(obj_tokens)
        nh, no = hp.shape[1], op.shape[1]
        out = {"hand_query": hp / self.scale, "hand_query_sdf": d_h / self.scale,
               "obj_query": op / self.scale, "obj_query_sdf": d_o / self.scale}
        out.update(self.regressor(self, inter_h, memory, hp / self.scale, nh))
        obj = self.obj_head(inter_o[:, :, :no])
        out.update({"obj_rot_points": obj["rot"], "obj_trans_points": obj["trans"],
                    "obj_rotation": self.object_rotation(obj["rot"][-1]),
                    "obj_translation": center + obj["trans"][-1].float().mean(dim=1)})
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
