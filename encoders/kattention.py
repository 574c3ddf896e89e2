"""K-Attention (QuadSwarm / Batra et al. CoRL 2021); ``se3_kattention`` is this encoder canonicalized
(``encoders.symmetric.Canonicalized`` with ``symmetry="se3"``, paper Lemma 1).

Per neighbour j of drone i: embedding e_j = MLP([s_i, o_j]), value h_j = MLP(e_j), score
a_j = MLP([e_j, mean_k e_k]); softmax of the scores over the real neighbours weights the values.
A self MLP (256-256 tanh) and the attended neighbourhood are joined by a 512-wide tanh layer.

The self state is broadcast to each neighbour *of the same sample* ([B, K, S]); the reference
implementation tiles the whole batch instead (``repeat``), pairing sample b's neighbours with other
samples' states, which is a bug we do not reproduce.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from quad_env.obs_layout import ObsLayout

from .common import flat_inputs, masked_mean, masked_softmax, mlp, read_obs, self_input_dim, xavier_init_


def _linear_of_concat(layer: nn.Linear, parts) -> torch.Tensor:
    """``layer(cat(parts, -1))`` [B, K, out] for parts in concatenation order, each per item [B, K, n] or per
    sample [B, n] (broadcast over the K items), without forming the concatenation: each part meets its own
    columns of the weight, so a per-sample part costs B rows, not B x K (the bias rides on the first of them)."""
    out, start, bias = None, 0, layer.bias
    for part in parts:
        w = layer.weight[:, start:start + part.shape[-1]]
        start += part.shape[-1]
        if part.dim() == 2:
            y, bias = F.linear(part, w, bias).unsqueeze(1), None
        else:
            y = F.linear(part, w)
        out = y if out is None else out + y
    if start != layer.in_features:
        raise ValueError(f"parts give {start} input features, the layer takes {layer.in_features}")
    return out if bias is None else out + bias


class KAttention(nn.Module):
    """The unconstrained K-Attention network on ``(self_x [B, S], neighbors [B, K, F], mask [B, K])``."""

    def __init__(self, self_dim: int, neighbor_dim: int, hidden: int, out_dim: int, activation: str):
        super().__init__()
        self.self_mlp = mlp([self_dim, hidden, hidden], activation)
        self.embed = mlp([self_dim + neighbor_dim, hidden, hidden], activation)
        self.value = mlp([hidden, hidden, hidden], activation)
        self.score = mlp([2 * hidden, hidden, hidden, 1], activation, last_act=False)
        self.join = mlp([2 * hidden, out_dim], activation)

    def forward(self, self_x: torch.Tensor, nb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        # embed(cat[s_i, o_j]) and score(cat[e_j, mean_k e_k]) have a per-sample half in their first layer: it is
        # applied once per sample and broadcast over the K neighbours, not tiled K times (the same function and
        # parameters; 12 % fewer multiply-adds at paper size and no [B, K, 2H] concatenation)
        e = self.embed[1:](_linear_of_concat(self.embed[0], [self_x, nb]))  # [B, K, H]
        e_mean = masked_mean(e, mask, dim=1)  # [B, H]
        scores = self.score[1:](_linear_of_concat(self.score[0], [e, e_mean])).squeeze(-1)  # [B, K]
        weights = masked_softmax(scores, mask)  # [B, K]; all zero without neighbours
        neighborhood = (weights.unsqueeze(-1) * self.value(e)).sum(dim=1)  # [B, H]
        return self.join(torch.cat([self.self_mlp(self_x), neighborhood], dim=-1))  # [B, out_dim]


class KAttentionEncoder(nn.Module):
    """K-Attention baseline on world-frame observations.

    Args:
        layout: observation layout.
        hidden: width of the self, embedding, value and score MLPs.
        out_dim: width of the joining layer.
        activation: nonlinearity.
    """

    equivariance = None

    def __init__(self, layout: ObsLayout, hidden: int = 256, out_dim: int = 512, activation: str = "tanh"):
        super().__init__()
        self.layout = layout
        self.out_dim = out_dim
        self.net = KAttention(self_input_dim(layout), layout.neighbor_dim, hidden, out_dim, activation)
        xavier_init_(self)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(*flat_inputs(self.layout, read_obs(self.layout, obs)))

