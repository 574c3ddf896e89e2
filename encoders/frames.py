"""Group canonicalization (paper, Lemma 1): express inputs in drone i's own frame, map typed outputs back.

Drone i's frame is g_i = (R_i, x_i). Every position in the observation is already relative to x_i, so
x_i is the origin and only R_i acts:

- ``world_vector`` v  ->  R_i^T v
- ``rotation``     R  ->  R_i^T R
- ``body`` / ``scalar`` fields are unchanged.

A global move of the world by (Q, t) turns R_i into Q R_i and every world vector v into Q v, so the
canonical inputs are invariant; a network of them, whose vector outputs are mapped back by R_i,
is therefore SE(3)-equivariant whatever the network is.

Typed outputs are laid out ``[num_scalars | num_vectors x 3]``: the scalars first, then each 3-vector's
x, y, z in turn (``out[..., S:].reshape(..., V, 3)``).
"""
from __future__ import annotations

from typing import Dict, Tuple

import torch

from quad_env.obs_layout import ObsLayout


def to_frame(v: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """R^T v for 3-vectors ``v`` [..., 3] and rotations ``R`` [..., 3, 3] (broadcast)."""
    return (v.unsqueeze(-2) @ R).squeeze(-2)


def from_frame(v: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """R v for 3-vectors ``v`` [..., 3] and rotations ``R`` [..., 3, 3] (broadcast)."""
    return (R @ v.unsqueeze(-1)).squeeze(-1)


def own_rotation(fields: Dict[str, torch.Tensor]) -> torch.Tensor:
    """R_i, drone i's body->world rotation, as [B, 3, 3]."""
    return ObsLayout.as_matrix(fields["self.rot"])


def canonicalize(layout: ObsLayout, fields: Dict[str, torch.Tensor], R: torch.Tensor,
                 groups: Tuple[str, ...] = ("self", "neighbor", "obstacle")) -> Dict[str, torch.Tensor]:
    """The fields of ``groups`` (from ``read_obs``) expressed in the frame with rotation ``R`` [B, 3, 3]."""
    out = dict(fields)
    for f in layout.fields:
        if f.group not in groups:
            continue
        key = f"{f.group}.{f.name}"
        value = fields[key]
        Rb = R if f.group != "neighbor" else R.unsqueeze(1)  # [B, 1, 3, 3] broadcasts over K
        if f.kind == "world_vector":
            out[key] = to_frame(value, Rb)
        elif f.kind == "rotation":
            M = ObsLayout.as_matrix(value)
            out[key] = (Rb.transpose(-1, -2) @ M).flatten(-2)
    return out


def typed_to_world(out: torch.Tensor, R: torch.Tensor, num_vectors: int) -> torch.Tensor:
    """Map a typed output computed in frame R back to the world: scalars unchanged, vectors rotated by R."""
    if num_vectors == 0:
        return out
    num_scalars = out.shape[-1] - 3 * num_vectors
    scalars, vectors = out[..., :num_scalars], out[..., num_scalars:]
    vectors = from_frame(vectors.reshape(*out.shape[:-1], num_vectors, 3), R.unsqueeze(-3))
    return torch.cat([scalars, vectors.flatten(-2)], dim=-1)
