"""InfoMARL baseline (Nayak et al., ICML 2023): a graph network over drone i's sensed neighbourhood.

Drone i's local graph has N = K + 2 nodes: drone i itself, its K neighbour slots (padded slots are left
out) and its goal. Each node p carries, relative to drone i and in world axes, its position x_p, velocity
v_p and goal offset g_p (its own goal minus its position; zero for the goal node), plus a learned
embedding of its entity type (self, neighbour, goal). Edges join every pair of real nodes, with the
distance |x_p - x_v| as edge feature (the graph is complete: every observed neighbour is already within
the sensing range).

1. Entity embedding (message passing with sum aggregation): h_v = sum_p MLP([x_p, v_p, g_p, type_p, d_vp]).
2. ``num_layers`` graph-transformer layers (attention with edge features, averaged over heads, root skip):
   k_vp = W_k h_p + W_e d_vp, u_vp = W_u h_p + W_e d_vp, a_vp = softmax_p(q_v . k_vp / sqrt(d)),
   h_v <- act(W_r h_v + sum_p a_vp u_vp).
3. Readout: drone i's node embedding h_i joined with drone i's own observation (and the obstacle field) by
   an MLP: the aggregated information of the neighbourhood, as InfoMARL's actor uses it.

The widths are this project's (the paper does not give InfoMARL's); the obstacle field enters the readout,
not the graph, because this simulator reports obstacles as a distance field rather than as entities.
Like every world-frame encoder it becomes SE(3)- or yaw-equivariant with ``model.symmetry``.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .common import activation, mlp, read_obs, self_keys, xavier_init_

ENTITY_TYPES = ("self", "neighbour", "goal")
NODE_FEATURES = 9  # position, velocity, goal offset: 3 each, relative to drone i, world axes


class GraphTransformerLayer(nn.Module):
    """Attention over a node's graph neighbours with a scalar edge feature, heads averaged, root skip."""

    def __init__(self, width: int, num_heads: int, act: str):
        super().__init__()
        self.heads, self.width = num_heads, width
        self.q = nn.Linear(width, width * num_heads)
        self.k = nn.Linear(width, width * num_heads)
        self.u = nn.Linear(width, width * num_heads)
        self.edge = nn.Linear(1, width * num_heads, bias=False)
        self.root = nn.Linear(width, width)
        self.act = activation(act)

    def forward(self, h: torch.Tensor, dist: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
        B, N, W = h.shape
        H = self.heads
        q = self.q(h).view(B, N, 1, H, W)  # [B, N(v), 1, H, W]
        e = self.edge(dist.unsqueeze(-1)).view(B, N, N, H, W)  # [B, N(v), N(p), H, W]
        k = self.k(h).view(B, 1, N, H, W) + e
        u = self.u(h).view(B, 1, N, H, W) + e
        logits = (q * k).sum(-1) / math.sqrt(W)  # [B, N, N, H]
        logits = logits.masked_fill(~edges.unsqueeze(-1), torch.finfo(logits.dtype).min)
        alpha = torch.softmax(logits, dim=2)  # over p; every row has its self-loop
        agg = (alpha.unsqueeze(-1) * u).sum(2).mean(2)  # [B, N, W]: sum over p, mean over heads
        return self.act(self.root(h) + agg)


class InfoMARLEncoder(nn.Module):
    """Graph network over drone i's neighbourhood (see the module docstring).

    Args:
        layout: observation layout.
        hidden: width of the node embeddings and of every graph layer.
        embedding_size: size of the learned entity-type embedding.
        num_layers: graph-transformer layers after the entity embedding.
        num_heads: attention heads (averaged).
        out_dim: width of the readout MLP's output.
        activation: nonlinearity.
    """

    equivariance = None  # world-frame inputs; model.symmetry canonicalizes them (encoders.symmetric)

    def __init__(self, layout: ObsLayout, hidden: int = 128, embedding_size: int = 8, num_layers: int = 2,
                 num_heads: int = 3, out_dim: int = 256, activation: str = "relu"):
        super().__init__()
        if min(hidden, embedding_size, num_heads, out_dim) < 1 or num_layers < 0:
            raise ValueError(f"InfoMARL sizes must be >= 1 (num_layers >= 0), got hidden={hidden}, "
                             f"embedding_size={embedding_size}, num_heads={num_heads}, out_dim={out_dim}, "
                             f"num_layers={num_layers}")
        self.layout = layout
        self.out_dim = out_dim
        self.type_embedding = nn.Embedding(len(ENTITY_TYPES), embedding_size)
        self.embed = mlp([NODE_FEATURES + embedding_size + 1, hidden, hidden], activation)
        self.layers = nn.ModuleList(GraphTransformerLayer(hidden, num_heads, activation) for _ in range(num_layers))
        own = sum(f.size for f in layout.fields if f.group in ("self", "obstacle"))
        self.readout = mlp([hidden + own, out_dim, out_dim], activation)
        xavier_init_(self)
        types = torch.tensor([0] + [1] * layout.num_neighbors + [2])
        self.register_buffer("node_types", types, persistent=False)  # [N]

    def graph(self, obs: torch.Tensor):
        """Node features [B, N, 9], node mask [B, N], pairwise distances [B, N, N] and the read fields."""
        f = read_obs(self.layout, obs)
        B, K = f["mask"].shape
        zeros = obs.new_zeros(B, 1, 3)
        goal = -f["self.rel_goal"].unsqueeze(1)  # x_i^d - x_i
        nb_goal = f["neighbor.goal_offset"] if "neighbor.goal_offset" in f else obs.new_zeros(B, K, 3)
        pos = torch.cat([zeros, f["neighbor.rel_pos"], goal], dim=1)  # [B, N, 3]
        vel = torch.cat([zeros, f["neighbor.rel_vel"], -f["self.vel"].unsqueeze(1)], dim=1)  # relative to v_i
        goal_offset = torch.cat([goal, nb_goal, zeros], dim=1)
        nodes = torch.cat([pos, vel, goal_offset], dim=-1)  # [B, N, 9]
        ones = f["mask"].new_ones(B, 1)
        node_mask = torch.cat([ones, f["mask"], ones], dim=1)  # [B, N]
        sq = (pos.unsqueeze(2) - pos.unsqueeze(1)).pow(2).sum(-1)  # [B, N, N]
        # exact 0 on coinciding nodes, and a finite gradient there (sqrt's is infinite at 0)
        dist = torch.where(sq > 0, sq.clamp(min=torch.finfo(sq.dtype).tiny).sqrt(), torch.zeros_like(sq))
        return nodes, node_mask, dist, f

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        nodes, node_mask, dist, f = self.graph(obs)
        B, N, _ = nodes.shape
        eye = torch.eye(N, dtype=torch.bool, device=obs.device)
        edges = (node_mask.unsqueeze(2) & node_mask.unsqueeze(1)) | eye  # [B, N(v), N(p)]
        types = self.type_embedding(self.node_types).expand(B, N, -1)  # [B, N, E]
        sender = torch.cat([nodes, types], dim=-1)  # [B, N(p), 9 + E]
        messages = self.embed(torch.cat([sender.unsqueeze(1).expand(B, N, N, -1), dist.unsqueeze(-1)], dim=-1))
        h = (messages * edges.unsqueeze(-1).to(messages.dtype)).sum(2)  # [B, N, hidden]: sum over p
        for layer in self.layers:
            h = layer(h, dist, edges)
        own = torch.cat([f[k] for k in self_keys(self.layout)], dim=-1)  # [B, S]
        return self.readout(torch.cat([h[:, 0], own], dim=-1))  # [B, out_dim]
