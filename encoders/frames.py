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

import functools
from typing import Dict, Optional, Tuple

import torch

from quad_env.obs_layout import ObsLayout


def full_precision(fn):
    """Run ``fn`` (a frame map) in float32 even inside a bf16 ``torch.autocast`` region: its floating tensor
    arguments are cast to float32 and autocast is off while it runs. Rotating a position by a bf16 matrix
    would err by ~0.4 % (4 cm at 10 m) and break the exact equivariance that canonicalization gives; these
    3x3 maps cost little next to the network's matmuls. Outside autocast it is a plain call."""
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        tensors = [a for a in args if isinstance(a, torch.Tensor)]
        device_type = tensors[0].device.type if tensors else "cpu"
        if not torch.is_autocast_enabled(device_type):
            return fn(*args, **kwargs)
        args = tuple(a.float() if isinstance(a, torch.Tensor) and a.is_floating_point() else a for a in args)
        with torch.autocast(device_type, enabled=False):
            return fn(*args, **kwargs)
    return wrapped


@full_precision
def to_frame(v: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """R^T v for 3-vectors ``v`` [..., 3] and rotations ``R`` [..., 3, 3] (broadcast)."""
    return (v.unsqueeze(-2) @ R).squeeze(-2)


@full_precision
def from_frame(v: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """R v for 3-vectors ``v`` [..., 3] and rotations ``R`` [..., 3, 3] (broadcast)."""
    return (R @ v.unsqueeze(-1)).squeeze(-1)


def own_rotation(fields: Dict[str, torch.Tensor]) -> torch.Tensor:
    """R_i, drone i's body->world rotation, as [B, 3, 3]."""
    return ObsLayout.as_matrix(fields["self.rot"])


@full_precision
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


@full_precision
def typed_to_world(out: torch.Tensor, R: torch.Tensor, num_vectors: int) -> torch.Tensor:
    """Map a typed output computed in frame R back to the world: scalars unchanged, vectors rotated by R."""
    if num_vectors == 0:
        return out
    num_scalars = out.shape[-1] - 3 * num_vectors
    scalars, vectors = out[..., :num_scalars], out[..., num_scalars:]
    if R.shape[:-2] == out.shape[:-1]:  # one frame per row (every caller): a batched product, no broadcast copy
        rows = vectors.reshape(-1, num_vectors, 3)  # [B', V, 3]
        vectors = torch.bmm(rows, R.reshape(-1, 3, 3).transpose(1, 2))  # rows v^T R^T = (R v)^T
    else:
        vectors = from_frame(vectors.reshape(*out.shape[:-1], num_vectors, 3), R.unsqueeze(-3))
    return torch.cat([scalars, vectors.reshape(*out.shape[:-1], 3 * num_vectors)], dim=-1)


# ----------------------------------------------------------------------------------------------- symmetry groups
SYMMETRIES = ("none", "se3", "yaw")
"""Groups an encoder can be made equivariant to (``model.symmetry``):

- ``none``: world-frame inputs; only translations act (every position is relative), no rotation.
- ``se3``: drone i's frame is its attitude R_i (the paper): equivariant to every global rotation.
- ``yaw``: drone i's heading frame, the rotation about gravity by its yaw: equivariant to rotations about
  the world z axis only, the symmetry the quadrotor dynamics really have (gravity breaks the rest).
"""


def yaw_frame(R: torch.Tensor) -> torch.Tensor:
    """Heading frames [..., 3, 3] of attitudes ``R`` [..., 3, 3]: the rotation about z by the yaw of the body
    x axis (its horizontal projection, normalised). A global rotation Q about z maps the frame to Q F."""
    c, s = R[..., 0, 0], R[..., 1, 0]
    h = torch.sqrt(c * c + s * s).clamp(min=1e-12)  # 0 only for a body x axis pointing straight up or down
    c, s = c / h, s / h
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], dim=-1).unflatten(-1, (3, 3))


def frame_of(symmetry: str, R: torch.Tensor) -> torch.Tensor:
    """The canonicalizing frame of attitudes ``R`` [..., 3, 3] for ``symmetry`` (identity for ``none``)."""
    if symmetry == "se3":
        return R
    if symmetry == "yaw":
        return yaw_frame(R)
    if symmetry == "none":
        return torch.eye(3, dtype=R.dtype, device=R.device).expand(R.shape)
    raise ValueError(f"unknown symmetry {symmetry!r}; valid: {list(SYMMETRIES)}")


def typed_output(out_dim: int, out_vectors: Optional[int], symmetry: str,
                 width_name: str = "out_dim") -> Tuple[int, Optional[Tuple[int, int]]]:
    """``(out_vectors, equivariance)`` of an encoder output of width ``out_dim`` typed as scalars then 3-vectors.

    ``out_vectors`` None = a quarter of the width as 3-vectors with a symmetry (the paper's split: 128 of 512 for
    SE(3)-K-Attention, 64 of 256 for the Graphormer), 0 without one. ``equivariance`` is ``(num_scalars,
    num_vectors)``, None without a symmetry (the output is then plain, in world axes)."""
    if out_vectors is None:
        out_vectors = 0 if symmetry == "none" else out_dim // 4
    out_vectors = int(out_vectors)
    if not 0 <= 3 * out_vectors <= out_dim:
        raise ValueError(f"out_vectors={out_vectors} needs 0 <= 3 * out_vectors <= {width_name}={out_dim}")
    return out_vectors, None if symmetry == "none" else (out_dim - 3 * out_vectors, out_vectors)
