"""The learned stages :class:`hoisdf.model.HOISDF` is composed of, besides the backbone: the density widths, the
pixel-aligned features of points, the two SDF fields and the pose stage. Each owns its modules (their names are the
state-dict keys under ``widths.``, ``features.``, ``fields.`` and ``pose.``) and the settings it needs;
:func:`hoisdf.model.build_model` builds them.

Coordinates: "scaled" points are metric offsets from a centre times ``sdf_scale`` (see :mod:`hoisdf.model.sampling`);
SDFs are scaled units.
"""

from __future__ import annotations

import torch
from torch import nn

from hoisdf.model.encoding import fourier_encode
from hoisdf.model.parts import Camera
from hoisdf.model.precision import full


class PixelFeatures(nn.Module):
    """Pixel-aligned features of camera-frame points: the camera samples every pyramid level at the points'
    projections; ``sdf_in`` (-> the SDF decoders' input) and ``token_in`` (-> the transformer tokens' feature) map
    them.

    ``project_grid``: the field-guided ranking samples maps that ``sdf_in``'s first layer already projected (exact;
    fewer channels to sample with a big decoder, :func:`hoisdf.model.encoding.project_pyramid`).
    """

    def __init__(self, camera: Camera, sdf_in: nn.Module, token_in: nn.Module, project_grid: bool):
        super().__init__()
        self.camera, self.project_grid = camera, project_grid
        self.sdf_in, self.token_in = sdf_in, token_in

    def sample(self, pyramid, points_cam: torch.Tensor, K: torch.Tensor, detach: bool = True) -> torch.Tensor:
        """Multi-level features (B, N, C) of camera points (B, N, 3), metres (:meth:`Camera.features`)."""
        return self.camera.features(pyramid, points_cam, K, detach)


