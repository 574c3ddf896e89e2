"""Observations re-expressed in a frame of drone i: every world-frame quantity rotated by F_i^T.

Two uses, one module:

- ``FrameInput(layout, "se3", keep_own_rot=False)`` is the input side of group canonicalization (paper,
  Lemma 1; ``encoders.symmetric``): world vectors v -> F_i^T v, rotations R -> F_i^T R (drone i's own
  attitude included), with F_i = R_i (``se3``) or drone i's heading frame (``yaw``). The result is
  invariant to the group.
- ``BodyFrameInput(layout)`` (``model.body_frame_obs``, world-frame encoders only): the same with F_i = R_i,
  but drone i's own rotation R_i is kept as it is (its last row is "up" in the body frame: gravity breaks the
  rotational symmetry, so no information is dropped). A rotor command depends on body-frame quantities,
  which a small world-frame MLP would otherwise have to learn as products of its inputs.

Body fields, scalars and the mask are unchanged.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .frames import frame_of, full_precision


class FrameInput(nn.Module):
    """``forward(obs [B, D], F [B, 3, 3] = None) -> obs [B, D]`` expressed in frame F (default: the frame of
    ``symmetry`` computed from drone i's own attitude)."""

    def __init__(self, layout: ObsLayout, symmetry: str = "se3", keep_own_rot: bool = False):
        super().__init__()
        self.layout = layout
        self.symmetry = symmetry
        rot = layout.field("rot")
        self.rot_slice = slice(rot.start, rot.stop)
        vec_idx, mat_idx = [], []
        blocks = [(0, f) for f in layout.fields if f.group in ("self", "obstacle")]
        for k in range(layout.num_neighbors):
            blocks += [(k * layout.neighbor_dim, f) for f in layout.fields if f.group == "neighbor"]
        for off, f in blocks:
            if f.kind == "world_vector":
                vec_idx += range(f.start + off, f.stop + off)
            elif f.kind == "rotation" and not (keep_own_rot and f.group == "self" and f.name == "rot"):
                mat_idx += range(f.start + off, f.stop + off)
        # Every 3-vector the frame acts on, as one [B, V, 3] gather: the world vectors, then each rotation's
        # columns (F^T M is F^T applied to every column of M; M is stored row-major, so column k of the block at
        # m is entries m + k, m + 3 + k, m + 6 + k). One batched 3x3 product then rotates them all.
        triples = [vec_idx[i:i + 3] for i in range(0, len(vec_idx), 3)]
        for m in range(0, len(mat_idx), 9):
            triples += [[mat_idx[m + 3 * r + k] for r in range(3)] for k in range(3)]
        self.num_triples = len(triples)
        triple_idx = [c for t in triples for c in t]
        self.register_buffer("triple_idx", torch.tensor(triple_idx, dtype=torch.long), persistent=False)
        # Output column c reads column perm[c] of [obs | rotated triples]: one gather, no in-place index writes
        # (which the ONNX exporter mistranslates).
        perm = list(range(layout.dim))
        for k, c in enumerate(triple_idx):
            perm[c] = layout.dim + k
        self.register_buffer("perm", torch.tensor(perm, dtype=torch.long), persistent=False)

    def own_frame(self, obs: torch.Tensor) -> torch.Tensor:
        """F_i [B, 3, 3] of every row, from drone i's attitude R_i (body -> world)."""
        return frame_of(self.symmetry, obs[:, self.rot_slice].reshape(obs.shape[0], 3, 3))

    @full_precision
    def forward(self, obs: torch.Tensor, F: Optional[torch.Tensor] = None) -> torch.Tensor:
        B = obs.shape[0]
        F = self.own_frame(obs) if F is None else F  # [B, 3, 3]
        v = obs[:, self.triple_idx].reshape(B, self.num_triples, 3)  # [B, V, 3] vectors and rotation columns
        v_local = torch.bmm(v, F).reshape(B, -1)  # rows v^T F = (F^T v)^T
        return torch.cat([obs, v_local], dim=1)[:, self.perm]


def BodyFrameInput(layout: ObsLayout) -> FrameInput:
    """Body-frame inputs for the world-frame encoders (``model.body_frame_obs``): R_i^T v, R_i^T R_j, R_i kept."""
    return FrameInput(layout, "se3", keep_own_rot=True)
