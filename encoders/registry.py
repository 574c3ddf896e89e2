"""Encoders by name, each with a symmetry and a size preset.

An encoder is an *architecture* (``ARCHITECTURES``: graphormer, kattention, deepsets, mlp, infomarl) times a *symmetry*
(``encoders.frames.SYMMETRIES``: none, se3, yaw), orthogonal to each other as the paper's Lemma 1 allows:
any architecture is made equivariant by canonicalization (``encoders.symmetric``; the Graphormer does it
node by node itself). The paper's names stay selectable: ``se3_graphormer`` and ``se3_kattention`` are
graphormer / kattention with ``se3`` (``ALIASES``).

Adding an architecture: write its module (a class ``(layout, **sizes)`` with ``out_dim``), then add one line
to ``ARCHITECTURES`` and its entry in ``SIZE_PRESETS``.
"""
from __future__ import annotations

import inspect
from typing import Dict, Optional, Tuple

from torch import nn

from quad_env.obs_layout import ObsLayout

from .deepsets import DeepSetsEncoder
from .frames import SYMMETRIES
from .graphormer import GraphormerEncoder
from .infomarl import InfoMARLEncoder
from .kattention import KAttentionEncoder
from .mlp import MLPEncoder
from .symmetric import Canonicalized

ARCHITECTURES = {
    "graphormer": GraphormerEncoder,
    "kattention": KAttentionEncoder,
    "deepsets": DeepSetsEncoder,
    "mlp": MLPEncoder,
    "infomarl": InfoMARLEncoder,
}
# the paper's names: (architecture, symmetry)
ALIASES: Dict[str, Tuple[str, str]] = {
    "se3_graphormer": ("graphormer", "se3"),
    "se3_kattention": ("kattention", "se3"),
}
ENCODERS = tuple(ALIASES) + tuple(ARCHITECTURES)

# model.size: encoder options per preset ("paper" = the constructors' defaults, the paper's sizes)
SIZES = ("paper", "small")
SIZE_PRESETS: Dict[str, Dict[str, dict]] = {
    "paper": {name: {} for name in ARCHITECTURES},
    "small": {  # a 2-core laptop: ~64-wide layers, every architecture within a factor ~3 of the others in cost
        "graphormer": dict(multiplicity=8, num_layers=2, zeta_sizes=(64, 64, 64, 64)),
        "kattention": dict(hidden=64, out_dim=64),
        "deepsets": dict(hidden=64, out_dim=64),
        "mlp": dict(hidden=64, out_dim=64),
        "infomarl": dict(hidden=32, num_heads=2, out_dim=64),
    },
}
WRAPPER_OPTIONS = ("out_vectors",)  # options of the canonicalization, not of the architecture


def resolve(name: str, symmetry: Optional[str] = None) -> Tuple[str, str]:
    """``(architecture, symmetry)`` of encoder ``name`` with ``symmetry`` (None = the name's own: se3 for the
    paper's se3_* names, none otherwise). Raises ValueError naming both when they contradict."""
    if name not in ENCODERS:
        raise ValueError(f"unknown encoder {name!r}; valid: {list(ENCODERS)}")
    if symmetry is not None and symmetry not in SYMMETRIES:
        raise ValueError(f"unknown symmetry {symmetry!r}; valid: {list(SYMMETRIES)}")
    if name in ALIASES:
        arch, own = ALIASES[name]
        if symmetry is not None and symmetry != own:
            raise ValueError(f"encoder {name!r} is {arch} with symmetry {own!r}, but symmetry {symmetry!r} was asked "
                             f"for: use encoder {arch!r} with symmetry {symmetry!r}, or leave the symmetry unset")
        return arch, own
    return name, symmetry or "none"


def encoder_options(name: str, symmetry: Optional[str] = None) -> dict:
    """Keyword options of encoder ``name`` (with ``symmetry``) and their defaults."""
    arch, symmetry = resolve(name, symmetry)
    cls = ARCHITECTURES[arch]
    params = list(inspect.signature(cls.__init__).parameters.values())[2:]  # skip self, layout
    options = {p.name: p.default for p in params if p.name != "symmetry"}
    if symmetry != "none" and not getattr(cls, "handles_symmetry", False):
        options["out_vectors"] = None
    return options


def make_encoder(name: str, layout: ObsLayout, symmetry: Optional[str] = None, size: str = "paper",
                 **kwargs) -> nn.Module:
    """Build encoder ``name`` for observations of ``layout``, equivariant to ``symmetry`` (None: the name's own),
    sized by the preset ``size``; ``kwargs`` override single options of the preset.

    The module maps ``obs [B, layout.dim]`` to ``[B, enc.out_dim]``; ``enc.equivariance`` is
    ``(num_scalars, num_vectors)`` of its typed output for a symmetry group, None without one.
    """
    arch, symmetry = resolve(name, symmetry)
    if size not in SIZE_PRESETS:
        raise ValueError(f"unknown size preset {size!r}; valid: {list(SIZES)}")
    if not isinstance(layout, ObsLayout):
        raise TypeError(f"layout must be a quad_env.obs_layout.ObsLayout, got {type(layout).__name__}")
    valid = encoder_options(name, symmetry)
    unknown = sorted(set(kwargs) - set(valid))
    if unknown:
        raise TypeError(f"encoder {name!r} (symmetry {symmetry!r}) got unknown option(s) {unknown}; "
                        f"valid: {sorted(valid)}")
    options = {**SIZE_PRESETS[size][arch], **kwargs}
    cls = ARCHITECTURES[arch]
    if getattr(cls, "handles_symmetry", False):
        return cls(layout, symmetry=symmetry, **options)
    wrapper = {k: options.pop(k) for k in WRAPPER_OPTIONS if k in options}
    inner = cls(layout, **options)
    return inner if symmetry == "none" else Canonicalized(inner, layout, symmetry, **wrapper)
