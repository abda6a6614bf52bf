"""Small generic layers shared by the HOISDF model."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class MLP(nn.Module):
    """Stack of ``nn.Linear`` layers with ReLU between them.

    Dimensions ``in_dim -> hidden[0] -> ... -> hidden[-1] -> out_dim``. A ReLU follows every layer except the
    last; with ``relu_last=True`` the last layer is followed by a ReLU as well (upstream's feature MLPs
    ``linear_sdfin`` / ``linear_transformerin``); prediction heads use ``relu_last=False``.

    Input ``(..., in_dim)`` -> output ``(..., out_dim)``; works on any number of leading dimensions.
    """

    def __init__(self, in_dim: int, hidden: Sequence[int], out_dim: int, relu_last: bool = False) -> None:
        super().__init__()
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
        return self.layers(x)
