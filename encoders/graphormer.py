"""The paper's Group Equivariant Graphormer (sections 5-6), built by canonicalization, for any symmetry.

Graph: drone i and its real neighbours are the nodes (masked slots are left out); node v carries a frame
g_v = (F_v, x_v) -- x_v its position relative to drone i, F_v the rotation of its frame: its attitude R_v
for ``symmetry="se3"`` (the paper's ``se3_graphormer``), its heading frame (yaw about gravity) for ``"yaw"``,
the world axes for ``"none"`` (the non-equivariant baseline of the same architecture) -- and features f_v of
types 0 and 1 (``m`` scalars and ``m`` 3-vectors, each node's own in its own frame). Edges join every pair of
nodes (self-loops included) closer than ``edge_radius``; with the default ``None`` the graph is complete,
as every observed neighbour already lies within drone i's sensing range.

Layer l updates node v by the paper's rule  f_v <- phi_{g_v}[ mu( f_v' + attn_v(phi_{g_v^-1}[F]) ) ]:
every node p is seen in v's frame as the pair input

    x_vp = [ |x_p - x_v|,  s_p,  F_v^T (x_p - x_v),  F_v^T R_p,  F_v^T F_p V_p ]      (= phi_{g_v^-1}[(g_p, f_p)])

attn_v = sum_p softmax_p(q_v . W_K x_vp / sqrt(d)) W_V x_vp with q_v = W_Q f_v', mu = LayerNorm and a
residual feed-forward block with LayerNorm, and the result stays in v's frame.

Nothing of size N x N x features is built: because x_vp is linear in the world-frame node data,
  q_v . W_K x_vp = (F_v-rotated W_K^T q_v) . z_p + const_v   and   sum_p a_vp x_vp = canon_v(sum_p a_vp z_p),
so keys and values cost one matmul per *node*, and the pair work is two small batched matmuls
([B, N, Z] x [B, Z, N]). The test suite checks this against the literal per-pair formula.

Readout (section 6): zeta(canonical own state (+) mean_j F_i^T f_j^L), typed as scalars + 3-vectors and
mapped back by F_i.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .common import activation, mlp, read_obs, self_input_dim, self_keys, xavier_init_
from .frames import SYMMETRIES, canonicalize, frame_of, full_precision, own_rotation, typed_output, typed_to_world

NODE_INPUTS = 10  # per node, in its own frame: velocity (3), goal offset (3), body rates (3), is-self flag (1)
POSE_CHANNELS = 4  # vector channels of a node's pose: its position and the 3 columns of its attitude


def low_precision(t: torch.Tensor) -> torch.Tensor:
    """``t`` cast to the autocast dtype inside an autocast region (once, for several matmuls), else ``t``."""
    if t.is_floating_point() and torch.is_autocast_enabled(t.device.type):
        return t.to(torch.get_autocast_dtype(t.device.type))
    return t


def rotate_features(R: torch.Tensor, V: torch.Tensor) -> torch.Tensor:
    """R @ V for rotations R [B, N, 3, 3] and spatial-major vector blocks V [B, N, (H,) 3, C], in the dtype
    autocast gives (bf16 under bf16): used on the layers' features, which the layers' matmuls round to bf16
    anyway. Observations and the readout go through ``rotate``, which stays fp32."""
    if V.dim() == 5:
        return torch.einsum("bnij,bnhjc->bnhic", R, V)
    return torch.einsum("bnij,bnjc->bnic", R, V)


@full_precision
def rotate(R: torch.Tensor, V: torch.Tensor) -> torch.Tensor:
    """``rotate_features`` in fp32 even under autocast (``encoders.frames.full_precision``)."""
    return rotate_features(R, V)


class Graph:
    """Drone i's local graph: node frames and edges, all [B, N, ...] with N = K + 1 (node 0 is drone i)."""

    def __init__(self, R: torch.Tensor, x: torch.Tensor, node_mask: torch.Tensor, edge_radius: Optional[float],
                 F: Optional[torch.Tensor] = None):
        self.R = R  # [B, N, 3, 3] body -> world attitude of each node
        self.F = R if F is None else F  # [B, N, 3, 3] rotation of each node's frame (se3: its attitude)
        self.Ft = self.F.transpose(-1, -2)
        self.x = x  # [B, N, 3] position relative to drone i
        self.node_mask = node_mask  # [B, N] bool
        self.dist = torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist")  # [B, N, N]
        N = x.shape[1]
        edges = node_mask.unsqueeze(2) & node_mask.unsqueeze(1)
        if edge_radius is not None:
            edges = edges & (self.dist <= edge_radius)
        self.edges = edges | torch.eye(N, dtype=torch.bool, device=x.device)  # self-loops: no empty rows
        # world-frame pose block of each node: vector channels [x_v, R_v[:, 0], R_v[:, 1], R_v[:, 2]]
        self.pose = torch.cat([x.unsqueeze(-1), R], dim=-1)  # [B, N, 3, 4]


