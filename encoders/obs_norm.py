"""Observation normalisation that keeps SE(3) equivariance: one running scalar scale per observation field.

Every vector field (world vectors, body vectors) and the obstacle scalars are divided by the running RMS
of their norm, sqrt(E[||v||^2]); rotations and the mask are left as they are. A scalar multiple commutes
with every rotation (Q (s v) = s (Q v)), so an SE(3)-equivariant encoder behind this stage stays exactly
equivariant. There is no mean subtraction: a mean vector would pick a direction in world axes.
A neighbour field has one scale for all K slots (permutation symmetry), estimated over real neighbours only.

The statistics are buffers, so they travel in the ``state_dict`` to rollout workers and checkpoints.
``forward`` never changes them; the learner calls ``update(obs)`` once per training batch
(Sample Factory style), so rollout workers act with frozen statistics.
"""
from __future__ import annotations

from typing import List

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

SCALED_KINDS = ("world_vector", "body", "scalar")  # rotations and masks keep their values


class FieldScaleNorm(nn.Module):
    """``obs [B, D] -> obs * scale [D]`` with one scale per scaled field: 1 / max(running RMS norm, min_rms).

    Args:
        layout: observation layout.
        min_rms: floor of the RMS norm (a field that is always ~0 is not blown up).
    """

    def __init__(self, layout: ObsLayout, min_rms: float = 1e-3):
        super().__init__()
        self.layout = layout
        self.min_rms = float(min_rms)
        self.fields = [f for f in layout.fields if f.kind in SCALED_KINDS]
        self.field_names: List[str] = [f"{f.group}.{f.name}" for f in self.fields]
        # field id of every observation entry; -1 = not scaled (rotation, mask)
        entry_field = torch.full((layout.dim,), -1, dtype=torch.long)
        copies = lambda f: layout.num_neighbors if f.group == "neighbor" else 1  # noqa: E731
        for i, f in enumerate(self.fields):
            for k in range(copies(f)):
                off = k * layout.neighbor_dim if f.group == "neighbor" else 0
                entry_field[f.start + off:f.stop + off] = i
        self.register_buffer("entry_field", entry_field, persistent=False)
        # running statistics, float64 so long runs do not lose precision
        self.register_buffer("count", torch.zeros(len(self.fields), dtype=torch.float64))  # [F] vectors seen
        self.register_buffer("mean_sq_norm", torch.zeros(len(self.fields), dtype=torch.float64))  # [F] E||v||^2

    def field_scales(self) -> torch.Tensor:
        """``[F]`` scale of each field; 1 for a field not seen yet."""
        rms = self.mean_sq_norm.sqrt().clamp(min=self.min_rms)
        return torch.where(self.count > 0, 1.0 / rms, torch.ones_like(rms))

    def entry_scales(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """``[D]`` scale of every observation entry (1 for rotations and masks)."""
        scales = torch.cat([self.field_scales(), self.field_scales().new_ones(1)])  # index -1 -> the trailing 1
        return scales[self.entry_field].to(dtype)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return obs * self.entry_scales(obs.dtype)

    @torch.no_grad()
    def update(self, obs: torch.Tensor) -> None:
        """Fold a batch ``[..., D]`` of raw observations into the running E||v||^2 of every field."""
        fields = self.layout.split(obs.reshape(-1, self.layout.dim).to(torch.float64))
        real = fields["mask"] > 0.5 if self.layout.num_neighbors else None  # [M, K]
        for i, f in enumerate(self.fields):
            sq = fields[f"{f.group}.{f.name}"].pow(2).sum(-1)  # [M] or [M, K]
            if f.group == "neighbor":
                sq = sq[real]
            n = sq.numel()
            if n == 0:
                continue
            total = self.count[i] + n
            self.mean_sq_norm[i] += (sq.mean() - self.mean_sq_norm[i]) * (n / total)
            self.count[i] = total

    def extra_repr(self) -> str:
        return f"fields={self.field_names}, min_rms={self.min_rms}"
