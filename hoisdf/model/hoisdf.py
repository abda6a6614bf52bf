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

Outputs are metres; hand outputs are relative to the (given) hand root, the object translation is
absolute (camera frame).
"""

from __future__ import annotations

import torch
from torch import nn

from hoisdf.model import heads as H
from hoisdf.model.backbone import ResNetUNet
from hoisdf.model.encoding import (
    PIXEL_CONVENTIONS,
    fourier_encode,
    pixel_aligned_features,
    pixel_to_grid,
    project_points,
    project_pyramid,
    sample_projected,
)
from hoisdf.model.ik import solve_ik
from hoisdf.model.layers import MLP
from hoisdf.model.precision import full
from hoisdf.model.sampling import (
    field_guided_points,
    grid_points,
    inside_rows,
    jitter,
    random_grid_points,
)
from hoisdf.model.sdf_decoder import SDFDecoder
from hoisdf.model.transformer import (
    QueryDecoder,
    TokenEncoder,
    init_transformer_weights,
    mano_query_mask,
    memory_mask,
)

CHOICES = {
    "sampling": ("absolute", "signed", "random", "gradient"),
    "feature_augmentation": ("density", "none", "density_concat", "distance_concat"),
    "cross_field": ("sdf", "none", "image", "target"),
    "pose_regressor": ("mano", "mano_only", "voting", "ik"),
    "density_sign": ("paper", "code"),
    "object_rotation": ("chordal", "axis_angle"),
    "test_boxes": ("gt", "predicted"),
    "pixel_convention": PIXEL_CONVENTIONS,
}
POINT_DIM = 33  # xyz (3) + Fourier code (30) of every token


class HOISDF(nn.Module):
    """The full model. Constructor arguments are :class:`hoisdf.config.ModelSettings`'s fields plus ``mano``.

    ``mano`` (the project's right-hand MANO layer) is used by the MANO head and the IK variant; it is
    kept out of the state dict (its data is licensed and belongs to the user, not to checkpoints).
    """

    def __init__(self, mano, depth=50, decoder="small", weights="", normalize_input=True, freeze_bn_affine=True,
                 channels_last=False, image_size=256, sdf_scale=3.1, sdf_clamp=0.15, n_freq=5, d_model=256, heads=4,
                 ff=1024, dropout=0.1, hand_layers=6, decoder_layers=4, object_layers=3, sdf_features=256,
                 sdf_hidden=512, sdf_dropout=0.2, token_hidden=(1024, 512, 256), n_hand=600, n_object=200,
                 grid_resolution=64, sheared_grid=False, fixed_shape=False, sampling="absolute",
                 feature_augmentation="density", cross_field="sdf", pose_regressor="mano", density_sign="paper",
                 beta_init=0.1, beta_min=2e-3,
                 object_rotation="chordal", test_boxes="gt", mask_threshold=0.5, chunk=32768, cls_dist=0.04,
                 pixel_convention="centers"):
        super().__init__()
        for name, value in (("sampling", sampling), ("feature_augmentation", feature_augmentation),
                            ("cross_field", cross_field), ("pose_regressor", pose_regressor),
                            ("density_sign", density_sign), ("object_rotation", object_rotation),
                            ("test_boxes", test_boxes), ("pixel_convention", pixel_convention)):
            if value not in CHOICES[name]:
                raise ValueError(f"model.{name} must be one of {CHOICES[name]}, got {value!r}")
        if not all(int(w) > 0 for w in token_hidden):
            raise ValueError(f"model.token_hidden must be positive layer widths, got {list(token_hidden)}")
        if 6 * n_freq + 3 != POINT_DIM:
            raise ValueError(f"model.n_freq must be 5 (tokens carry a {POINT_DIM}-dim point code), got {n_freq}")
        if d_model <= POINT_DIM + 1 or d_model % heads:
            raise ValueError(f"model.d_model must exceed {POINT_DIM + 1} (a token holds the {POINT_DIM}-dim point code) "
                             f"and be a multiple of model.heads ({heads}), got {d_model}")
        if sdf_hidden <= sdf_features + POINT_DIM:
            raise ValueError(f"model.sdf_hidden must exceed model.sdf_features + {POINT_DIM} "
                             f"({sdf_features + POINT_DIM}: the decoder's skip connection), got {sdf_hidden}")
        self._mano = [mano]  # a list: not a registered submodule, so not in state_dict()
        self.image_size, self.scale, self.clamp = image_size, sdf_scale, sdf_clamp
        self.n_freq, self.n_hand, self.n_object = n_freq, n_hand, n_object
        self.sampling, self.augmentation, self.cross = sampling, feature_augmentation, cross_field
        self.regressor, self.sign = pose_regressor, (-1.0 if density_sign == "paper" else 1.0)
        self.beta_min, self.object_rotation, self.test_boxes = beta_min, object_rotation, test_boxes
        self.mask_threshold, self.chunk, self.cls_dist = mask_threshold, chunk, cls_dist
        self.fixed_shape, self.pixels = bool(fixed_shape), pixel_convention
        self.project_grid = False  # set below: grid SDFs through project_pyramid (exact) when it samples fewer channels
        self.register_buffer("grid", grid_points(grid_resolution, sheared_grid), persistent=False)

        self.backbone = ResNetUNet(depth, decoder, weights or None, freeze_bn_affine, normalize_input, channels_last)
        feat = sum(self.backbone.channels)
        self.sdf_in = MLP(feat, [2 * sdf_features], sdf_features, relu_last=True)
        # sampling the projected maps reads levels x width channels instead of sum(C): a gain for the big decoder
        # (3968 vs 5 x 512; 2x faster on the CPU, bench/bench_grid_features.py), a loss for the small one (992)
        self.project_grid = feat > len(self.backbone.channels) * 2 * sdf_features
        concat = feature_augmentation in ("density_concat", "distance_concat")
        self.token_in = MLP(feat, token_hidden, d_model - POINT_DIM - int(concat), relu_last=True)
        pe = 6 * n_freq
        self.hand_sdf = SDFDecoder(sdf_features, pe, sdf_hidden, dropout=sdf_dropout)
        self.obj_sdf = SDFDecoder(sdf_features, pe, sdf_hidden, dropout=sdf_dropout)
        if feature_augmentation != "none":
            self.hand_beta = nn.Parameter(torch.tensor(float(beta_init)))
            self.obj_beta = nn.Parameter(torch.tensor(float(beta_init)))
        self.hand_encoder = TokenEncoder(hand_layers, d_model, heads, ff, dropout)
        self.obj_encoder = TokenEncoder(object_layers, d_model, heads, ff, dropout)
        queries = {"mano": 17, "mano_only": 17, "ik": 1, "voting": 0}[pose_regressor]
        if queries:
            self.hand_decoder = QueryDecoder(decoder_layers, queries, d_model, heads, ff, dropout)
        if pose_regressor in ("mano", "mano_only"):
            self.mano_head = H.ManoHead(d_model)
        if pose_regressor == "ik":
            self.shape_head = H.ShapeHead(d_model)
        if pose_regressor != "mano_only":
            self.vote_head = H.VoteHead(d_model)
        self.obj_head = H.ObjectHead(d_model)
        for module in (self.hand_encoder, self.obj_encoder, getattr(self, "hand_decoder", None)):
            if module is not None:
                init_transformer_weights(module)

    @property
    def mano(self):
        return self._mano[0]

    # --- fields -------------------------------------------------------------------------------------------
    def features(self, pyramid: list[torch.Tensor], points_cam: torch.Tensor, K: torch.Tensor,
                 detach: bool = True) -> torch.Tensor:
        """Pixel-aligned multi-level features (B, N, C) of camera points (B, N, 3) (``detach=False``: with
        the gradient through the projection)."""
        return pixel_aligned_features(pyramid, points_cam, K, self.image_size, detach, self.pixels)

    def field(self, decoder: SDFDecoder, sdf_in: torch.Tensor, scaled: torch.Tensor,
              clamp: bool = True) -> torch.Tensor:
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
            return self.field(decoder, self.sdf_in(self.features(pyramid, points_cam, K, detach)),
                              (points_cam - center[:, None]) * self.scale, clamp)
        return fn

    def _grid_sdf_fn(self, decoder, projected, K, center):
        """As :meth:`_sdf_fn` (unclamped) for many points: ``sdf_in``'s first layer was applied to the pyramid
        (exact)."""
        first, rest = self.sdf_in.layers[0], self.sdf_in.layers[1:]

        def fn(points_cam):
            grid = pixel_to_grid(project_points(points_cam.detach(), K), self.image_size, self.pixels)
            return self.field(decoder, rest(sample_projected(projected, grid, first.bias, self.pixels)),
                              (points_cam - center[:, None]) * self.scale, clamp=False)
        return fn

    def _density(self, sdf: torch.Tensor, which: str) -> torch.Tensor:
        return H.density(sdf, getattr(self, f"{which}_beta"), self.sign, self.beta_min)

    def _augment(self, feat: torch.Tensor, sdf: torch.Tensor | None, which: str) -> torch.Tensor:
        """Token feature from the image feature (B, N, F) and a detached scaled SDF (None: not augmented)."""
        mode, feat = self.augmentation, full(feat)
        if mode == "none":
            return feat
        if sdf is None:  # "image" cross tokens: no field information
            return feat if mode == "density" else torch.cat([feat, torch.ones_like(feat[..., :1])], -1)
        sdf = sdf.detach()
        if mode == "density":
            return feat * self._density(sdf, which)[..., None]
        value = self._density(sdf, which) if mode == "density_concat" else sdf
        return torch.cat([feat, value[..., None].to(feat)], -1)

    def _token(self, offset: torch.Tensor, feat: torch.Tensor) -> torch.Tensor:
        return torch.cat([offset, fourier_encode(offset * self.scale, self.n_freq), feat], dim=-1)

    # --- query points -------------------------------------------------------------------------------------
    def _training_points(self, batch, K, root, center, boxes, generator):
        """Scaled ground-truth guided points (the "gt" path) of the sampling variant: near-surface rows
        ("absolute", "gradient"), rows inside the meshes ("signed"), random grid points in the box ("random")."""
        if self.sampling == "random":
            grid, s, c = self.grid, self.scale, self.chunk
            return (random_grid_points(grid, root, s, K, boxes[0], self.n_hand, generator, c),
                    random_grid_points(grid, center, s, K, boxes[1], self.n_object, generator, c))
        if self.sampling == "signed":
            rows = {w: (torch.cat([batch[f"{w}_points"], batch[f"{w}_near_points"]], 1),
                        torch.cat([batch[f"{w}_sdf"], batch[f"{w}_near_sdf"]], 1)) for w in ("hand", "obj")}
            hand = inside_rows(*rows["hand"], self.n_hand, generator)
            obj = inside_rows(*rows["obj"], self.n_object, generator)
        else:
            hand, obj = batch["hand_near_points"][:, :self.n_hand], batch["obj_near_points"][:, :self.n_object]
        return hand * self.scale, (obj + (root - center)[:, None]) * self.scale

    def _query_points(self, batch, pyramid, K, root, center, boxes, mode, noise, generator):
        """Scaled query points (hand rel. root (B, Nh, 3), object rel. centre (B, No, 3))."""
        if mode == "gt":
            hand, obj = self._training_points(batch, K, root, center, boxes, generator)
            return jitter(hand, noise, generator), jitter(obj, noise, generator)
        if mode != "field":
            raise ValueError(f"points must be 'gt' or 'field', got {mode!r}")
        # the "gradient" variant trains as "absolute" and moves the points onto the surface only at inference
        strategy = "absolute" if self.sampling == "gradient" and self.training else self.sampling
        newton = {}
        if strategy == "gradient":
            newton = {"hand": self._sdf_fn(self.hand_sdf, pyramid, K, root, detach=False),
                      "obj": self._sdf_fn(self.obj_sdf, pyramid, K, center, detach=False)}
        if self.project_grid:
            projected = project_pyramid(pyramid, self.sdf_in.layers[0])
            hand_fn = self._grid_sdf_fn(self.hand_sdf, projected, K, root)
            obj_fn = self._grid_sdf_fn(self.obj_sdf, projected, K, center)
        else:  # ranked by the unclamped SDF (as the reference: clamping would tie every point beyond the clamp)
            hand_fn = self._sdf_fn(self.hand_sdf, pyramid, K, root, clamp=False)
            obj_fn = self._sdf_fn(self.obj_sdf, pyramid, K, center, clamp=False)
        hand, _ = field_guided_points(self.grid, root, self.scale, K, boxes[0], hand_fn, self.n_hand, strategy,
                                      self.chunk, generator, self.fixed_shape, newton.get("hand"))
        obj, _ = field_guided_points(self.grid, center, self.scale, K, boxes[1], obj_fn, self.n_object, strategy,
                                     self.chunk, generator, self.fixed_shape, newton.get("obj"))
        return hand, obj

    def boxes(self, batch: dict, maps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """2D boxes (B, 4) that filter the inference grid: ground truth, or from the predicted masks."""
        if self.test_boxes == "gt":
            return batch["hand_box"], batch["object_box"]
        prob = torch.sigmoid(maps[:, 1:3].float())
        return (H.masks_to_boxes(prob[:, 0], self.mask_threshold, self.image_size, self.pixels),
                H.masks_to_boxes(prob[:, 1], self.mask_threshold, self.image_size, self.pixels))

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
        hp, op = self._query_points(batch, pyramid, K, root, center, self.boxes(batch, maps), points, noise, generator)
        out.update(self._pose(pyramid, K, root, center, hp, op))
        return out

    def _pose(self, pyramid, K, root, center, hp, op) -> dict[str, torch.Tensor]:
        hand_cam, obj_cam = hp / self.scale + root[:, None], op / self.scale + center[:, None]
        f_hand, f_obj = self.features(pyramid, hand_cam, K), self.features(pyramid, obj_cam, K)
        sdf_in_h, sdf_in_o = self.sdf_in(f_hand), self.sdf_in(f_obj)
        tok_h, tok_o = self.token_in(f_hand), self.token_in(f_obj)
        hand_in_obj, obj_in_hand = (hand_cam - center[:, None]), (obj_cam - root[:, None])
        with torch.no_grad():
            d_h = self.field(self.hand_sdf, sdf_in_h, hp)
            d_o = self.field(self.obj_sdf, sdf_in_o, op)
            d_ho = self.field(self.obj_sdf, sdf_in_h, hand_in_obj * self.scale)  # hand points, object field
            d_oh = self.field(self.hand_sdf, sdf_in_o, obj_in_hand * self.scale)  # object points, hand field
        hand_tokens = self._token(hp / self.scale, self._augment(tok_h, d_h, "hand"))
        obj_tokens = self._token(op / self.scale, self._augment(tok_o, d_o, "obj"))
        if self.cross != "none":
            cross_sdf = {"sdf": (d_oh, d_ho), "image": (None, None), "target": (d_o, d_h)}[self.cross]
            cross_beta = ("obj", "hand") if self.cross == "target" else ("hand", "obj")
            obj_h = self._token(obj_in_hand, self._augment(tok_o, cross_sdf[0], cross_beta[0])).detach()
            hand_o = self._token(hand_in_obj, self._augment(tok_h, cross_sdf[1], cross_beta[1])).detach()
            hand_tokens_all, obj_tokens_all = torch.cat([hand_tokens, obj_h], 1), torch.cat([obj_tokens, hand_o], 1)
        else:
            hand_tokens_all, obj_tokens_all = hand_tokens, obj_tokens
        inter_h, memory = self.hand_encoder(hand_tokens_all)
        inter_o, _ = self.obj_encoder(obj_tokens_all)
        nh, no = hp.shape[1], op.shape[1]
        out = {"hand_query": hp / self.scale, "hand_query_sdf": d_h / self.scale,
               "obj_query": op / self.scale, "obj_query_sdf": d_o / self.scale}
        out.update(self._hand_outputs(inter_h, memory, hp / self.scale, nh))
        obj = self.obj_head(inter_o[:, :, :no])
        rotation = H.mean_rotation(obj["rot"][-1], self.object_rotation)
        out.update({"obj_rot_points": obj["rot"], "obj_trans_points": obj["trans"], "obj_rotation": rotation,
                    "obj_translation": center + obj["trans"][-1].float().mean(dim=1)})
        return out

    def _hand_outputs(self, inter_h, memory, hand_metric, nh) -> dict[str, torch.Tensor]:
        out = {}
        if self.regressor != "mano_only":
            votes = self.vote_head(inter_h[:, :, :nh], hand_metric)
            out.update({"vote_offsets": votes["offsets"], "vote_logits": votes["logits"], "vote_joints": votes["joints"]})
        if self.regressor == "voting":
            out["joints"] = H.with_root(votes["joints"][-1])
            return out
        n_queries = self.hand_decoder.query_embed.num_embeddings
        mask = mano_query_mask(memory.device) if n_queries == 17 else None
        queries = self.hand_decoder(memory, mask, memory_mask(n_queries, memory.shape[1], nh, memory.device))
        if self.regressor == "ik":
            betas = self.shape_head(queries)["betas"]
            out["betas"] = betas
            voted = H.with_root(votes["joints"][-1])
            with torch.no_grad():  # the reported hand is the MANO fit of the voted joints (as the reference)
                pose = solve_ik(voted.detach().float(), betas[-1].detach().float(), self.mano)
                verts, joints = H.wrist_centred_mano(self.mano, pose, betas[-1].detach().float())
            out.update({"joints": joints, "verts": verts, "ik_pose": pose})
            return out
        mano_out = self.mano_head(queries, self.mano)
        out.update({"rotations": mano_out["rotations"], "betas": mano_out["betas"], "mano_verts": mano_out["verts"],
                    "mano_joints": mano_out["joints"], "joints": mano_out["joints"][-1], "verts": mano_out["verts"][-1]})
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
