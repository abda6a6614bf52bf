"""Hand regressors (``model.pose_regressor``): how the hand transformer's output becomes the hand.

Each variant names the heads it needs (:meth:`heads`, built by :func:`hoisdf.model.build_model` and registered on
the model under those names, which are the state-dict prefixes) and turns the encoder output into hand outputs
(``__call__``). Shapes: ``inter`` (L, B, T, D) per-layer encoder tokens, ``memory`` (B, T, D) the last layer,
``hand_metric`` (B, Nh, 3) query points in metres relative to the hand root, ``nh`` = Nh (the first Nh tokens
are the hand's own points). Outputs: see :data:`hoisdf.model.hoisdf.OUTPUTS`.
"""

from __future__ import annotations

import torch
from torch import nn

from hoisdf.model import heads as H
from hoisdf.model.ik import solve_ik
from hoisdf.model.transformer import QueryDecoder, mano_query_mask, memory_mask

MANO_QUERIES = 17  # 16 joint rotations + 1 shape query


def _votes(model, inter, hand_metric, nh) -> dict[str, torch.Tensor]:
    votes = model.vote_head(inter[:, :, :nh], hand_metric)
    return {"vote_offsets": votes["offsets"], "vote_logits": votes["logits"], "vote_joints": votes["joints"]}


def _queries(model, memory, nh) -> torch.Tensor:
    """Decoder outputs (L, B, Q, D) of the model's ``hand_decoder`` over the encoder memory."""
    n_queries = model.hand_decoder.query_embed.num_embeddings
    mask = mano_query_mask(memory.device) if n_queries == MANO_QUERIES else None
    return model.hand_decoder(memory, mask, memory_mask(n_queries, memory.shape[1], nh, memory.device))


def _mano(model, memory, nh) -> dict[str, torch.Tensor]:
    mano_out = model.mano_head(_queries(model, memory, nh), model.mano)
    return {"rotations": mano_out["rotations"], "betas": mano_out["betas"], "mano_verts": mano_out["verts"],
            "mano_joints": mano_out["joints"], "joints": mano_out["joints"][-1], "verts": mano_out["verts"][-1]}


class ManoRegressor:
    """``"mano"`` (HOISDF): MANO from 17 decoder queries, plus the voting head's auxiliary outputs."""

    def heads(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float) -> dict[str, nn.Module]:
        return {"hand_decoder": QueryDecoder(layers, MANO_QUERIES, d_model, n_heads, ff, dropout),
                "mano_head": H.ManoHead(d_model), "vote_head": H.VoteHead(d_model)}

    def __call__(self, model, inter, memory, hand_metric, nh) -> dict[str, torch.Tensor]:
        return {**_votes(model, inter, hand_metric, nh), **_mano(model, memory, nh)}


class ManoOnlyRegressor:
    """``"mano_only"``: MANO from the decoder queries, no voting head."""

    def heads(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float) -> dict[str, nn.Module]:
        return {"hand_decoder": QueryDecoder(layers, MANO_QUERIES, d_model, n_heads, ff, dropout),
                "mano_head": H.ManoHead(d_model)}

    def __call__(self, model, inter, memory, hand_metric, nh) -> dict[str, torch.Tensor]:
        return _mano(model, memory, nh)


class VotingRegressor:
    """``"voting"``: the hand is the voted joints (no mesh)."""

    def heads(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float) -> dict[str, nn.Module]:
        return {"vote_head": H.VoteHead(d_model)}

    def __call__(self, model, inter, memory, hand_metric, nh) -> dict[str, torch.Tensor]:
        out = _votes(model, inter, hand_metric, nh)
        out["joints"] = H.with_root(out["vote_joints"][-1])
        return out


class IKRegressor:
    """``"ik"``: voted joints + betas from one shape query; the reported hand is the MANO fit (inverse
    kinematics) of the voted joints, as the reference."""

    def heads(self, d_model: int, layers: int, n_heads: int, ff: int, dropout: float) -> dict[str, nn.Module]:
        return {"hand_decoder": QueryDecoder(layers, 1, d_model, n_heads, ff, dropout),
                "shape_head": H.ShapeHead(d_model), "vote_head": H.VoteHead(d_model)}

    def __call__(self, model, inter, memory, hand_metric, nh) -> dict[str, torch.Tensor]:
        out = _votes(model, inter, hand_metric, nh)
        betas = model.shape_head(_queries(model, memory, nh))["betas"]
        out["betas"] = betas
        voted = H.with_root(out["vote_joints"][-1])
        with torch.no_grad():
            pose = solve_ik(voted.detach().float(), betas[-1].detach().float(), model.mano)
            verts, joints = H.wrist_centred_mano(model.mano, pose, betas[-1].detach().float())
        out.update({"joints": joints, "verts": verts, "ik_pose": pose})
        return out


REGRESSORS = {"mano": ManoRegressor, "mano_only": ManoOnlyRegressor, "voting": VotingRegressor, "ik": IKRegressor}
"""``model.pose_regressor`` value -> regressor class."""
