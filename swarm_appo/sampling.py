"""Samplers: where fragments come from. Serial (in-process, deterministic) or Ray actors (asynchronous).

Both expose the same three calls, so the training loop does not know which one it drives:

    sampler.publish(version, state_dict, env_schedule)   # newest weights; workers pick them up between fragments
    sampler.get() -> fragment              # blocks until one fragment is ready
    sampler.close()

The serial sampler lives here; the Ray one (``swarm_appo.ray_sampling``) is imported only by runs that use
it, so an in-process run (``runner.serial``) needs no Ray installed (e.g. a GPU box with torch alone).
"""
from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Tuple

import numpy as np
import torch

from quad_env import EnvConfig
from swarm_appo.rollout import RolloutWorker, worker_seed

Weights = Tuple[int, Dict[str, torch.Tensor], Optional[Dict[str, float]]]  # version, state dict, env schedule


def fragment_nbytes(fragment: Dict[str, Any]) -> int:
    """Bytes of a fragment's arrays (what moves between nodes, give or take the small episode records)."""
    return sum(v.nbytes for v in fragment.values() if isinstance(v, np.ndarray))


class SerialSampler:
    """Round-robin over in-process workers; every fragment uses the newest weights (lag 0)."""

    def __init__(self, env_cfg: EnvConfig, model_factory: Callable, num_workers: int, envs_per_worker: int,
                 rollout: int, seed: int, store_values: bool = False, precision: str = "fp32"):
        self.workers = [RolloutWorker(env_cfg, model_factory, envs_per_worker, rollout,
                                      worker_seed(seed, i), worker_id=i, store_values=store_values,
                                      precision=precision)
                        for i in range(num_workers)]
        self._next = 0
        self._weights: Optional[Weights] = None
        self.restarts = 0
        self.stalls = 0

    def publish(self, version: int, state_dict: Dict[str, torch.Tensor],
                env_schedule: Optional[Dict[str, float]] = None) -> None:
        self._weights = (version, state_dict, env_schedule)

    def get(self) -> Dict[str, Any]:
        worker = self.workers[self._next]
        self._next = (self._next + 1) % len(self.workers)
        return worker.collect_with_weights(self._weights)

    def close(self) -> None:
        self.workers.clear()
