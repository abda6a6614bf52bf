"""ResNet encoder + U-Net decoder producing the 5-level feature pyramid and the three 2D auxiliary maps.

Follows the upstream HOISDF backbone (docs/upstream.md, "Backbone and decoder" and "Initialisation"):

- a torchvision ResNet-18/34/50 (fc and avgpool unused) gives skip features at strides 2, 4, 8, 16, 32;
- a U-Net decoder (:data:`SMALL` = upstream ``Decoder``, :data:`BIG` = upstream ``Decoder_big``) refines them into a
  pyramid ``[stride2, stride4, stride8, stride16, stride32]`` whose channel counts are ``ResNetUNet.channels``
  (R50: small 32/64/128/256/512, sum 992; big 128/256/512/1024/2048, sum 3968);
- three 1x1-conv heads on the stride-2 map give ``(B, 3, S/2, S/2)``: channel 0 the single-channel joint
  heatmap (raw), channels 1 and 2 the hand and object mask **logits** (upstream applies a sigmoid and uses
  ``BCELoss``; here the sigmoid is left to the loss, ``BCEWithLogits``, which is numerically safer).

Input: RGB ``(B, 3, S, S)`` in [0, 1], S a multiple of 32. Upstream feeds [0, 1] images without ImageNet
normalisation (``normalize_input=False`` reproduces that); torchvision's pretrained weights expect
normalised input, so the default ``normalize_input=True`` subtracts the ImageNet mean and divides by the std.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
import torchvision
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

_RESNETS = {
    18: (torchvision.models.resnet18, torchvision.models.ResNet18_Weights),
    34: (torchvision.models.resnet34, torchvision.models.ResNet34_Weights),
    50: (torchvision.models.resnet50, torchvision.models.ResNet50_Weights),
}


def resnet_channels(depth: int) -> list[int]:
    """Channels of the skip features (stride2 = conv1 output, layer1..layer4) of a torchvision ResNet."""
    if depth not in _RESNETS:
        raise ValueError(f"depth must be one of {sorted(_RESNETS)}, got {depth}")
    return [64, 256, 512, 1024, 2048] if depth >= 50 else [64, 64, 128, 256, 512]


def imagenet_weights_path(depth: int) -> Path:
    """Where torchvision would cache the IMAGENET1K_V1 weights of ResNet-``depth`` (torch hub checkpoints dir)."""
    url = _RESNETS[depth][1].IMAGENET1K_V1.url
    return Path(torch.hub.get_dir()) / "checkpoints" / url.rsplit("/", 1)[-1]


NAMED_WEIGHTS = {"imagenet": imagenet_weights_path}
"""Backbone weights named in the settings (``model.weights``) -> their file for a ResNet depth; any other value is a
path."""


def conv_bn_relu(in_ch: int, out_ch: int, kernel: int = 3, final: bool = True) -> nn.Sequential:
    """Conv2d (k=kernel, same padding, with bias) optionally followed by BatchNorm + ReLU."""
    layers: list[nn.Module] = [nn.Conv2d(in_ch, out_ch, kernel, padding=kernel // 2)]
    if final:
        layers += [nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


def deconv_bn_relu(in_ch: int, out_ch: int) -> nn.Sequential:
    """x2 upsampling: ConvTranspose2d(k=4, s=2, p=1, no bias) + BatchNorm + ReLU."""
    return nn.Sequential(nn.ConvTranspose2d(in_ch, out_ch, 4, stride=2, padding=1, bias=False),
                         nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True))


def head(channels: list[int]) -> nn.Sequential:
    """A 1x1-conv stack ``channels[0] -> ... -> channels[-1]``, BN + ReLU between, none after the last conv."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(channels)):
        layers.append(conv_bn_relu(a, b, kernel=1, final=i < len(channels) - 2))
    return nn.Sequential(*layers)


class UpStage(nn.Module):
    """One decoder stage: ``fuse(concat[lateral(skip), deconv(coarse)])`` at twice the coarse resolution."""

    def __init__(self, skip_in: int, skip_out: int, coarse_in: int, up_out: int, out_ch: int, lateral: bool):
        super().__init__()
        self.lateral = conv_bn_relu(skip_in, skip_out, kernel=1) if lateral else nn.Identity()
        if not lateral and skip_in != skip_out:
            raise ValueError("without a lateral conv the skip channels pass through unchanged")
        self.up = deconv_bn_relu(coarse_in, up_out)
        self.fuse = conv_bn_relu(skip_out + up_out, out_ch, kernel=3)

    def forward(self, skip: torch.Tensor, coarse: torch.Tensor) -> torch.Tensor:
        """skip (B, skip_in, 2h, 2w), coarse (B, coarse_in, h, w) -> (B, out_ch, 2h, 2w)."""
        return self.fuse(torch.cat([self.lateral(skip), self.up(coarse)], dim=1))


