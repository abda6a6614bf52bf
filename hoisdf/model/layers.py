"""Small generic layers shared by the HOISDF model."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from hoisdf.model.precision import full, no_autocast


class MLP(nn.Module):
    """Stack of ``nn.Linear`` layers with ReLU between them.

    Dimensions ``in_dim -> hidden[0] -> ... -> hidden[-1] -> out_dim``. A ReLU follows every layer except the
    last; with ``relu_last=True`` the last layer is followed by a ReLU as well (upstream's feature MLPs
    ``linear_sdfin`` / ``linear_transformerin``); prediction heads use ``relu_last=False`` and
    ``full_precision_out=True``: their last layer runs in full precision even under autocast (the outputs are
    geometry: rotations, offsets, translations).

    Input ``(..., in_dim)`` -> output ``(..., out_dim)``; works on any number of leading dimensions.
    """

    def __init__(self, in_dim: int, hidden: Sequence[int], out_dim: int, relu_last: bool = False,
                 full_precision_out: bool = False) -> None:
        super().__init__()
        if relu_last and full_precision_out:
            raise ValueError("full_precision_out is for prediction heads (relu_last=False)")
        self.full_precision_out = full_precision_out
        dims = [int(in_dim), *[int(h) for h in hidden], int(out_dim)]
        layers: list[nn.Module] = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2 or relu_last:
                layers.append(nn.ReLU(inplace=True))
        self.layers = nn.Sequential(*layers)
        self.in_dim = dims[0]
        self.out_dim = dims[-1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (..., in_dim)`` -> ``(..., out_dim)``."""
        if not self.full_precision_out:
            return self.layers(x)
        last = self.layers[-1]
        h = full(self.layers[:-1](x))
        with no_autocast(h):
            return last(h.to(last.weight.dtype))
