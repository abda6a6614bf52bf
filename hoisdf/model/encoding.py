"""Point encodings: Fourier positional codes and pixel-aligned image features.

Conventions
-----------
* Points are in the OpenCV camera frame (x right, y down, z forward), metres.
* ``K`` is the intrinsic matrix of the *crop* (pixel coordinates of the network input image).
* Pixels follow the OpenCV convention: pixel centres lie at integer coordinates, so an ``S``-pixel-wide
  image spans ``[-0.5, S - 0.5]``. Normalised grid coordinates are for ``grid_sample(align_corners=False)``,
  under which ``-1`` / ``+1`` are the outer edges of the image; a feature map of any stride covering the same
  image therefore uses the same normalised coordinates.
* :data:`UPSTREAM` (``model.pixel_convention = "upstream"``) is the released code's convention instead: the
  normalised coordinate is ``(uv - (S-1)/2) / ((S-1)/2)`` with ``grid_sample(align_corners=True)`` (amathislab/HOISDF
  ``main/model.py``), i.e. input pixel ``u`` lands at ``u (W-1)/(S-1)`` on a level of width ``W``. Both agree at
  the crop centre and differ by ``0.5 - W/(2S)`` level pixels at the border (up to 15.5 input pixels at
  stride 32); released checkpoints were trained with it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from hoisdf.model.precision import full, no_autocast


@dataclass(frozen=True)
class PixelCenters:
    """The stores' convention: pixel centres at integers, ``grid_sample(align_corners=False)``."""

    align_corners = False

    def to_grid(self, uv: torch.Tensor, image_size: int) -> torch.Tensor:
        """``g = (uv + 0.5) / S * 2 - 1`` (``-1`` = left/top image edge, ``+1`` = right/bottom)."""
        return (uv + 0.5) / float(image_size) * 2.0 - 1.0

    def mask_box(self, box: torch.Tensor, image_size: int, width: int) -> torch.Tensor:
        """Mask-pixel box edges (B, 4) -> input pixels: a mask pixel i covers input pixels around
        ``(i + 0.5) * S / w - 0.5``."""
        return box * (image_size / width) - 0.5


@dataclass(frozen=True)
class UpstreamPixels:
    """The released code's convention: ``g = (uv - c) / c`` with ``c = (S - 1) / 2``, ``align_corners=True``."""

    align_corners = True

    def to_grid(self, uv: torch.Tensor, image_size: int) -> torch.Tensor:
        """``g = (uv - c) / c``, computed as the released code does."""
        c = (image_size - 1) / 2.0
        return (uv - c) / c

    def mask_box(self, box: torch.Tensor, image_size: int, width: int) -> torch.Tensor:
        """Mask-pixel box edges (B, 4) -> input pixels: mask pixel i sits at input pixel ``i (S - 1) / (w - 1)``."""
        return (box - 0.5) * ((image_size - 1) / max(width - 1, 1))


CENTERS, UPSTREAM = PixelCenters(), UpstreamPixels()
PIXEL_CONVENTIONS = {"centers": CENTERS, "upstream": UPSTREAM}
"""``model.pixel_convention`` -> the convention: ``centers`` the stores' pixel centres (align_corners=False);
``upstream`` the released code's."""
MIN_DEPTH = 1e-6
"""Depths (z, metres) are clamped to at least this before the perspective division."""


def fourier_encode(x: torch.Tensor, n_freq: int = 5) -> torch.Tensor:
    """NeRF-style Fourier code without the input and without a pi factor.

    Args:
        x: ``(..., 3)`` points (HOISDF: scaled space, |coords| <~ 1).
        n_freq: number of octaves; frequencies ``2^0 .. 2^(n_freq-1)``.

    Returns:
        ``(..., 6 * n_freq)``; for each frequency ``f`` (ascending) the block
        ``[sin(f x), sin(f y), sin(f z), cos(f x), cos(f y), cos(f z)]``.
    """
    freqs = 2.0 ** torch.arange(n_freq, device=x.device, dtype=x.dtype)  # (F,)
    scaled = x.unsqueeze(-2) * freqs.unsqueeze(-1)  # (..., F, 3)
    code = torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-1)  # (..., F, 6)
    return code.flatten(-2)


