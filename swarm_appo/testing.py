"""Helpers for tests and benchmarks: an untrained policy saved exactly as the trainer saves a checkpoint."""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import torch

from swarm_appo.checkpoint import TrainingState
from swarm_appo.config import config_to_dict, load_config
from swarm_appo.model import model_factory


def untrained_checkpoint(root, name: str, overrides: Sequence[str] = (), encoder_kwargs: Optional[dict] = None,
                         seed: int = 0, agent_steps: int = 1000, config: Optional[str] = None) -> Path:
    """Build the model of ``load_config(config, overrides)`` (default: the quickstart config; ``key=value``
    overrides; ``encoder_kwargs`` replaces the encoder's options), initialised from ``seed``, and save it
    as ``root/name/checkpoints/ckpt_<agent_steps>.pt``. Returns the run directory ``root/name``."""
    cfg = load_config(config, [f"runner.name={name}", f"runner.seed={seed}", *overrides])
    if encoder_kwargs is not None:
        cfg.model.encoder_kwargs = dict(encoder_kwargs)
    torch.manual_seed(seed)
    model = model_factory(cfg.env.obs_layout(), cfg.model)()
    run_dir = Path(root) / name
    TrainingState(learner={"model": model.state_dict()}, agent_steps=agent_steps,
                  config=config_to_dict(cfg)).save(run_dir)
    return run_dir
