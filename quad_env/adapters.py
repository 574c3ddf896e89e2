"""Adapters to the standard APIs, each for the shape it fits:

- ``QuadDroneEnv``: one drone, a ``gymnasium.Env`` (passes gymnasium's ``check_env``);
- ``QuadSwarmVectorEnv``: a swarm (or several), a ``gymnasium.vector.VectorEnv`` with one slot per drone;
- ``QuadSwarmParallelEnv``: a swarm, a PettingZoo ``ParallelEnv`` (passes ``parallel_api_test``);
- ``QuadSwarmEnv``: a swarm with per-drone arrays, gymnasium *style* (arrays where gymnasium expects scalars; the
  base of the PettingZoo adapter).

All but the vector env wrap ``VecQuadEnv`` with one swarm and no auto-reset: at the end of an episode (a
truncation) the returned observation is the true last one and ``reset()`` must be called. Arrays returned are copies.
"""
from __future__ import annotations

from typing import Any, Dict, Optional

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from quad_env.actions import check_actions
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
        n = self.vec.num_agents
        obs, rew, terminated, truncated = self.vec.step(check_actions(actions, (n, 4), f"actions (one row of 4 per "
                                                                                      f"drone, {n} drones)"))
        info: Dict[str, Any] = {"reward_terms": {k: v.copy() for k, v in self.vec.reward_terms.items()}}
        if truncated.any():
            info["episode"] = self.vec.pop_episode_stats()[0]
        return obs.copy(), rew.copy(), terminated.copy(), truncated.copy(), info


class QuadDroneEnv(gymnasium.Env):
    """One drone (a swarm of N = 1), as gymnasium defines an environment: ``obs [D]``, ``action [4]``, a float
    reward and bool terminated / truncated. Passes ``gymnasium.utils.env_checker.check_env``; the episode stats
    come in ``info["episode_stats"]`` at the last step. ``env.num_agents`` must be 1 (a swarm is a vector env:
    ``QuadSwarmVectorEnv``)."""

    metadata = {"render_modes": []}

    def __init__(self, cfg: Optional[EnvConfig] = None, seed: int = 0):
        cfg = cfg if cfg is not None else EnvConfig(num_agents=1)
        if cfg.num_agents != 1:
            raise ValueError(f"QuadDroneEnv flies one drone, got env.num_agents={cfg.num_agents}; for a swarm use "
                             "QuadSwarmVectorEnv (one slot per drone) or QuadSwarmParallelEnv (PettingZoo)")
        self.env = QuadSwarmEnv(cfg, seed=seed)
        self.layout = self.env.layout
        self.observation_space = spaces.Box(-np.inf, np.inf, (self.env.vec.obs_dim,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed)
        return obs[0], info

    def step(self, action):
        obs, rew, term, trunc, info = self.env.step(check_actions(action, (4,), "action").reshape(1, 4))
        info = {"reward_terms": {k: float(v[0]) for k, v in info["reward_terms"].items()},
                **({"episode_stats": info["episode"]} if "episode" in info else {})}
        return obs[0], float(rew[0]), bool(term[0]), bool(trunc[0]), info


class QuadSwarmVectorEnv(gymnasium.vector.VectorEnv):
    """E swarms of N drones as a gymnasium ``VectorEnv`` with one slot per drone (``num_envs = E * N``; drone a of
    swarm e is slot ``e * N + a``), auto-reset in the same step (``AutoresetMode.SAME_STEP``): when a swarm's
    episode ends, its slots return the first observation of the next episode, and ``infos["final_obs"]`` (with
    the mask ``infos["_final_obs"]``) holds the true last ones. Works with gymnasium's vector wrappers (e.g.
    ``gymnasium.wrappers.vector.RecordEpisodeStatistics``)."""

    metadata = {"render_modes": [], "autoreset_mode": gymnasium.vector.AutoresetMode.SAME_STEP}

    def __init__(self, cfg: Optional[EnvConfig] = None, num_swarms: int = 1, seed: int = 0):
        self.cfg = cfg if cfg is not None else EnvConfig()
        self.vec = VecQuadEnv(self.cfg, num_envs=num_swarms, seed=seed, auto_reset=True)
        self.layout = self.vec.layout
        self.num_envs = num_swarms * self.vec.num_agents
        self.single_observation_space = spaces.Box(-np.inf, np.inf, (self.vec.obs_dim,), np.float32)
        self.single_action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, self.num_envs)

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        obs = self.vec.reset(seed=seed)
        return obs.copy(), {}

    def step(self, actions):
        obs, rew, term, trunc = self.vec.step(check_actions(actions, (self.num_envs, 4),
                                                            f"actions (one row of 4 per slot, {self.num_envs} slots)"))
        infos: Dict[str, Any] = {}
        done = term | trunc
        if done.any():
            final = np.empty(self.num_envs, dtype=object)
            for k in np.flatnonzero(done):
                final[k] = self.vec.final_obs[k].copy()
            infos["final_obs"], infos["_final_obs"] = final, done.copy()
            infos["episode_stats"] = self.vec.pop_episode_stats()  # one dict per swarm that ended
        return obs.copy(), rew.astype(np.float64), term.copy(), trunc.copy(), infos


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
        unknown = [a for a in actions if a not in self.agents]
        if unknown:
            raise ValueError(f"actions for unknown agents {unknown}; the agents are {self.agents}")
        batch = np.stack([check_actions(actions[a], (4,), f"action of {a!r}").astype(np.float64, copy=False)
                          for a in self.possible_agents])
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
