"""Hand regressors (``model.pose_regressor``): how the hand transformer's output becomes the hand.

Each variant is a module that owns the heads it needs (their names are the state-dict keys under
``pose.regressor.``) and turns the encoder output into hand outputs (``forward``). Shapes: ``inter`` (L, B, T, D)
per-layer encoder tokens, ``memory`` (B, T, D) the last layer, ``hand_metric`` (B, Nh, 3) query points in metres
relative to the hand root, ``nh`` = Nh (the first Nh tokens are the hand's own points), ``mano`` the MANO layer
(not a registered module: it belongs to the user, not to checkpoints). Outputs: see
:data:`hoisdf.model.hoisdf.OUTPUTS`.
"""

from __future__ import annotations

import torch
from torch import nn

from hoisdf.model import heads as H
from hoisdf.model.ik import solve_ik
from hoisdf.model.transformer import QueryDecoder, mano_query_mask, memory_mask

MANO_QUERIES = 17  # 16 joint rotations + 1 shape query


def votes(vote_head: H.VoteHead, inter, hand_metric, nh) -> dict[str, torch.Tensor]:
    """The voting head's outputs over the hand's own tokens."""
    out = vote_head(inter[:, :, :nh], hand_metric)
    return {"vote_offsets": out["offsets"], "vote_logits": out["logits"], "vote_joints": out["joints"]}


def decoded_queries(decoder: QueryDecoder, memory, nh) -> torch.Tensor:
    """Decoder outputs (L, B, Q, D) of the query decoder over the encoder memory."""
    n_queries = decoder.query_embed.num_embeddings
    mask = mano_query_mask(memory.device) if n_queries == MANO_QUERIES else None
    return decoder(memory, mask, memory_mask(n_queries, memory.shape[1], nh, memory.device))


class ManoOnlyRegressor(nn.Module):
    """``"mano_only"``: MANO from 17 decoder queries, no voting head."""

    def __init__(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float):
        super().__init__()
        self.hand_decoder = QueryDecoder(layers, MANO_QUERIES, d_model, n_heads, ff, dropout)
        self.mano_head = H.ManoHead(d_model)

    def transformers(self) -> list[nn.Module]:
        """The transformer modules (their weights get :func:`hoisdf.model.transformer.init_transformer_weights`)."""
        return [self.hand_decoder]

    def predict_raw_6d(self) -> None:
        """The MANO head predicts the raw 6D code (``model.rot6d = "raw"``, :meth:`hoisdf.model.heads.ManoHead`)."""
        self.mano_head.predict_raw_6d()

    def mano(self, memory, nh, mano) -> dict[str, torch.Tensor]:
        out = self.mano_head(decoded_queries(self.hand_decoder, memory, nh), mano)
        return {"rotations": out["rotations"], "betas": out["betas"], "mano_verts": out["verts"],
                "mano_joints": out["joints"], "joints": out["joints"][-1], "verts": out["verts"][-1]}

    def forward(self, inter, memory, hand_metric, nh, mano) -> dict[str, torch.Tensor]:
        return self.mano(memory, nh, mano)


class ManoRegressor(ManoOnlyRegressor):
    """``"mano"`` (HOISDF): MANO from 17 decoder queries, plus the voting head's auxiliary outputs."""

    def __init__(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float):
        super().__init__(d_model, layers, n_heads, ff, dropout)
        self.vote_head = H.VoteHead(d_model)

    def forward(self, inter, memory, hand_metric, nh, mano) -> dict[str, torch.Tensor]:
        return {**votes(self.vote_head, inter, hand_metric, nh), **self.mano(memory, nh, mano)}


class VotingRegressor(nn.Module):
    """``"voting"``: the hand is the voted joints (no mesh)."""

    def __init__(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float):
        super().__init__()
        self.vote_head = H.VoteHead(d_model)

    def transformers(self) -> list[nn.Module]:
        return []

    def predict_raw_6d(self) -> None:
        """No MANO head: nothing to switch."""

    def forward(self, inter, memory, hand_metric, nh, mano) -> dict[str, torch.Tensor]:
        out = votes(self.vote_head, inter, hand_metric, nh)
        out["joints"] = H.with_root(out["vote_joints"][-1])
        return out


class IKRegressor(nn.Module):
    """``"ik"``: voted joints + betas from one shape query; the reported hand is the MANO fit (inverse
    kinematics) of the voted joints, as the reference."""

    def __init__(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float):
        super().__init__()
        self.hand_decoder = QueryDecoder(layers, 1, d_model, n_heads, ff, dropout)
        self.shape_head = H.ShapeHead(d_model)
        self.vote_head = H.VoteHead(d_model)

    def transformers(self) -> list[nn.Module]:
        return [self.hand_decoder]

    def predict_raw_6d(self) -> None:
        """No MANO head: nothing to switch."""

    def forward(self, inter, memory, hand_metric, nh, mano) -> dict[str, torch.Tensor]:
        out = votes(self.vote_head, inter, hand_metric, nh)
        betas = self.shape_head(decoded_queries(self.hand_decoder, memory, nh))["betas"]
        out["betas"] = betas
        voted = H.with_root(out["vote_joints"][-1])
        with torch.no_grad():
            pose = solve_ik(voted.detach().float(), betas[-1].detach().float(), mano)
            verts, joints = H.wrist_centred_mano(mano, pose, betas[-1].detach().float())
        out.update({"joints": joints, "verts": verts, "ik_pose": pose})
        return out


REGRESSORS = {"mano": ManoRegressor, "mano_only": ManoOnlyRegressor, "voting": VotingRegressor, "ik": IKRegressor}
"""``model.pose_regressor`` value -> regressor class (built with d_model, decoder layers, heads, ff, dropout)."""
