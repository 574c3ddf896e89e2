"""InfoMARL encoder against a literal per-node, per-edge float64 reference of its module docstring."""
from __future__ import annotations

import math

import numpy as np
import torch

from encoders import make_encoder
from encoders.testing import random_obs
from quad_env.obs_layout import ObsLayout


def reference(enc, obs_row: torch.Tensor) -> torch.Tensor:
    """One observation, node by node and edge by edge, with the encoder's weights."""
    f = enc.layout.split(obs_row[None])
    real = [k for k in range(enc.layout.num_neighbors) if f["mask"][0, k] > 0.5]
    goal = -f["self.rel_goal"][0]
    zero = torch.zeros(3, dtype=obs_row.dtype)
    nb_goal = (lambda k: f["neighbor.goal_offset"][0, k]) if "neighbor.goal_offset" in f else (lambda k: zero)
    # nodes: (position, velocity, goal offset, type) for self, the real neighbours, the goal
    nodes = [(zero, zero, goal, 0)]
    nodes += [(f["neighbor.rel_pos"][0, k], f["neighbor.rel_vel"][0, k], nb_goal(k), 1) for k in real]
    nodes += [(goal, -f["self.vel"][0], zero, 2)]
    n = len(nodes)
    dist = [[torch.linalg.norm(nodes[p][0] - nodes[v][0]) for p in range(n)] for v in range(n)]
    emb = enc.type_embedding.weight
    h = []
    for v in range(n):  # entity embedding: sum over every node p (the graph is complete) of MLP(x_p, type_p, d_vp)
        msgs = [enc.embed(torch.cat([nodes[p][0], nodes[p][1], nodes[p][2], emb[nodes[p][3]], dist[v][p][None]]))
                for p in range(n)]
        h.append(torch.stack(msgs).sum(0))
    for layer in enc.layers:
        W, H = layer.width, layer.heads
        new = []
        for v in range(n):
            q = layer.q(h[v]).view(H, W)
            heads = []
            for hd in range(H):
                logits, values = [], []
                for p in range(n):
                    e = layer.edge(dist[v][p][None]).view(H, W)[hd]
                    logits.append(torch.dot(q[hd], layer.k(h[p]).view(H, W)[hd] + e) / math.sqrt(W))
                    values.append(layer.u(h[p]).view(H, W)[hd] + e)
                a = torch.softmax(torch.stack(logits), 0)
                heads.append(sum(a[p] * values[p] for p in range(n)))
            new.append(layer.act(layer.root(h[v]) + torch.stack(heads).mean(0)))
        h = new
    own = torch.cat([f[k][0] for k in ("self.rel_goal", "self.vel", "self.rot", "self.omega")]
                    + ([f["obstacle.obstacle_sdf"][0]] if "obstacle.obstacle_sdf" in f else []))
    return enc.readout(torch.cat([h[0], own]))


def test_dense_encoder_matches_the_per_edge_reference():
    for layout in (ObsLayout(4), ObsLayout(3, "pos_vel", obstacle_obs=True)):
        torch.manual_seed(0)
        enc = make_encoder("infomarl", layout, hidden=8, embedding_size=3, num_heads=2, num_layers=2,
                           out_dim=12).double()
        obs = torch.as_tensor(random_obs(layout, 6, np.random.default_rng(1)))
        with torch.no_grad():
            dense = enc(obs)
            ref = torch.stack([reference(enc, obs[b]) for b in range(obs.shape[0])])
        torch.testing.assert_close(dense, ref, rtol=1e-10, atol=1e-10)
