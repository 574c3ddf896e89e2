"""K-DeepSets baseline: self MLP, per-neighbour MLP, masked mean over the K slots, joined by one tanh layer."""
from __future__ import annotations

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .common import flat_inputs, masked_mean, mlp, read_obs, self_input_dim, xavier_init_


class DeepSetsEncoder(nn.Module):
    """QuadSwarm's DeepSets neighbour encoder (sizes as in its default config).

    Args:
        layout: observation layout.
        hidden: width of the self and neighbour MLPs (two layers each).
        out_dim: width of the joining layer.
        activation: nonlinearity.
    """

    equivariance = None  # world-frame inputs go straight into an MLP

    def __init__(self, layout: ObsLayout, hidden: int = 256, out_dim: int = 512, activation: str = "tanh"):
        super().__init__()
        self.layout = layout
        self.out_dim = out_dim
        self.self_mlp = mlp([self_input_dim(layout), hidden, hidden], activation)
        self.neighbor_mlp = mlp([layout.neighbor_dim, hidden, hidden], activation)
        self.join = mlp([2 * hidden, out_dim], activation)
        xavier_init_(self)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        self_x, nb, mask = flat_inputs(self.layout, read_obs(self.layout, obs))  # [B, S], [B, K, F], [B, K]
        neighborhood = masked_mean(self.neighbor_mlp(nb), mask, dim=1)  # [B, H]; zeros without neighbours
        return self.join(torch.cat([self.self_mlp(self_x), neighborhood], dim=-1))  # [B, out_dim]
