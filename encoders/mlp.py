"""Flat-MLP baseline: the K neighbour slots concatenated in order of distance.

The neighbours are re-sorted nearest first inside the encoder (padded slots last), so the result does
not depend on the order of the slots, only on the set of neighbours. Its weights depend on K, so,
unlike the set encoders, one set of weights serves one K only.
"""
from __future__ import annotations

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .common import flat_inputs, mlp, read_obs, self_input_dim, xavier_init_


class MLPEncoder(nn.Module):
    """Self MLP and an MLP over the distance-sorted neighbour slots (each with its mask bit), joined.

    Args:
        layout: observation layout.
        hidden: width of the self and neighbour MLPs (two layers each).
        out_dim: width of the joining layer.
        activation: nonlinearity.
    """

    equivariance = None

    def __init__(self, layout: ObsLayout, hidden: int = 256, out_dim: int = 512, activation: str = "tanh"):
        super().__init__()
        self.layout = layout
        self.out_dim = out_dim
        k = layout.num_neighbors
        self.self_mlp = mlp([self_input_dim(layout), hidden, hidden], activation)
        self.neighbor_mlp = mlp([k * (layout.neighbor_dim + 1), hidden, hidden], activation) if k else None
        self.join = mlp([(2 if k else 1) * hidden, out_dim], activation)
        xavier_init_(self)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        fields = read_obs(self.layout, obs)
        self_x, nb, mask = flat_inputs(self.layout, fields)  # [B, S], [B, K, F], [B, K]
        parts = [self.self_mlp(self_x)]
        if self.neighbor_mlp is not None:
            dist = fields["neighbor.rel_pos"].norm(dim=-1).masked_fill(~mask, float("inf"))  # [B, K]
            order = torch.argsort(dist, dim=1, stable=True)  # nearest first, padding last
            nb = torch.gather(nb, 1, order.unsqueeze(-1).expand_as(nb))
            bits = torch.gather(mask, 1, order).to(nb.dtype).unsqueeze(-1)  # [B, K, 1]
            parts.append(self.neighbor_mlp(torch.cat([nb, bits], dim=-1).flatten(1)))
        return self.join(torch.cat(parts, dim=-1))  # [B, out_dim]
