"""Single-swarm adapters: a gymnasium-style env and a PettingZoo ``ParallelEnv``.

Both wrap ``VecQuadEnv`` with one swarm and no auto-reset: at the end of an episode (a truncation) the
returned observation is the true last one and ``reset()`` must be called. Arrays returned are copies.
"""
from __future__ import annotations

from typing import Any, Dict, Optional

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from quad_env.config import EnvConfig
from quad_env.vec_env import VecQuadEnv


class QuadSwarmEnv(gymnasium.Env):
    """One swarm of N drones, gymnasium style, with per-drone arrays.

    ``reset(seed=None) -> (obs [N, D], info)``;
    ``step(actions [N, 4]) -> (obs [N, D], rew [N], terminated [N], truncated [N], info)``.
    ``info["reward_terms"]`` maps each reward term to its [N] values; the step that ends the episode adds
    ``info["episode"]`` (the stats dict of ``VecQuadEnv.pop_episode_stats``).
    """

    metadata = {"render_modes": []}

    def __init__(self, cfg: Optional[EnvConfig] = None, seed: int = 0):
        self.cfg = cfg if cfg is not None else EnvConfig()
        self.vec = VecQuadEnv(self.cfg, num_envs=1, seed=seed, auto_reset=False)
        self.layout = self.vec.layout
        n, d = self.vec.num_agents, self.vec.obs_dim
        self.observation_space = spaces.Box(-np.inf, np.inf, (n, d), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (n, 4), np.float32)

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        obs = self.vec.reset(seed=seed)
        return obs.copy(), {"scenario": self.vec.scenario.episode_name(0)}

    def step(self, actions):
        obs, rew, terminated, truncated = self.vec.step(np.asarray(actions))
        info: Dict[str, Any] = {"reward_terms": {k: v.copy() for k, v in self.vec.reward_terms.items()}}
        if truncated.any():
            info["episode"] = self.vec.pop_episode_stats()[0]
        return obs.copy(), rew.copy(), terminated.copy(), truncated.copy(), info


class QuadSwarmParallelEnv(ParallelEnv):
    """PettingZoo parallel API over one swarm: agents ``drone_0`` ... ``drone_{N-1}``.

    Observation space per agent: ``Box(-inf, inf, (D,), float32)`` laid out by ``self.layout``;
    action space: ``Box(-1, 1, (4,), float32)``. All agents are truncated together at the episode end.
    """

    metadata = {"name": "quad_swarm_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, cfg: Optional[EnvConfig] = None, seed: int = 0):
        self.env = QuadSwarmEnv(cfg, seed=seed)
        self.layout = self.env.layout
        n = self.env.vec.num_agents
        self.possible_agents = [f"drone_{a}" for a in range(n)]
        self.agents = []
        self._obs_space = spaces.Box(-np.inf, np.inf, (self.env.vec.obs_dim,), np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (4,), np.float32)

    def observation_space(self, agent):
        return self._obs_space

    def action_space(self, agent):
        return self._act_space

    def reset(self, seed: Optional[int] = None, options: Optional[dict] = None):
        obs, info = self.env.reset(seed=seed)
        self.agents = list(self.possible_agents)
        return ({a: obs[k] for k, a in enumerate(self.agents)},
                {a: {"scenario": info["scenario"]} for a in self.agents})

    def step(self, actions: Dict[str, Any]):
        if not self.agents:
            raise RuntimeError("the episode is over: call reset()")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"missing actions for agents {missing}")
        batch = np.stack([np.asarray(actions[a], dtype=np.float32) for a in self.possible_agents])
        obs, rew, term, trunc, info = self.env.step(batch)
        agents = self.agents
        out = ({a: obs[k] for k, a in enumerate(agents)},
               {a: float(rew[k]) for k, a in enumerate(agents)},
               {a: bool(term[k]) for k, a in enumerate(agents)},
               {a: bool(trunc[k]) for k, a in enumerate(agents)},
               {a: {name: float(v[k]) for name, v in info["reward_terms"].items()} for k, a in enumerate(agents)})
        if term.any() or trunc.any():
            self.agents = []
        return out