def _check_channels(channels: list[int]) -> None:
    if min(channels) < 8:
        raise ValueError(f"decoder channel counts must be >= 8, got {channels}")


class SmallDecoder(nn.Module):
    """Upstream ``Decoder``: pyramid channels ``[c0/2, c1/4, c2/4, c3/4, c4/4]`` for skip channels c0..c4."""

    def __init__(self, c: list[int]):
        super().__init__()
        c0, c1, c2, c3, c4 = c
        self.channels = [c0 // 2, c1 // 4, c2 // 4, c3 // 4, c4 // 4]
        _check_channels(self.channels)
        self.top = conv_bn_relu(c4, c4 // 4, kernel=1)
        # The first deconv upsamples the raw layer4 output (c4 channels), as upstream does.
        self.up16 = UpStage(c3, c3 // 4, c4, c3 // 4, c3 // 4, lateral=True)
        self.up8 = UpStage(c2, c2 // 4, c3 // 4, c2 // 4, c2 // 4, lateral=True)
        self.up4 = UpStage(c1, c1 // 4, c2 // 4, c1 // 4, c1 // 4, lateral=True)
        self.up2 = UpStage(c0, c0 // 2, c1 // 4, c1 // 4, c0 // 2, lateral=True)

    def forward(self, skips: list[torch.Tensor]) -> list[torch.Tensor]:
        """Skip features stride2..stride32 -> decoded pyramid stride2..stride32."""
        s2, s4, s8, s16, s32 = skips
        d16 = self.up16(s16, s32)
        d8 = self.up8(s8, d16)
        d4 = self.up4(s4, d8)
        d2 = self.up2(s2, d4)
        return [d2, d4, d8, d16, self.top(s32)]


class BigDecoder(nn.Module):
    """Upstream ``Decoder_big``: pyramid channels ``[c1/2, c1, c2, c3, c4]`` (stride32 is raw layer4)."""

    def __init__(self, c: list[int]):
        super().__init__()
        c0, c1, c2, c3, c4 = c
        self.channels = [c1 // 2, c1, c2, c3, c4]
        _check_channels(self.channels)
        self.up16 = UpStage(c3, c3, c4, c3, c3, lateral=False)
        self.up8 = UpStage(c2, c2, c3, c2, c2, lateral=False)
        self.up4 = UpStage(c1, c1, c2, c1, c1, lateral=False)
        self.up2 = UpStage(c0, c0, c1, c1 // 2, c1 // 2, lateral=False)

    def forward(self, skips: list[torch.Tensor]) -> list[torch.Tensor]:
        """Skip features stride2..stride32 -> decoded pyramid stride2..stride32."""
        s2, s4, s8, s16, s32 = skips
        d16 = self.up16(s16, s32)
        d8 = self.up8(s8, d16)
        d4 = self.up4(s4, d8)
        d2 = self.up2(s2, d4)
        return [d2, d4, d8, d16, s32]


def init_decoder_(module: nn.Module, std: float = 1e-3) -> None:
    """Upstream decoder init (docs/upstream.md, "Initialisation"): conv/deconv weights N(0, std), conv bias 0, BN
    weight 1 / bias 0."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.normal_(m.weight, std=std)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


@dataclass(frozen=True)
class DecoderKind:
    """A U-Net decoder variant: its module class and the hidden widths of the 2D heads for a top level of ``c``
    channels."""

    module: type
    head_hidden: Callable[[int], list[int]]


SMALL = DecoderKind(SmallDecoder, lambda c: [c, c])
BIG = DecoderKind(BigDecoder, lambda c: [c, c, c // 2])
DECODERS = {"small": SMALL, "big": BIG}
"""``model.decoder`` -> the decoder variant: "small" upstream's ``Decoder``, "big" its ``Decoder_big``."""


class ResNetUNet(nn.Module):
    """ResNet encoder + U-Net decoder + 2D heads.

    Args:
        depth: 18, 34 or 50 (torchvision ResNet, built with ``weights=None``).
        decoder: :data:`SMALL` (upstream ``Decoder``) or :data:`BIG` (upstream ``Decoder_big``), see :data:`DECODERS`.
        weights: None (random init); a path to a torchvision-layout ResNet state dict (``fc.*`` ignored,
            everything else loaded strictly); or "imagenet": torchvision's IMAGENET1K_V1 file from the torch
            hub cache (never downloaded; FileNotFoundError naming the expected path if absent).
        freeze_bn_affine: set ``requires_grad=False`` on the backbone's BatchNorm weights/biases except the
            ``downsample`` BNs (upstream's ``freeze_stages`` quirk, docs/upstream.md, "Backbone and decoder");
            running statistics still update.
        normalize_input: subtract the ImageNet mean / divide by the std inside ``forward``.
        channels_last: NHWC weights and activations; the numbers are the same as with NCHW (``False``). On 2 CPU
            cores a toy training step was 0.97-1.14x as fast as with NCHW over four runs of
            ``bench/bench_train_step.py``, within a shared machine's noise; GPUs not measured.

    Attributes:
        channels: pyramid channel counts, stride2..stride32 (sum = per-point feature dim C).
    """

    def __init__(self, depth: int = 50, decoder: DecoderKind = SMALL, weights: str | os.PathLike | None = None,
                 freeze_bn_affine: bool = True, normalize_input: bool = True, channels_last: bool = False):
        super().__init__()
        skip_channels = resnet_channels(depth)
        self.depth = depth
        self.normalize_input = normalize_input
        self.backbone = _RESNETS[depth][0](weights=None)
        self.backbone.fc = nn.Identity()
        self.backbone.avgpool = nn.Identity()
        self.decoder: nn.Module = decoder.module(skip_channels)
        self.channels: list[int] = list(self.decoder.channels)
        hidden = decoder.head_hidden(self.channels[0])
        self.heatmap_head = head(hidden + [1])
        self.hand_mask_head = head(hidden + [1])
        self.obj_mask_head = head(hidden + [1])
        for m in (self.decoder, self.heatmap_head, self.hand_mask_head, self.obj_mask_head):
            init_decoder_(m)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if weights is not None:
            self.load_backbone(weights)
        if freeze_bn_affine:
            for p in frozen_bn_parameters(self.backbone):
                p.requires_grad_(False)
        self.memory_format = torch.channels_last if channels_last else torch.contiguous_format
        self.to(memory_format=self.memory_format)

    @property
    def feature_dim(self) -> int:
        """Sum of the pyramid channels: the per-point feature dimension C."""
        return sum(self.channels)

    def load_backbone(self, weights: str | os.PathLike) -> None:
        """Load ResNet weights ("imagenet" = torch hub cache file, or a .pth path); ``fc.*`` keys are dropped."""
        named = NAMED_WEIGHTS.get(str(weights))
        if named is not None:
            path = named(self.depth)
            if not path.is_file():
                url = _RESNETS[self.depth][1].IMAGENET1K_V1.url
                raise FileNotFoundError(
                    f"ImageNet weights for ResNet-{self.depth} not found at {path}. Nothing is downloaded at run "
                    f"time: fetch {url} into that folder (or set TORCH_HOME), or pass the file's path as weights.")
        else:
            path = Path(weights)  # missing, a folder or not a checkpoint: read_torch's one line
        from hoidata.errors import DataError
        from hoidata.reading_media import read_torch

        state = read_torch(path, "backbone weights file")
        if not isinstance(state, dict) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
            raise DataError(path, None, f"expected a ResNet-{self.depth} state dict of tensors")
        try:
            self.backbone.load_state_dict({k: v for k, v in state.items() if not k.startswith("fc.")}, strict=True)
        except RuntimeError as exc:  # missing, unexpected or misshaped keys
            lines = str(exc).splitlines()
            raise DataError(path, None, f"not ResNet-{self.depth} weights ({lines[0] if lines else exc})") from None

    def encode(self, img: torch.Tensor) -> list[torch.Tensor]:
        """Image (B, 3, S, S) (already normalised if wanted) -> ResNet skip features stride2..stride32."""
        r = self.backbone
        s2 = r.relu(r.bn1(r.conv1(img)))
        s4 = r.layer1(r.maxpool(s2))
        s8 = r.layer2(s4)
        s16 = r.layer3(s8)
        s32 = r.layer4(s16)
        return [s2, s4, s8, s16, s32]

    def forward(self, img: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        """RGB ``img`` (B, 3, S, S) in [0, 1], S a multiple of 32.

        Returns:
            pyramid: [stride2 (B, channels[0], S/2, S/2), ..., stride32 (B, channels[4], S/32, S/32)];
            maps: (B, 3, S/2, S/2): ch0 joint heatmap (raw), ch1 hand mask logits, ch2 object mask logits.
        """
        if img.ndim != 4 or img.shape[1] != 3 or img.shape[-1] % 32 or img.shape[-2] % 32:
            raise ValueError(f"expected an image batch (B, 3, S, S) with S a multiple of 32, got {tuple(img.shape)}")
        if self.normalize_input:
            img = (img - self.mean) / self.std
        img = img.contiguous(memory_format=self.memory_format)
        pyramid = self.decoder(self.encode(img))
        top = pyramid[0]
        maps = torch.cat([self.heatmap_head(top), self.hand_mask_head(top), self.obj_mask_head(top)], dim=1)
        return pyramid, maps


def frozen_bn_parameters(backbone: nn.Module) -> list[nn.Parameter]:
    """The BatchNorm affine parameters that upstream freezes: every backbone BN except ``downsample`` ones."""
    params = []
    for name, m in backbone.named_modules():
        if isinstance(m, nn.BatchNorm2d) and "downsample" not in name:
            params += [m.weight, m.bias]
    return params
