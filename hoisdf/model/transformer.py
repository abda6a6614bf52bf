"""DETR / Keypoint-Transformer style post-norm encoder and query decoder (batch-first tensors).

Shapes: ``B`` batch, ``T`` tokens, ``Q`` queries, ``D`` model width, ``L`` layers. Positional embeddings of the
tokens are all zero in HOISDF, so the encoder takes none; the decoder adds learned query positions.
Boolean attention masks follow ``nn.MultiheadAttention``: ``True`` = attention blocked.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

MANO_QUERY_GROUPS: tuple[tuple[int, ...], ...] = ((0,), (1, 2, 3), (4, 5, 6), (7, 8, 9), (10, 11, 12),
                                                  (13, 14, 15), (16,))
"""Decoder query groups: global rotation, the five fingers (MANO joint order), shape."""


class _FeedForward(nn.Module):
    """``Linear(d, ff) -> ReLU -> dropout -> Linear(ff, d)``."""

    def __init__(self, d: int, ff: int, dropout: float) -> None:
        super().__init__()
        self.linear1 = nn.Linear(d, ff)
        self.linear2 = nn.Linear(ff, d)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear2(self.dropout(F.relu(self.linear1(x))))


class EncoderLayer(nn.Module):
    """Post-norm layer: self-attn -> dropout -> add -> LN -> FFN -> dropout -> add -> LN.

    ``forward(x (B, T, D), mask (T, T) bool | None) -> (B, T, D)``.
    """

    def __init__(self, d: int = 256, heads: int = 4, ff: int = 1024, dropout: float = 0.1) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, heads, dropout=dropout, batch_first=True)
        self.ffn = _FeedForward(d, ff, dropout)
        self.norm1 = nn.LayerNorm(d)
        self.norm2 = nn.LayerNorm(d)
        self.dropout1 = nn.Dropout(dropout)
        self.dropout2 = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        attn = self.self_attn(x, x, x, attn_mask=mask, need_weights=False)[0]
        x = self.norm1(x + self.dropout1(attn))
        return self.norm2(x + self.dropout2(self.ffn(x)))


class TokenEncoder(nn.Module):
    """Stack of :class:`EncoderLayer` returning every layer's output through one shared ``inter_norm``.

    ``forward(tokens (B, T, D)) -> (intermediate (L, B, T, D), memory (B, T, D))``; ``memory`` is the raw output
    of the last layer (it already ends in that layer's LayerNorm), as consumed by the decoder.
    """

    def __init__(self, n_layers: int = 6, d: int = 256, heads: int = 4, ff: int = 1024,
                 dropout: float = 0.1) -> None:
        super().__init__()
        self.layers = nn.ModuleList(EncoderLayer(d, heads, ff, dropout) for _ in range(n_layers))
        self.inter_norm = nn.LayerNorm(d)

    def forward(self, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = tokens
        intermediate = []
        for layer in self.layers:
            x = layer(x)
            intermediate.append(self.inter_norm(x))
        return torch.stack(intermediate), x


class DecoderLayer(nn.Module):
    """Post-norm decoder layer: query self-attn, cross-attn to memory, FFN (each -> dropout -> add -> LN).

    The query positions are added to queries and keys of the self-attention and to the query of the
    cross-attention; values never carry them, and the memory has no positional embedding.
    """

    def __init__(self, d: int = 256, heads: int = 4, ff: int = 1024, dropout: float = 0.1) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, heads, dropout=dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(d, heads, dropout=dropout, batch_first=True)
        self.ffn = _FeedForward(d, ff, dropout)
        self.norm1 = nn.LayerNorm(d)
        self.norm2 = nn.LayerNorm(d)
        self.norm3 = nn.LayerNorm(d)
        self.dropout1 = nn.Dropout(dropout)
        self.dropout2 = nn.Dropout(dropout)
        self.dropout3 = nn.Dropout(dropout)

    def forward(self, tgt: torch.Tensor, memory: torch.Tensor, query_pos: torch.Tensor,
                tgt_mask: torch.Tensor | None = None, memory_mask: torch.Tensor | None = None) -> torch.Tensor:
        """Args:
            tgt: ``(B, Q, D)`` query states.
            memory: ``(B, T, D)`` encoder output.
            query_pos: ``(B, Q, D)`` or ``(Q, D)`` query positional embedding.
            tgt_mask: ``(Q, Q)`` bool, ``True`` = query i may not attend query j.
            memory_mask: ``(Q, T)`` bool, ``True`` = query i may not attend token j.

        Returns:
            ``(B, Q, D)``.
        """
        q = tgt + query_pos
        attn = self.self_attn(q, q, tgt, attn_mask=tgt_mask, need_weights=False)[0]
        tgt = self.norm1(tgt + self.dropout1(attn))
        attn = self.cross_attn(tgt + query_pos, memory, memory, attn_mask=memory_mask, need_weights=False)[0]
        tgt = self.norm2(tgt + self.dropout2(attn))
        return self.norm3(tgt + self.dropout3(self.ffn(tgt)))


class QueryDecoder(nn.Module):
    """Decoder with learned query positions (``nn.Embedding(n_queries, d)``) and zero initial queries.

    ``forward(memory (B, T, D), tgt_mask (Q, Q) | None, memory_mask (Q, T) | None) -> (L, B, Q, D)``: the
    output of every layer through one shared LayerNorm. Masks may live on any device; they are moved to the
    memory's device.
    """

    def __init__(self, n_layers: int = 4, n_queries: int = 17, d: int = 256, heads: int = 4, ff: int = 1024,
                 dropout: float = 0.1) -> None:
        super().__init__()
        self.query_embed = nn.Embedding(n_queries, d)
        self.layers = nn.ModuleList(DecoderLayer(d, heads, ff, dropout) for _ in range(n_layers))
        self.norm = nn.LayerNorm(d)

    def forward(self, memory: torch.Tensor, tgt_mask: torch.Tensor | None = None,
                memory_mask: torch.Tensor | None = None) -> torch.Tensor:
        if tgt_mask is not None:
            tgt_mask = tgt_mask.to(memory.device)
        if memory_mask is not None:
            memory_mask = memory_mask.to(memory.device)
        query_pos = self.query_embed.weight.to(memory.dtype).unsqueeze(0).expand(memory.shape[0], -1, -1)
        tgt = torch.zeros_like(query_pos)
        outputs = []
        for layer in self.layers:
            tgt = layer(tgt, memory, query_pos, tgt_mask=tgt_mask, memory_mask=memory_mask)
            outputs.append(self.norm(tgt))
        return torch.stack(outputs)


def group_attention_mask(groups: tuple[tuple[int, ...], ...], device: torch.device | str | None = None) -> torch.Tensor:
    """``(Q, Q)`` bool mask (``True`` = blocked) letting each query attend only the queries of its own group."""
    n = sum(len(g) for g in groups)
    group_id = torch.empty(n, dtype=torch.long, device="cpu")  # filled from Python here, then moved
    for gi, members in enumerate(groups):
        group_id[list(members)] = gi
    group_id = group_id.to(device)
    return group_id[:, None] != group_id[None, :]


def mano_query_mask(device: torch.device | str | None = None) -> torch.Tensor:
    """``(17, 17)`` bool decoder self-attention mask of :data:`MANO_QUERY_GROUPS` (``True`` = blocked)."""
    return group_attention_mask(MANO_QUERY_GROUPS, device)


def memory_mask(n_queries: int, n_tokens: int, n_visible: int,
                device: torch.device | str | None = None) -> torch.Tensor:
    """``(Q, T)`` bool cross-attention mask blocking tokens ``n_visible .. T-1`` for every query."""
    if not 1 <= n_visible <= n_tokens:
        raise ValueError(f"n_visible must be in [1, {n_tokens}], got {n_visible}")
    mask = torch.zeros(n_queries, n_tokens, dtype=torch.bool, device=device)
    mask[:, n_visible:] = True
    return mask


def init_transformer_weights(module: nn.Module) -> None:
    """Upstream initialisation (docs/upstream.md, "Transformers" and "Initialisation") of a transformer module, in
    place.

    1. xavier-uniform on every parameter with more than one dimension (attention in-projections, FFN and
       out-projection weights), except ``nn.Embedding`` tables (the learned query positions keep N(0, 1));
    2. then every module whose type is exactly ``nn.Linear`` (the FFN layers; not the attention
       ``out_proj``, which is a ``Linear`` subclass) gets N(0, 0.01) weights and zero bias.
    """
    with torch.no_grad():
        for sub in module.modules():
            if isinstance(sub, nn.Embedding):
                continue
            for p in sub.parameters(recurse=False):
                if p.dim() > 1:
                    nn.init.xavier_uniform_(p)
        for sub in module.modules():
            if type(sub) is nn.Linear:
                sub.weight.normal_(0.0, 0.01)
                if sub.bias is not None:
                    sub.bias.zero_()
