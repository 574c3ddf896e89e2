"""Encoders by name. Adding one: write its module, then add one line to ``ENCODER_CLASSES``."""
from __future__ import annotations

import inspect

from torch import nn

from quad_env.obs_layout import ObsLayout

from .deepsets import DeepSetsEncoder
from .kattention import KAttentionEncoder, SE3KAttentionEncoder
from .mlp import MLPEncoder
from .se3_graphormer import SE3GraphormerEncoder

ENCODER_CLASSES = {
    "se3_graphormer": SE3GraphormerEncoder,
    "se3_kattention": SE3KAttentionEncoder,
    "kattention": KAttentionEncoder,
    "deepsets": DeepSetsEncoder,
    "mlp": MLPEncoder,
}
ENCODERS = tuple(ENCODER_CLASSES)


def encoder_options(name: str) -> dict:
    """Keyword options of encoder ``name`` with their defaults."""
    params = list(inspect.signature(_encoder_class(name).__init__).parameters.values())[2:]  # skip self, layout
    return {p.name: p.default for p in params}


def _encoder_class(name: str):
    if name not in ENCODER_CLASSES:
        raise ValueError(f"unknown encoder {name!r}; valid: {list(ENCODERS)}")
    return ENCODER_CLASSES[name]


def make_encoder(name: str, layout: ObsLayout, **kwargs) -> nn.Module:
    """Build encoder ``name`` for observations of ``layout``; ``kwargs`` override its default sizes.

    The module maps ``obs [B, layout.dim]`` to ``[B, enc.out_dim]``; ``enc.equivariance`` is
    ``(num_scalars, num_vectors)`` for the SE(3) encoders and None for the baselines.
    """
    cls = _encoder_class(name)
    if not isinstance(layout, ObsLayout):
        raise TypeError(f"layout must be a quad_env.obs_layout.ObsLayout, got {type(layout).__name__}")
    valid = encoder_options(name)
    unknown = sorted(set(kwargs) - set(valid))
    if unknown:
        raise TypeError(f"encoder {name!r} got unknown option(s) {unknown}; valid: {sorted(valid)}")
    return cls(layout, **kwargs)