class EquivariantGraphormerLayer(nn.Module):
    """One update f_v <- phi_{g_v}[mu(f_v' + attn_v(phi_{g_v^-1}[F]))]; features in and out are canonical
    (node v's own features in v's frame, ``[m scalars | 3 x m vector block, spatial-major]``)."""

    def __init__(self, multiplicity: int, num_heads: int, ffn_dim: int, act: str):
        super().__init__()
        m = multiplicity
        self.m, self.heads = m, num_heads
        self.width = 4 * m  # m scalars + m 3-vectors
        if self.width % num_heads:
            raise ValueError(f"num_heads={num_heads} must divide the feature size 4 * multiplicity = {self.width}")
        self.head_dim = self.width // num_heads
        self.pair_dim = 1 + m + 3 * (POSE_CHANNELS + m)  # [distance | scalars | vector block]
        self.W_Q = nn.Linear(self.width, self.width, bias=False)
        self.W_K = nn.Linear(self.pair_dim, self.width, bias=False)
        self.W_V = nn.Linear(self.pair_dim, self.width)
        self.norm_attn = nn.LayerNorm(self.width)
        self.ffn = nn.Sequential(nn.Linear(self.width, ffn_dim), activation(act), nn.Linear(ffn_dim, self.width))
        self.norm_ffn = nn.LayerNorm(self.width)

    def forward(self, f: torch.Tensor, g: Graph) -> torch.Tensor:
        B, N, _ = f.shape
        m, H, C = self.m, self.heads, POSE_CHANNELS + self.m
        # Tensors are cut with split, not slices: a slice's backward writes a zero-filled copy of the whole
        # tensor per slice, and this layer is bound by memory traffic once its GEMMs are fast (bf16).
        # Under bf16 autocast the pair work below runs in bf16 from one cast of f and of the graph's small
        # tensors (each matmul would cast them again); the residual stream, LayerNorm and softmax stay fp32.
        f_lp = low_precision(f)
        F, pose = low_precision(g.F), low_precision(g.pose)
        f_s, f_v = f_lp.split([m, 3 * m], dim=-1)  # [B, N, m] scalars, [B, N, 3m] vector block
        # world-frame node data z_p = [s_p | (x_p, R_p, F_p V_p) as a spatial-major vector block]
        vec_world = torch.cat([pose, rotate_features(F, f_v.unflatten(-1, (3, m)))], dim=-1)  # [B, N, 3, C]
        z = torch.cat([f_s, vec_world.flatten(-2)], dim=-1)  # [B, N, Z]

        # keys: q_v . W_K x_vp = w_v . z_p + (term constant in p), w_v = W_K^T q_v with its vectors in world axes
        q = self.W_Q(f_lp).unflatten(-1, (H, self.head_dim))  # [B, N, H, d]
        W_K = self.W_K.weight.unflatten(0, (H, self.head_dim)) * (1.0 / math.sqrt(self.head_dim))  # [H, d, X]
        w = torch.einsum("bnhd,hdx->bnhx", q, W_K)  # [B, N, H, X] in v's frame
        w_dist, w_s, w_v = w.split([1, m, 3 * C], dim=-1)
        w_vec = rotate_features(F, w_v.unflatten(-1, (3, C)))  # [B, N, H, 3, C] world axes
        w_world = torch.cat([w_s, w_vec.flatten(-2)], dim=-1)  # [B, N, H, Z]
        # z on the left: its gradient (summed with the value product's) comes out contiguous
        logits = torch.bmm(z, w_world.reshape(B, N * H, -1).transpose(1, 2)).transpose(1, 2).view(B, N, H, N)
        logits = logits + w_dist * g.dist.unsqueeze(2)  # distance term, [B, N, H, N]
        logits = logits.masked_fill(~g.edges.unsqueeze(2), torch.finfo(logits.dtype).min)
        alpha = torch.softmax(logits, dim=-1)  # [B, N(v), H, N(p)]; each row has its self-loop

        # values: sum_p alpha_vp x_vp = canon_v(sum_p alpha_vp z_p), then W_V per head
        agg = torch.bmm(alpha.reshape(B, N * H, N).to(z.dtype), z).view(B, N, H, -1)  # [B, N, H, Z] world
        agg_dist = torch.einsum("bvhp,bvp->bvh", alpha, g.dist).unsqueeze(-1)  # [B, N, H, 1]
        agg_s, agg_v = agg.split([m, 3 * C], dim=-1)
        agg_x, agg_rest = agg_v.unflatten(-1, (3, C)).split([1, C - 1], dim=-1)
        agg_vec = torch.cat([agg_x - low_precision(g.x).view(B, N, 1, 3, 1), agg_rest], dim=-1)
        agg_vec = rotate_features(F.transpose(-1, -2), agg_vec)  # [B, N, H, 3, C] in v's frame
        pair = torch.cat([agg_dist, agg_s, agg_vec.flatten(-2)], dim=-1)  # [B, N, H, X]
        if H == 1:
            attn = self.W_V(pair.squeeze(2))  # [B, N, F]
        else:
            attn = torch.einsum("bnhx,hdx->bnhd", pair, self.W_V.weight.unflatten(0, (H, self.head_dim)))
            attn = attn.flatten(-2) + self.W_V.bias

        u = self.norm_attn(f + attn)  # mu: LayerNorm, then a residual feed-forward block with LayerNorm
        return self.norm_ffn(u + self.ffn(u))  # [B, N, F] in v's frame