class DensityWidths(nn.Module):
    """The learned widths of the SDF -> density conversion of the hand and the object tokens (scaled units).

    Args:
        init: initial width, or None: no learned width (the token features do not use one).
        floor: None, or project the widths onto [floor, inf) in place at each use (the reference's
            ``beta.data.copy_(max(beta.data, 2e-3))``).
    """

    def __init__(self, init: float | None, floor: float | None = None):
        super().__init__()
        self.floor = floor
        if init is None:
            self.hand_beta = self.obj_beta = None
        else:
            self.hand_beta = nn.Parameter(torch.tensor(float(init)))
            self.obj_beta = nn.Parameter(torch.tensor(float(init)))

    def forward(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(hand, object) widths (None, None without them), projected onto the floor first when it is set."""
        if self.floor is not None and self.hand_beta is not None:
            with torch.no_grad():
                for beta in (self.hand_beta, self.obj_beta):
                    beta.clamp_(min=self.floor)
        return self.hand_beta, self.obj_beta


class SDFFields(nn.Module):
    """The hand and the object SDF decoders and the scale and clamp of their values.

    Args:
        hand_sdf: the hand SDF decoder (:class:`hoisdf.model.sdf_decoder.SDFDecoder`).
        obj_sdf: the object SDF decoder.
        scale: metres -> scaled units (``sdf_scale``).
        clamp: SDF clamp, scaled units.
        n_freq: Fourier frequencies per axis of the point code.
    """

    def __init__(self, hand_sdf: nn.Module, obj_sdf: nn.Module, scale: float, clamp: float, n_freq: int):
        super().__init__()
        self.scale, self.clamp, self.n_freq = scale, clamp, n_freq
        self.hand_sdf, self.obj_sdf = hand_sdf, obj_sdf

    def field(self, decoder: nn.Module, sdf_in: torch.Tensor, scaled: torch.Tensor, clamp: bool = True) -> torch.Tensor:
        """Scaled SDF (B, N) of a decoder at scaled points (B, N, 3) with their ``sdf_in`` features, clamped to
        +-``clamp`` (``clamp=False``: the raw value, which the grid ranking uses, as the reference)."""
        out = full(decoder(sdf_in, fourier_encode(scaled, self.n_freq), scaled))
        return out.clamp(-self.clamp, self.clamp) if clamp else out


class PoseStage(nn.Module):
    """Tokens of the query points -> the hand and object transformers -> the hand regressor and the object head.

    Args:
        token_features: the feature-augmentation variant (:mod:`hoisdf.model.parts`): (feature, SDF, width) ->
            token feature.
        cross: the cross-field variant (None: no cross tokens).
        hand_encoder: the hand token encoder.
        obj_encoder: the object token encoder.
        regressor: the hand regressor variant (:mod:`hoisdf.model.regressors`), owning its heads.
        obj_head: the object pose head.
        object_rotation: per-point axis-angles (B, N, 3) -> object rotation (B, 3, 3)
            (:func:`hoisdf.model.heads.chordal_mean` or :func:`~hoisdf.model.heads.axis_angle_mean`).
        scale: metres -> scaled units (the tokens' Fourier code is of scaled offsets).
        n_freq: Fourier frequencies per axis.
    """

    def __init__(self, token_features, cross, hand_encoder: nn.Module, obj_encoder: nn.Module, regressor: nn.Module,
                 obj_head: nn.Module, object_rotation, scale: float, n_freq: int):
        super().__init__()
        self.token_features, self.cross, self.object_rotation = token_features, cross, object_rotation
        self.scale, self.n_freq = scale, n_freq
        self.hand_encoder, self.obj_encoder = hand_encoder, obj_encoder
        self.regressor, self.obj_head = regressor, obj_head

    def token(self, offset: torch.Tensor, feat: torch.Tensor) -> torch.Tensor:
        """[offset (metres, 3), Fourier code of the scaled offset (30), feature] (B, N, d_model)."""
        return torch.cat([offset, fourier_encode(offset * self.scale, self.n_freq), feat], dim=-1)

    def forward(self, feats, sdfs, betas, points, center, mano) -> dict[str, torch.Tensor]:
        """``feats``: ``token_in`` features (B, Nh, F) of the hand and (B, No, F) of the object points; ``sdfs``:
        (hand points in the hand field, object points in the object field, hand points in the object field, object
        points in the hand field) (B, N), clamped scaled SDFs; ``betas``: (hand, object) widths; ``points``: (hand
        points rel. the hand root, object points rel. the object centre, hand points rel. the object centre, object
        points rel. the hand root) (B, N, 3), metres; ``center``: (B, 3) object centre, camera frame."""
        (tok_h, tok_o), (d_h, d_o, d_ho, d_oh) = feats, sdfs
        hand, obj, hand_in_obj, obj_in_hand = points
        hand_tokens = self.token(hand, self.token_features(tok_h, d_h, betas[0]))
        obj_tokens = self.token(obj, self.token_features(tok_o, d_o, betas[1]))
        if self.cross is not None:
            (sdf_oh, beta_oh), (sdf_ho, beta_ho) = self.cross(d_h, d_o, d_ho, d_oh, *betas)
            obj_h = self.token(obj_in_hand, self.token_features(tok_o, sdf_oh, beta_oh)).detach()
            hand_o = self.token(hand_in_obj, self.token_features(tok_h, sdf_ho, beta_ho)).detach()
            hand_tokens, obj_tokens = torch.cat([hand_tokens, obj_h], 1), torch.cat([obj_tokens, hand_o], 1)
        inter_h, memory = self.hand_encoder(hand_tokens)
        inter_o, _ = self.obj_encoder(obj_tokens)
        out = self.regressor(inter_h, memory, hand, hand.shape[1], mano)
        pose = self.obj_head(inter_o[:, :, :obj.shape[1]])
        out.update({"obj_rot_points": pose["rot"], "obj_trans_points": pose["trans"],
                    "obj_rotation": self.object_rotation(pose["rot"][-1]),
                    "obj_translation": center + pose["trans"][-1].float().mean(dim=1)})
        return out
