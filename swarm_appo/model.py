"""Building the actor-critic from config (a picklable factory, so Ray actors can build their copy)."""
from __future__ import annotations

import functools
from typing import Any, Callable, Dict

import torch

import encoders
from quad_env import ObsLayout


def build_model(layout: Dict[str, Any], model: Dict[str, Any]) -> torch.nn.Module:
    """``model`` is the ``model`` section of the config as a plain dict."""
    return encoders.ActorCritic(ObsLayout.from_dict(layout), encoder=model["encoder"],
                                encoder_kwargs=dict(model["encoder_kwargs"] or {}),
                                share_encoder=bool(model["share_encoder"]), head_hidden=model["head_hidden"],
                                head_activation=model["head_activation"], init_log_std=model["init_log_std"],
                                normalize_obs=bool(model.get("normalize_obs", False)),
                                init_action_mean=float(model.get("init_action_mean", 0.0)),
                                init_actor_out_scale=float(model.get("init_actor_out_scale", 1.0)),
                                body_frame_obs=bool(model.get("body_frame_obs", False)))


def model_factory(layout: ObsLayout, model_cfg) -> Callable[[], torch.nn.Module]:
    """A zero-argument, picklable constructor of the configured actor-critic."""
    if model_cfg.encoder not in encoders.ENCODERS:
        raise ValueError(f"model.encoder: unknown encoder {model_cfg.encoder!r}; valid: {list(encoders.ENCODERS)}")
    fields = ("encoder", "encoder_kwargs", "share_encoder", "head_hidden", "head_activation", "init_log_std",
              "normalize_obs", "init_action_mean", "init_actor_out_scale",
              "body_frame_obs")
    return functools.partial(build_model, layout.to_dict(), {k: getattr(model_cfg, k) for k in fields})
