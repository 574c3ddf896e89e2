"""Exponential moving averages of the policy's weights over agent steps (``algo.weight_ema``).

Late in a run the critic explains little, and Adam's normalised steps make the weights wander about a good policy
(benchmarks/RESULTS.md, "one hour in serial mode with checkpoint selection"): the mean of the last few checkpoints
flew better than any one of them. An EMA is the same idea at the resolution of every learner batch. It is a pure
read-out: training, the published weights and the run's transitions are the same with or without it.

Each average weighs the weights after the k-th batch by ``exp(-(S - s_k) / H)``, where ``s_k`` is the agent step of
that batch, ``S`` the current step and ``H`` the horizon in agent steps, normalised by the sum of those weights (so
no bias toward the initial weights, and the same meaning for any batch size). Only parameters are averaged; the
observation statistics and other buffers of an averaged policy are the live model's.
"""
from __future__ import annotations

import math
from typing import Dict, List, Sequence

import torch

STATE_KEY = "weight_ema"  # key of the averages in Learner.state_dict() (checkpoint payload "learner")


class WeightEMA:
    """One running average per horizon (agent steps) of ``model``'s parameters, kept on the parameters' device."""

    def __init__(self, model: torch.nn.Module, horizons: Sequence[float]):
        self.horizons = [float(h) for h in horizons]
        if not self.horizons or any(not h > 0 for h in self.horizons):
            raise ValueError(f"weight EMA horizons must be > 0 agent steps, got {list(horizons)}")
        self.names = [name for name, _ in model.named_parameters()]
        self.averages: List[Dict[str, torch.Tensor]] = [
            {n: p.detach().clone() for n, p in model.named_parameters()} for _ in self.horizons]
        self.norms = [0.0] * len(self.horizons)  # sum of the weights so far (0: nothing averaged yet)

    def update(self, model: torch.nn.Module, agent_steps: int) -> None:
        """Fold in the weights after a batch of ``agent_steps`` samples."""
        params = dict(model.named_parameters())
        live = [params[n].detach() for n in self.names]
        for i, h in enumerate(self.horizons):
            decay = math.exp(-float(agent_steps) / h)
            self.norms[i] = decay * self.norms[i] + (1.0 - decay)
            weight = (1.0 - decay) / self.norms[i]  # 1 on the first update: the average starts at the weights
            avg = [self.averages[i][n] for n in self.names]
            torch._foreach_lerp_(avg, live, weight)

    def state_dict(self) -> Dict:
        return {"horizons": list(self.horizons), "norms": list(self.norms),
                "averages": [dict(a) for a in self.averages]}

    def load_state_dict(self, state: Dict) -> None:
        if [float(h) for h in state["horizons"]] != self.horizons:
            raise ValueError(f"weight EMA horizons differ: checkpoint {state['horizons']}, config {self.horizons}")
        for avg, saved in zip(self.averages, state["averages"]):
            missing = set(avg) - set(saved)
            if missing:
                raise ValueError(f"weight EMA state lacks parameters {sorted(missing)[:3]}")
            for n in avg:
                avg[n].copy_(saved[n])
        self.norms = [float(z) for z in state["norms"]]


def averaged_model_state(model_state: Dict[str, torch.Tensor], ema_state: Dict, index: int) -> Dict:
    """A policy's state dict with average ``index`` of a saved ``WeightEMA.state_dict()`` as its parameters and
    everything else (buffers: observation statistics) from ``model_state``."""
    if not 0 <= index < len(ema_state["horizons"]):
        raise IndexError(f"weight EMA index {index} out of range: horizons {ema_state['horizons']}")
    out = dict(model_state)
    for name, value in ema_state["averages"][index].items():
        if name not in out:
            raise KeyError(f"weight EMA parameter {name!r} is not in the model's state dict")
        out[name] = value.to(device=out[name].device, dtype=out[name].dtype)
    return out
