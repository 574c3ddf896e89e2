"""Building blocks shared by the encoders: reading observations, MLPs, masked set operations, init."""
from __future__ import annotations

from typing import Dict, Sequence

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout


class _TanhViaFloat32(torch.autograd.Function):
    """tanh of a bf16/fp16 CPU tensor computed in fp32 and rounded once: bit-identical to ``torch.tanh`` on the
    low-precision tensor, but 2-2.7x faster for bf16 on the CPU, where torch's bf16 tanh kernel is 2x slower than its
    fp32 one (benchmarks/RESULTS.md, "bf16_tanh"). The backward uses the saved output in its own dtype, as
    ``torch.tanh``'s does."""

    CHUNK = 1 << 17  # elements per fp32 pass: 512 KB, stays in L2 (3x the native kernel, vs 2.2x unchunked)

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        flat = x.contiguous().view(-1)
        y = torch.empty_like(flat)
        buf = torch.empty(min(_TanhViaFloat32.CHUNK, flat.numel()), dtype=torch.float32)
        for start in range(0, flat.numel(), _TanhViaFloat32.CHUNK):
            n = min(_TanhViaFloat32.CHUNK, flat.numel() - start)
            chunk = buf[:n]
            chunk.copy_(flat[start:start + n])
            chunk.tanh_()
            y[start:start + n].copy_(chunk)
        y = y.view(x.shape)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


class Tanh(nn.Module):
    """``nn.Tanh`` with a faster path for bf16/fp16 tensors on the CPU (``runner.precision=bf16``); every other
    dtype and device (fp32, CUDA, an exported or traced policy) and torch.compile (whose generated kernel computes
    in fp32 anyway) run ``torch.tanh`` itself."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (x.device.type == "cpu" and x.dtype in (torch.bfloat16, torch.float16)
                and not torch.compiler.is_compiling()):
            return _TanhViaFloat32.apply(x)
        return torch.tanh(x)


ACTIVATIONS = {"tanh": Tanh, "relu": nn.ReLU, "silu": nn.SiLU, "gelu": nn.GELU, "elu": nn.ELU}


def activation(name: str) -> nn.Module:
    if name not in ACTIVATIONS:
        raise ValueError(f"unknown activation {name!r}; valid: {sorted(ACTIVATIONS)}")
    return ACTIVATIONS[name]()


def mlp(sizes: Sequence[int], act: str = "tanh", last_act: bool = True) -> nn.Sequential:
    """Linear layers ``sizes[0] -> sizes[1] -> ...`` with ``act`` after each (and after the last if ``last_act``)."""
    layers = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(n_in, n_out))
        if last_act or i < len(sizes) - 2:
            layers.append(activation(act))
    return nn.Sequential(*layers)


def xavier_init_(module: nn.Module) -> nn.Module:
    """Xavier-uniform weights and zero biases for every Linear (paper, Appendix III); LayerNorms stay (1, 0)."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
    return module


def masked_mean(x: torch.Tensor, mask: torch.Tensor, dim: int) -> torch.Tensor:
    """Mean of ``x`` over ``dim`` counting only entries where ``mask`` (bool, x's shape without the feature
    dim) is true; an empty set gives zeros. ``x`` must already be finite in masked slots."""
    w = mask.to(x.dtype).unsqueeze(-1)
    count = w.sum(dim).clamp(min=1.0)
    return (x * w).sum(dim) / count


def masked_softmax(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Softmax over the last dim restricted to ``mask``; masked entries get exactly 0 weight and an
    all-masked row gives all zeros (not NaN)."""
    logits = logits.masked_fill(~mask, torch.finfo(logits.dtype).min)
    return torch.softmax(logits, dim=-1) * mask.to(logits.dtype)


def read_obs(layout: ObsLayout, obs: torch.Tensor) -> Dict[str, torch.Tensor]:
    """Split ``obs`` [B, D] with the layout and make padded neighbour slots exactly zero.

    Returns the layout's keys (``self.*`` [B, n], ``neighbor.*`` [B, K, n], ``obstacle.*``) plus
    ``mask`` as a bool tensor [B, K]. Zeroing with ``torch.where`` (not a multiply) keeps NaN/inf garbage
    in padded slots out of both the outputs and the gradients.
    """
    if obs.dim() != 2:
        raise ValueError(f"expected an observation batch [B, {layout.dim}], got shape {tuple(obs.shape)}")
    fields = layout.split(obs)
    mask = fields["mask"] > 0.5  # [B, K]
    out = {"mask": mask}
    zero = obs.new_zeros(())
    for key, value in fields.items():
        if key.startswith("neighbor."):
            value = torch.where(mask.unsqueeze(-1), value, zero)
        if key != "mask":
            out[key] = value
    return out


def self_keys(layout: ObsLayout):
    """Keys of the fields that describe drone i itself: its own state plus the obstacle field if present."""
    return [f"{f.group}.{f.name}" for f in layout.fields if f.group in ("self", "obstacle")]


def neighbor_keys(layout: ObsLayout):
    return [f"neighbor.{f.name}" for f in layout.fields_of("neighbor")]



def flat_inputs(layout: ObsLayout, fields: Dict[str, torch.Tensor]):
    """``(self_x [B, S], neighbors [B, K, F], mask [B, K])`` from ``read_obs`` (or canonicalized) fields."""
    self_x = torch.cat([fields[k] for k in self_keys(layout)], dim=-1)
    nb = torch.cat([fields[k] for k in neighbor_keys(layout)], dim=-1)
    return self_x, nb, fields["mask"]


def self_input_dim(layout: ObsLayout) -> int:
    return sum(f.size for f in layout.fields if f.group in ("self", "obstacle"))