def project_points(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pinhole projection of camera-frame points to pixel coordinates.

    Args:
        points: ``(B, N, 3)`` camera-frame points, metres.
        K: ``(B, 3, 3)`` intrinsics (pixels).

    Returns:
        ``(B, N, 2)`` pixel coordinates ``(u, v)``, in full precision (fp32, or fp64 for fp64 points) even under
        autocast. The homogeneous depth is clamped to ``MIN_DEPTH`` so points on or behind the camera give large
        but finite values (never inf/nan).
    """
    points = full(points)
    with no_autocast(points):
        homo = torch.einsum("bij,bnj->bni", K.to(points.dtype), points)  # (B, N, 3)
    depth = homo[..., 2:3].clamp_min(MIN_DEPTH)
    return homo[..., :2] / depth


def pixel_to_grid(uv: torch.Tensor, image_size: int, convention=CENTERS) -> torch.Tensor:
    """Pixel coordinates ``(B, N, 2)`` (OpenCV convention, pixel centres at integers) of a square ``image_size``
    input -> normalised ``grid_sample`` coordinates ``(B, N, 2)`` of ``convention`` (:data:`CENTERS` or
    :data:`UPSTREAM`)."""
    return convention.to_grid(uv, image_size)


def _sample(fmap: torch.Tensor, grid: torch.Tensor, convention=CENTERS) -> torch.Tensor:
    """(B, C, H, W) map at (B, 1, N, 2) full-precision coordinates -> (B, N, C) in the grid's dtype (a bf16 map
    is sampled as fp32: bilinear weights from bf16 coordinates would be off by up to a pixel)."""
    with no_autocast(grid):
        sampled = F.grid_sample(fmap.to(grid.dtype), grid, mode="bilinear", padding_mode="border",
                                align_corners=convention.align_corners)  # (B, C, 1, N)
    return sampled.squeeze(2).transpose(1, 2)


def sample_pyramid(features: Sequence[torch.Tensor], grid: torch.Tensor, detach: bool = True,
                   convention=CENTERS) -> torch.Tensor:
    """Bilinearly sample every pyramid level at the same normalised locations and concatenate.

    Args:
        features: list of ``(B, C_l, H_l, W_l)`` maps covering the same image extent (any strides).
        grid: ``(B, N, 2)`` normalised coordinates (see :func:`pixel_to_grid`). Detached by default: no gradient
            flows back to the points, only to the features; ``detach=False`` keeps d(feature)/d(grid) (the
            full field gradient of the "gradient" sampling step).
        convention: the pixel convention ``grid`` was made with (:func:`pixel_to_grid`).

    Returns:
        ``(B, N, sum_l C_l)`` in full precision, levels concatenated in list order. Outside the image the border
        value is used (``padding_mode="border"``).
    """
    grid = full(grid.detach() if detach else grid).unsqueeze(1)  # (B, 1, N, 2)
    return torch.cat([_sample(fmap, grid, convention) for fmap in features], dim=-1)


def pixel_aligned_features(features: Sequence[torch.Tensor], points_cam: torch.Tensor, K: torch.Tensor,
                           image_size: int, detach: bool = True, convention=CENTERS) -> torch.Tensor:
    """Project camera-frame points into the image and sample the feature pyramid there.

    Args:
        features: list of ``(B, C_l, H_l, W_l)`` feature maps of the ``image_size``-pixel input crop.
        points_cam: ``(B, N, 3)`` camera-frame points, metres.
        K: ``(B, 3, 3)`` crop intrinsics.
        image_size: input crop side length in pixels.
        detach: no gradient to ``points_cam`` (the default); ``False`` for the full field gradient.
        convention: pixel convention, :data:`CENTERS` or :data:`UPSTREAM` (:func:`pixel_to_grid`).

    Returns:
        ``(B, N, sum_l C_l)`` features.
    """
    uv = project_points(points_cam.detach() if detach else points_cam, K)
    return sample_pyramid(features, pixel_to_grid(uv, image_size, convention), detach, convention)


def project_pyramid(features: Sequence[torch.Tensor], linear: nn.Linear) -> list[torch.Tensor]:
    """Apply a Linear layer over concatenated pyramid features *before* sampling: one 1x1 conv per level.

    Bilinear sampling is linear per channel, so ``linear(sample_pyramid(features, g))`` equals
    ``sum_l sample(conv_l(features_l), g) + bias`` with ``conv_l`` the weight columns of level l. For many
    points (the 64^3 inference grid) this moves the widest matrix product from every point to every pixel
    and samples ``out_features`` channels instead of ``sum C_l``. Returns per-level (B, out, H_l, W_l) maps
    without the bias; use :func:`sample_projected`.
    """
    out, start = [], 0
    for fmap in features:
        c = fmap.shape[1]
        weight = linear.weight[:, start:start + c, None, None].to(fmap.dtype)
        out.append(F.conv2d(fmap, weight))
        start += c
    if start != linear.in_features:
        raise ValueError(f"pyramid has {start} channels, the layer expects {linear.in_features}")
    return out


def sample_projected(projected: Sequence[torch.Tensor], grid: torch.Tensor, bias: torch.Tensor,
                     convention=CENTERS) -> torch.Tensor:
    """(B, N, out): the sum over levels of the sampled projected maps, plus ``bias`` (see :func:`project_pyramid`);
    ``grid`` made with ``convention`` (:func:`pixel_to_grid`)."""
    grid = full(grid.detach()).unsqueeze(1)
    total = bias.to(grid.dtype)
    for fmap in projected:
        total = total + _sample(fmap, grid, convention)
    return total
