"""DeepSDF-style signed-distance decoder (one instance for the hand, one for the object)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.parametrizations import weight_norm as _weight_norm

from hoisdf.model.precision import full, no_autocast


class SDFDecoder(nn.Module):
    """Per-point MLP ``[feature, fourier, xyz] -> SDF`` with a DeepSDF skip connection and a final tanh.

    With the defaults the layer widths are ``289 -> 512 -> 223 -> (223+289=512) -> 512 -> 512 -> 1``:
    hidden layers ``0 .. n_hidden-1`` are ``Linear`` (optionally weight-normalised) + ReLU + dropout, the raw
    input is concatenated again in front of hidden layer ``latent_in`` (so layer ``latent_in - 1`` outputs
    ``hidden - in_dim``), and the last layer is a plain ``Linear(hidden, 1)`` followed by ``tanh``.

    Dropout is functional and active whenever the module is in train mode. The decoder is a pure per-point
    function (no normalisation across points), so it can be applied to arbitrarily large point chunks.

    Args:
        feat_dim: per-point image-feature width (output of ``linear_sdfin``).
        pe_dim: Fourier-code width.
        hidden: hidden width.
        n_hidden: number of hidden (ReLU) layers.
        latent_in: index of the hidden layer that receives the re-concatenated input; ``None`` disables it.
        dropout: dropout probability after every hidden layer.
        weight_norm: wrap the hidden ``Linear`` layers in weight normalisation.
    """

    def __init__(self, feat_dim: int = 256, pe_dim: int = 30, hidden: int = 512, n_hidden: int = 4,
                 latent_in: int | None = 2, dropout: float = 0.2, weight_norm: bool = True) -> None:
        super().__init__()
        self.in_dim = feat_dim + pe_dim + 3
        if latent_in is not None:
            if not 1 <= latent_in < n_hidden:
                raise ValueError(f"latent_in must be in [1, {n_hidden - 1}], got {latent_in}")
            if hidden <= self.in_dim:
                raise ValueError(f"hidden ({hidden}) must exceed the input width ({self.in_dim}) for the skip")
        self.latent_in = latent_in
        self.dropout = float(dropout)
        layers = []
        for i in range(n_hidden):
            d_in = self.in_dim if i == 0 else hidden
            d_out = hidden - self.in_dim if latent_in is not None and i + 1 == latent_in else hidden
            lin = nn.Linear(d_in, d_out)
            layers.append(_weight_norm(lin) if weight_norm else lin)
        self.hidden_layers = nn.ModuleList(layers)
        self.out_layer = nn.Linear(hidden, 1)

    def forward(self, feat: torch.Tensor, pe: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        """Predict the SDF at every point.

        Args:
            feat: ``(B, N, feat_dim)`` image features.
            pe: ``(B, N, pe_dim)`` Fourier codes of ``xyz``.
            xyz: ``(B, N, 3)`` points in scaled space.

        Returns:
            ``(B, N)`` SDF in scaled units, in ``(-1, 1)`` (tanh); any leading dims work the same way. The hidden
            layers follow autocast; the output layer and the tanh run in full precision (the values are ranked).
        """
        x = torch.cat([feat, pe, xyz], dim=-1)
        h = x
        for i, layer in enumerate(self.hidden_layers):
            if i == self.latent_in:
                h = torch.cat([h, x], dim=-1)
            h = F.relu(layer(h))
            h = F.dropout(h, p=self.dropout, training=self.training)
        h = full(h)
        with no_autocast(h):
            return torch.tanh(self.out_layer(h.to(self.out_layer.weight.dtype))).squeeze(-1)


def init_sdf_decoder_weights(decoder: SDFDecoder) -> None:
    """Upstream's training initialisation (docs/upstream.md, "Initialisation") of an :class:`SDFDecoder`.

    Upstream draws every ``nn.Linear`` weight from N(0, 0.01) with zero bias; for the weight-normalised hidden
    layers the weight draw has no effect (the weight is recomputed from ``g``/``v``), so only their biases
    become zero. The plain output layer gets N(0, 0.01) weights and a zero bias.
    """
    with torch.no_grad():
        for layer in decoder.hidden_layers:
            layer.bias.zero_()
            if not hasattr(layer, "parametrizations"):
                layer.weight.normal_(0.0, 0.01)
        decoder.out_layer.weight.normal_(0.0, 0.01)
        decoder.out_layer.bias.zero_()
