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

from typing import Optional, Tuple

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .body_frame import FrameInput
from .frames import SYMMETRIES, typed_output, typed_to_world


class Canonicalized(nn.Module):
    """``inner`` run in drone i's frame of ``symmetry``; its output typed and mapped back to world axes.

    Args:
        inner: a world-frame encoder ``obs [B, D] -> [B, out_dim]`` (its attribute ``out_dim``).
        layout: observation layout.
        symmetry: "se3" or "yaw" (see ``encoders.frames.SYMMETRIES``).
        out_vectors: how many outputs are 3-vectors; None = a quarter of the width (``frames.typed_output``).
    """

    def __init__(self, inner: nn.Module, layout: ObsLayout, symmetry: str, out_vectors: Optional[int] = None):
        super().__init__()
        if symmetry not in SYMMETRIES or symmetry == "none":
            raise ValueError(f"Canonicalized needs a symmetry group, one of {list(SYMMETRIES[1:])}, got {symmetry!r}")
        self.out_vectors, self.equivariance = typed_output(inner.out_dim, out_vectors, symmetry)
        self.inner = inner
        self.layout = layout
        self.symmetry = symmetry
        self.out_dim = inner.out_dim
        self.to_local = FrameInput(layout, symmetry, keep_own_rot=False)

    def canonical(self, obs: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(obs in drone i's frame [B, D], the frame F_i [B, 3, 3])``: what ``forward`` feeds ``inner``; it has
        no weights, so two ``Canonicalized`` of one layout and symmetry can share it (the actor and the critic)."""
        F = self.to_local.own_frame(obs)  # [B, 3, 3] drone i's frame
        return self.to_local(obs, F), F

    def forward(self, obs: torch.Tensor, canonical: Optional[Tuple[torch.Tensor, torch.Tensor]] = None
                ) -> torch.Tensor:
        """``obs [B, D] -> [B, out_dim]`` in world axes; ``canonical``: ``self.canonical(obs)`` if already made."""
        local, F = self.canonical(obs) if canonical is None else canonical
        out = self.inner(local)  # [B, out_dim] in drone i's frame
        return typed_to_world(out, F, self.out_vectors)
