"""Building the actor-critic from config (a picklable factory, so Ray actors can build their copy)."""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Dict

import torch

import encoders
from quad_env import ObsLayout


def build_model(layout: Dict[str, Any], model: Dict[str, Any]) -> torch.nn.Module:
    """``model`` is the ``model`` section of the config as a plain dict (``ModelConfig`` fields are exactly the
    keyword arguments of ``encoders.ActorCritic``; keys missing in an older config keep their defaults)."""
    return encoders.ActorCritic(ObsLayout.from_dict(layout), **model)


def model_factory(layout: ObsLayout, model_cfg) -> Callable[[], torch.nn.Module]:
    """A zero-argument, picklable constructor of the configured actor-critic."""
    if model_cfg.encoder not in encoders.ENCODERS:
        raise ValueError(f"model.encoder: unknown encoder {model_cfg.encoder!r}; valid: {list(encoders.ENCODERS)}")
    return functools.partial(build_model, layout.to_dict(), dataclasses.asdict(model_cfg))