@full_precision
def build_graph(layout: ObsLayout, fields, edge_radius: Optional[float], symmetry: str = "se3"):
    """Node frames (of ``symmetry``) and canonical node inputs [B, N, NODE_INPUTS] from ``read_obs`` fields."""
    R_i = own_rotation(fields)  # [B, 3, 3]
    mask = fields["mask"]  # [B, K]
    B, K = mask.shape
    zeros3 = fields["self.vel"].new_zeros(B, K, 3)
    full = layout.neighbor_obs == "full"
    # a pos_vel neighbour has no attitude of its own: its frame borrows R_i (still equivariant)
    R_nb = ObsLayout.as_matrix(fields["neighbor.rot"]) if full else R_i.unsqueeze(1).expand(B, K, 3, 3)
    R = torch.cat([R_i.unsqueeze(1), R_nb], dim=1)  # [B, N, 3, 3]
    x = torch.cat([zeros3.new_zeros(B, 1, 3), fields["neighbor.rel_pos"]], dim=1)  # [B, N, 3]
    vel = torch.cat([fields["self.vel"].unsqueeze(1), fields["self.vel"].unsqueeze(1) + fields["neighbor.rel_vel"]], 1)
    goal = torch.cat([-fields["self.rel_goal"].unsqueeze(1),  # x_i^d - x_i, same sign as neighbours' goal_offset
                      fields["neighbor.goal_offset"] if full else zeros3], dim=1)
    omega = torch.cat([fields["self.omega"].unsqueeze(1), fields["neighbor.omega"] if full else zeros3], dim=1)
    is_self = torch.zeros_like(x[..., :1])
    is_self[:, 0] = 1.0
    node_mask = torch.cat([mask.new_ones(B, 1), mask], dim=1)  # [B, N]
    F = frame_of(symmetry, R)  # [B, N, 3, 3]
    graph = Graph(R, x, node_mask, edge_radius, F)
    # canonical node inputs: vectors in the node's own frame (F_v^T v), body rates and the flag unchanged
    vel_goal = torch.einsum("bnji,bnjc->bnic", F, torch.stack([vel, goal], dim=-1))  # [B, N, 3, 2]
    inputs = torch.cat([vel_goal.flatten(-2), omega, is_self], dim=-1)  # [B, N, NODE_INPUTS]
    return graph, inputs


