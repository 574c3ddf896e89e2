"""Body-frame inputs: drone i's observation with every world-frame quantity expressed in its own frame.

A controller of body-fixed rotors needs, e.g., the velocity along its own axes: R_i^T v. A network fed
world-frame vectors has to learn that product of inputs itself, which a small MLP learns slowly; this
module computes it exactly. World vectors v become R_i^T v, neighbour rotations R_j become R_i^T R_j,
and drone i's own rotation R_i is kept as it is (its last row is "up" in the body frame: gravity breaks
the rotational symmetry, so no information is dropped). Body fields, scalars and the mask are unchanged.

Meant for the world-frame encoders (``deepsets``, ``kattention``, ``mlp``); the SE(3) encoders
canonicalize their neighbour inputs by R_i already.
"""
from __future__ import annotations

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout


class BodyFrameInput(nn.Module):
    """``forward(obs [B, D]) -> obs [B, D]`` in drone i's body frame (see the module docstring)."""

    def __init__(self, layout: ObsLayout):
        super().__init__()
        self.layout = layout
        rot = layout.field("rot")
        self.rot_slice = slice(rot.start, rot.stop)
        vec_idx, mat_idx = [], []
        blocks = [(0, f) for f in layout.fields if f.group in ("self", "obstacle")]
        for k in range(layout.num_neighbors):
            blocks += [(k * layout.neighbor_dim, f) for f in layout.fields if f.group == "neighbor"]
        for off, f in blocks:
            if f.kind == "world_vector":
                vec_idx += range(f.start + off, f.stop + off)
            elif f.kind == "rotation" and not (f.group == "self" and f.name == "rot"):
                mat_idx += range(f.start + off, f.stop + off)
        self.register_buffer("vec_idx", torch.tensor(vec_idx, dtype=torch.long), persistent=False)
        self.register_buffer("mat_idx", torch.tensor(mat_idx, dtype=torch.long), persistent=False)
        # Output column c reads column perm[c] of [obs | rotated vectors | rotated matrices]: one gather, no
        # in-place index writes (which the ONNX exporter mistranslates).
        perm = list(range(layout.dim))
        for k, c in enumerate(vec_idx + mat_idx):
            perm[c] = layout.dim + k
        self.register_buffer("perm", torch.tensor(perm, dtype=torch.long), persistent=False)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        B = obs.shape[0]
        R = obs[:, self.rot_slice].reshape(B, 3, 3)  # [B, 3, 3] body -> world
        v = obs[:, self.vec_idx].reshape(B, -1, 3)  # [B, V, 3]
        v_body = (v @ R).reshape(B, -1)  # rows v^T R = (R^T v)^T
        M = obs[:, self.mat_idx].reshape(B, -1, 3, 3)  # [B, Q, 3, 3]
        m_body = (R.transpose(1, 2).unsqueeze(1) @ M).reshape(B, -1)  # R^T M
        return torch.cat([obs, v_body, m_body], dim=1)[:, self.perm]
