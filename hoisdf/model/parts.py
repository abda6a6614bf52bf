"""The small parts :func:`hoisdf.model.build_model` picks from the settings and :class:`~hoisdf.model.HOISDF`
composes: the camera (pixel convention), the query sampler, the token-feature variant, the cross field and the
source of the inference boxes.

Each variant of the paper's ablations is one class or function here; the model calls them and never compares
a setting string. None of them holds learned weights (the state dict belongs to the model's own modules).
Coordinates: "scaled" points are metric offsets from a centre times ``sdf_scale`` (see
:mod:`hoisdf.model.sampling`); SDFs are scaled units.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from hoisdf.model import heads as H
from hoisdf.model.encoding import (
    PixelCenters,
    UpstreamPixels,
    pixel_aligned_features,
    pixel_to_grid,
    project_points,
    sample_projected,
)
from hoisdf.model.precision import full
from hoisdf.model.sampling import Ranking, field_guided_points, inside_rows, random_grid_points


@dataclass(frozen=True)
class Camera:
    """Pixel-aligned sampling of image maps at camera-frame points, under one pixel convention.

    ``image_size``: px, side of the network input; ``convention``: :data:`~hoisdf.model.encoding.CENTERS`
    (align_corners=False) or :data:`~hoisdf.model.encoding.UPSTREAM` (the released code's align_corners=True), see
    :mod:`hoisdf.model.encoding`.
    """

    image_size: int
    convention: PixelCenters | UpstreamPixels

    def features(self, pyramid: list[torch.Tensor], points_cam: torch.Tensor, K: torch.Tensor,
                 detach: bool = True) -> torch.Tensor:
        """Multi-level features (B, N, C) of camera points (B, N, 3), metres; ``detach=False`` keeps the
        gradient through the projection."""
        return pixel_aligned_features(pyramid, points_cam, K, self.image_size, detach, self.convention)

    def projected(self, projected: list[torch.Tensor], points_cam: torch.Tensor, K: torch.Tensor,
                  bias: torch.Tensor) -> torch.Tensor:
        """Features (B, N, W) of points (B, N, 3) from maps that a linear layer (bias (W,)) already projected."""
        grid = pixel_to_grid(project_points(points_cam.detach(), K), self.image_size, self.convention)
        return sample_projected(projected, grid, bias, self.convention)

    def mask_boxes(self, prob: torch.Tensor, threshold: float) -> torch.Tensor:
        """Mask probabilities (B, h, w) -> boxes (B, 4) x1, y1, x2, y2 in input pixels."""
        return H.masks_to_boxes(prob, threshold, self.image_size, self.convention)


# --- inference boxes ------------------------------------------------------------------------------------------
def ground_truth_boxes(batch: dict, maps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The batch's hand and object boxes (B, 4) (``test_boxes = "gt"``, the published protocol)."""
    return batch["hand_box"], batch["object_box"]


@dataclass(frozen=True)
class PredictedBoxes:
    """Boxes (B, 4) from the predicted hand / object masks (``test_boxes = "predicted"``); ``threshold``:
    probability above which a mask pixel counts."""

    camera: Camera
    threshold: float

    def __call__(self, batch: dict, maps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        prob = torch.sigmoid(maps[:, 1:3].float())
        return self.camera.mask_boxes(prob[:, 0], self.threshold), self.camera.mask_boxes(prob[:, 1], self.threshold)


# --- query sampler --------------------------------------------------------------------------------------------
def near_surface_rows(sampler, batch, K, root, center, boxes, generator):
    """Training rows of "absolute" / "gradient": the first near-surface rows (|SDF| < ``train.near``)."""
    hand = batch["hand_near_points"][:, :sampler.hand_queries]
    obj = batch["obj_near_points"][:, :sampler.object_queries]
    return hand * sampler.scale, (obj + (root - center)[:, None]) * sampler.scale


def inside_mesh_rows(sampler, batch, K, root, center, boxes, generator):
    """Training rows of "signed": rows inside the meshes (:func:`hoisdf.model.sampling.inside_rows`)."""
    rows = {w: (torch.cat([batch[f"{w}_points"], batch[f"{w}_near_points"]], 1),
                torch.cat([batch[f"{w}_sdf"], batch[f"{w}_near_sdf"]], 1)) for w in ("hand", "obj")}
    hand = inside_rows(*rows["hand"], sampler.hand_queries, generator)
    obj = inside_rows(*rows["obj"], sampler.object_queries, generator)
    return hand * sampler.scale, (obj + (root - center)[:, None]) * sampler.scale


def random_box_rows(sampler, batch, K, root, center, boxes, generator):
    """Training points of "random": random grid points whose projection lies inside the 2D boxes."""
    grid, s, c = sampler.grid, sampler.scale, sampler.chunk
    return (random_grid_points(grid, root, s, K, boxes[0], sampler.hand_queries, generator, c),
            random_grid_points(grid, center, s, K, boxes[1], sampler.object_queries, generator, c))


class QuerySampler(nn.Module):
    """Chooses the scaled query points of the pose stage: ground-truth guided rows in training, field-guided
    grid points otherwise (see :mod:`hoisdf.model.sampling`).

    Args:
        grid: (G, 3) scaled inference lattice (a non-persistent buffer: not in the state dict).
        hand_queries: hand query points per sample (``model.hand_queries``).
        object_queries: object query points per sample.
        scale: metres -> scaled units (``sdf_scale``).
        chunk: grid points per SDF-decoder call.
        fixed_shape: decode the whole grid with the boxes as masks (static shapes).
        rows: the training-row variant (:func:`near_surface_rows`, :func:`inside_mesh_rows`,
            :func:`random_box_rows`): (sampler, batch, K, root, center, boxes, generator) -> scaled (hand, obj).
        train_strategy: the field-guided ranking in training mode (:class:`hoisdf.model.sampling.Ranking`).
        eval_strategy: the field-guided ranking in evaluation mode ("gradient": the one that steps onto the surface
            along the full field gradient).
        reuse_ranking_sdf: field-guided points carry into their tokens the SDF of the ranking pass (the reference:
            its dropout mask in training) instead of a second pass.
    """

    def __init__(self, grid: torch.Tensor, hand_queries: int, object_queries: int, scale: float, chunk: int,
                 fixed_shape: bool, rows: Callable, train_strategy: Ranking, eval_strategy: Ranking,
                 reuse_ranking_sdf: bool = False):
        super().__init__()
        self.register_buffer("grid", grid, persistent=False)
        self.hand_queries, self.object_queries, self.scale, self.chunk = hand_queries, object_queries, scale, chunk
        self.fixed_shape, self.rows, self.reuse_ranking_sdf = bool(fixed_shape), rows, reuse_ranking_sdf
        self.strategies = {True: train_strategy, False: eval_strategy}

    def training_points(self, batch, K, root, center, boxes, generator):
        """Scaled ground-truth guided points: hand rel. root (B, Nh, 3), object rel. centre (B, No, 3)."""
        return self.rows(self, batch, K, root, center, boxes, generator)

    def field_points(self, K, root, center, boxes, fns, newton_fns, generator):
        """Scaled field-guided points ((hand (B, Nh, 3), object (B, No, 3)), (their SDFs (B, Nh), (B, No) from the
        ranking pass, unclamped)); ``fns``: (hand, object) SDF functions of camera points that rank the grid;
        ``newton_fns``: (hand, object) full-gradient fields (or None)."""
        strategy = self.strategies[self.training]
        newton_fns = newton_fns if strategy.newton else (None, None)
        hand, hand_sdf = field_guided_points(self.grid, root, self.scale, K, boxes[0], fns[0], self.hand_queries,
                                             strategy, self.chunk, generator, self.fixed_shape, newton_fns[0])
        obj, obj_sdf = field_guided_points(self.grid, center, self.scale, K, boxes[1], fns[1], self.object_queries,
                                           strategy, self.chunk, generator, self.fixed_shape, newton_fns[1])
        return (hand, obj), (hand_sdf, obj_sdf)

    def uses_newton(self) -> bool:
        """Whether :meth:`field_points` would use the full-gradient fields now (build them only then)."""
        return self.strategies[self.training].newton


# --- token features -------------------------------------------------------------------------------------------
class PlainFeatures:
    """``feature_augmentation = "none"``: the image feature as it is (no learned density width)."""

    extra, learns_beta = 0, False

    def __call__(self, feat: torch.Tensor, sdf: torch.Tensor | None, beta) -> torch.Tensor:
        return full(feat)


@dataclass(frozen=True)
class DensityScaled:
    """``"density"``: feature (B, N, F) x the volume density of the detached scaled SDF (B, N).

    ``sign``: -1 the paper's sigmoid(-d/beta)/beta, +1 the released code's; ``beta_min``: floor of the width (None:
    none here, the model projects the width itself).
    """

    sign: float
    beta_min: float | None
    extra, learns_beta = 0, True

    def __call__(self, feat: torch.Tensor, sdf: torch.Tensor | None, beta: torch.Tensor) -> torch.Tensor:
        feat = full(feat)
        if sdf is None:  # "image" cross tokens: no field information
            return feat
        return feat * H.density(sdf.detach(), beta, self.sign, self.beta_min)[..., None]


@dataclass(frozen=True)
class Concatenated:
    """``"density_concat"`` / ``"distance_concat"``: feature (B, N, F) + one channel, the density of the detached
    SDF (``density=True``) or the SDF itself; ones where there is no field ("image" cross tokens)."""

    density: bool
    sign: float
    beta_min: float | None
    extra, learns_beta = 1, True

    def __call__(self, feat: torch.Tensor, sdf: torch.Tensor | None, beta: torch.Tensor) -> torch.Tensor:
        feat = full(feat)
        if sdf is None:
            return torch.cat([feat, torch.ones_like(feat[..., :1])], -1)
        sdf = sdf.detach()
        value = H.density(sdf, beta, self.sign, self.beta_min) if self.density else sdf
        return torch.cat([feat, value[..., None].to(feat)], -1)


# --- cross field: which SDF augments the other entity's points (None: no cross tokens) ------------------------
# Each takes the SDFs (B, N) of hand points in the hand field, object points in the object field, hand points
# in the object field, object points in the hand field, and the two learned widths; it returns
# ((sdf, width) of the object points in the hand transformer, (sdf, width) of the hand points in the object one).
def cross_sdf(d_h, d_o, d_ho, d_oh, hand_beta, obj_beta):
    """``cross_field = "sdf"``: each entity's points carry the other entity's field (HOISDF)."""
    return (d_oh, hand_beta), (d_ho, obj_beta)


def cross_image(d_h, d_o, d_ho, d_oh, hand_beta, obj_beta):
    """``"image"``: cross tokens with image features only."""
    return (None, hand_beta), (None, obj_beta)


def cross_target(d_h, d_o, d_ho, d_oh, hand_beta, obj_beta):
    """``"target"``: each entity's points carry their own field."""
    return (d_o, obj_beta), (d_h, hand_beta)
