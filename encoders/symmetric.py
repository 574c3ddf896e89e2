"""Group canonicalization of any world-frame encoder (paper, Lemma 1): pi_hat = phi_{g_i} zeta(phi_{g_i}^-1 obs).

The observation is expressed in drone i's frame F_i (``encoders.body_frame.FrameInput``), the unconstrained
encoder runs there, and its output, typed as ``out_dim - 3 * out_vectors`` scalars followed by
``out_vectors`` 3-vectors, is mapped back to world axes by F_i. A global group element Q (any rotation for
``se3``, a rotation about z for ``yaw``) turns F_i into Q F_i and leaves the canonical input unchanged, so
the scalars are invariant and the vectors turn with Q, whatever the inner network is.

The Graphormer canonicalizes node by node itself (each node in its own frame); this wrapper serves the
encoders whose neighbour set is read from drone i's point of view only (DeepSets, K-Attention, MLP).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .body_frame import FrameInput
from .frames import SYMMETRIES, typed_to_world


def default_out_vectors(out_dim: int) -> int:
    """A quarter of the output width as 3-vectors (3/4 of the entries), the rest scalars: the split of the
    paper's SE(3)-K-Attention (128 vectors + 128 scalars of 512)."""
    return out_dim // 4


class Canonicalized(nn.Module):
    """``inner`` run in drone i's frame of ``symmetry``; its output typed and mapped back to world axes.

    Args:
        inner: a world-frame encoder ``obs [B, D] -> [B, out_dim]`` (its attribute ``out_dim``).
        layout: observation layout.
        symmetry: "se3" or "yaw" (see ``encoders.frames.SYMMETRIES``).
        out_vectors: how many outputs are 3-vectors; None = ``default_out_vectors(out_dim)``.
    """

    def __init__(self, inner: nn.Module, layout: ObsLayout, symmetry: str, out_vectors: Optional[int] = None):
        super().__init__()
        if symmetry not in SYMMETRIES or symmetry == "none":
            raise ValueError(f"Canonicalized needs a symmetry group, one of {list(SYMMETRIES[1:])}, got {symmetry!r}")
        out_dim = inner.out_dim
        out_vectors = default_out_vectors(out_dim) if out_vectors is None else int(out_vectors)
        if not 0 <= 3 * out_vectors <= out_dim:
            raise ValueError(f"out_vectors={out_vectors} needs 0 <= 3 * out_vectors <= out_dim={out_dim}")
        self.inner = inner
        self.layout = layout
        self.symmetry = symmetry
        self.out_dim = out_dim
        self.out_vectors = out_vectors
        self.equivariance = (out_dim - 3 * out_vectors, out_vectors)
        self.to_local = FrameInput(layout, symmetry, keep_own_rot=False)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        F = self.to_local.own_frame(obs)  # [B, 3, 3] drone i's frame
        out = self.inner(self.to_local(obs, F))  # [B, out_dim] in drone i's frame
        return typed_to_world(out, F, self.out_vectors)