class GraphormerEncoder(nn.Module):
    """pi_hat of the paper: Group Equivariant Graphormer on drone i's local graph, then zeta.

    Args:
        layout: observation layout.
        multiplicity: m, the number of type-0 and of type-1 fibers per node (feature size 4 m; paper 60 -> 240).
        num_layers: Graphormer layers (paper 3).
        num_heads: attention heads (the paper's formula has 1); must divide 4 m.
        ffn_dim: hidden width of each layer's feed-forward block (default 4 m).
        ffn_activation: nonlinearity of the feed-forward blocks.
        zeta_sizes: widths of zeta (paper 256, 128, 256, 256): the canonical own state goes through the
            first two, is joined with the mean node feature (4 m) and goes through the rest.
        zeta_activation: nonlinearity of zeta (paper tanh, after every layer).
        out_vectors: how many of zeta's outputs are 3-vectors (mapped back by R_i); the rest are scalars.
        edge_radius: join only nodes closer than this (metres); None joins all nodes.
        symmetry: the group of the node frames (``encoders.frames.SYMMETRIES``): "se3" (the paper), "yaw" or
            "none" (world axes everywhere: the same architecture without the symmetry).
    """

    handles_symmetry = True  # canonicalizes node by node itself (the registry does not wrap it)

    def __init__(self, layout: ObsLayout, multiplicity: int = 60, num_layers: int = 3, num_heads: int = 1,
                 ffn_dim: Optional[int] = None, ffn_activation: str = "relu",
                 zeta_sizes: Sequence[int] = (256, 128, 256, 256), zeta_activation: str = "tanh",
                 out_vectors: Optional[int] = None, edge_radius: Optional[float] = None, symmetry: str = "se3"):
        super().__init__()
        if symmetry not in SYMMETRIES:
            raise ValueError(f"unknown symmetry {symmetry!r}; valid: {list(SYMMETRIES)}")
        if multiplicity < 1 or num_layers < 1:
            raise ValueError(f"multiplicity ({multiplicity}) and num_layers ({num_layers}) must be >= 1")
        if len(zeta_sizes) < 3:
            raise ValueError(f"zeta_sizes needs at least 3 widths (2 before the join, 1+ after), got {zeta_sizes}")
        out_dim = zeta_sizes[-1]
        self.out_vectors, self.equivariance = typed_output(out_dim, out_vectors, symmetry, "zeta_sizes[-1]")
        self.layout = layout
        self.out_dim = out_dim
        self.symmetry = symmetry
        self.edge_radius = edge_radius
        self.m = multiplicity
        width = 4 * multiplicity
        self.embed = nn.Linear(NODE_INPUTS, width)
        self.layers = nn.ModuleList(
            EquivariantGraphormerLayer(multiplicity, num_heads, ffn_dim or width, ffn_activation)
            for _ in range(num_layers))
        self.zeta_state = mlp([self_input_dim(layout), *zeta_sizes[:2]], zeta_activation)
        self.zeta_joint = mlp([zeta_sizes[1] + width, *zeta_sizes[2:]], zeta_activation)
        xavier_init_(self)

    def node_features(self, obs: torch.Tensor):
        """Final node features, canonical (each in its own node's frame) [B, N, 4 m], with the graph."""
        fields = read_obs(self.layout, obs)
        graph, inputs = build_graph(self.layout, fields, self.edge_radius, self.symmetry)
        f = self.embed(inputs)  # [B, N, 4m], node v's features in v's frame
        for layer in self.layers:
            f = layer(f, graph)
        return f, graph, fields

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        f, g, fields = self.node_features(obs)
        m = self.m
        # mean over real nodes of phi_{g_i^-1} f_j = (s_j, F_i^T F_j V_j)
        w = g.node_mask.to(f.dtype).unsqueeze(-1)  # [B, N, 1]
        count = w.sum(1)  # [B, 1], >= 1 (drone i itself)
        mean_s = (f[..., :m] * w).sum(1) / count  # [B, m]
        vec_world = rotate(g.F, f[..., m:].unflatten(-1, (3, m)))  # [B, N, 3, m]
        mean_vec = (vec_world * w.unsqueeze(-1)).sum(1) / count.unsqueeze(-1)  # [B, 3, m] world
        F_i = g.F[:, 0]
        mean_vec = rotate(F_i.transpose(-1, -2).unsqueeze(1), mean_vec.unsqueeze(1)).squeeze(1)  # [B, 3, m] frame i

        canon = canonicalize(self.layout, fields, F_i, groups=("self", "obstacle"))
        state = torch.cat([canon[k] for k in self_keys(self.layout)], dim=-1)  # [B, S]
        h = self.zeta_state(state)
        out = self.zeta_joint(torch.cat([h, mean_s, mean_vec.flatten(-2)], dim=-1))  # [B, out_dim] frame i
        return typed_to_world(out, F_i, self.out_vectors)
