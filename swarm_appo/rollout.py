"""Sampling: a rollout worker steps E swarms with a CPU copy of the policy and emits fragments.

The same ``RolloutWorker`` runs in-process (serial mode) and inside a Ray actor (``RayRolloutWorker``),
so both modes produce identical fragments for the same seed.

Fragment layout (time-major, B = E * N drone trajectories, T = ``algo.rollout``)::

    obs            float32 [T, B, D]   observation the action was taken from
    actions        float32 [T, B, A]   unclipped Gaussian sample (the env clips to [-1, 1])
    log_probs      float32 [T, B]      behaviour log-prob of ``actions``
    values         float32 [T, B]      behaviour-time value estimate (for value clipping; zeros when
                                       ``store_values`` is off, which skips the critic while acting)
    rewards        float32 [T, B]
    terminated     bool    [T, B]      true end of an episode (zero discount); never set by this env
    truncated      bool    [T, B]      time limit: bootstrap from ``final_obs``
    final_obs      float32 [M, D]      the true last observation of each truncated step ...
    final_idx      int64   [M, 2]      ... at (t, b) (sparse: truncation is rare)
    last_obs       float32 [B, D]      observation after step T-1 (bootstrap for the fragment tail)
    rnn_state      float32 [B, S]      recurrent core state before step 0 (zeros at an episode start; S = 0
                                       feed-forward): the learner unrolls each trajectory from it
    policy_version int64   [T]         version of the weights that acted at step t
    num_agents     int                 drones per swarm N: columns e*N .. e*N+N-1 are swarm e (a central
                                       critic reads each drone's swarm from the fragment's own observations)
    episode_stats  list[dict]          swarm episodes that ended inside this fragment
    worker_id, env_time_s, inference_time_s, num_agent_steps
"""
from __future__ import annotations

import os
import time
from typing import Any, Dict, Optional, Tuple

import numpy as np
import torch

from encoders import swarm_observations
from quad_env import EnvConfig, VecQuadEnv
from swarm_appo.precision import autocast, resolve_precision


def worker_seed(base_seed: int, worker_index: int, incarnation: int = 0) -> int:
    """Distinct, reproducible seeds per worker (and per restart of a worker)."""
    return int(np.random.SeedSequence([base_seed, worker_index, incarnation]).generate_state(1)[0])


class RolloutWorker:
    """Owns ``num_envs`` swarms and a policy copy; ``collect()`` returns one fragment."""

    def __init__(self, env_cfg: EnvConfig, model_factory, num_envs: int, rollout: int, seed: int,
                 worker_id: int = 0, store_values: bool = False, precision: str = "fp32"):
        torch.set_num_threads(1)  # one core per worker: batched inference is small, threads only contend
        self.worker_id = worker_id
        self.rollout = rollout
        self.store_values = store_values
        self.env = VecQuadEnv(env_cfg, num_envs=num_envs, seed=seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.model = model_factory()
        self.model.eval()
        # runner.inference_precision, "auto" resolved on this worker's own CPU (cluster nodes may differ)
        self.precision, _ = resolve_precision(precision, torch.device("cpu"), self.model.config["size"])
        self.policy_version = -1
        self.obs = self.env.reset().copy()  # [B, D]
        B, D = self.env.num_drones, self.env.obs_dim
        self.state = self.model.initial_state(B)  # [B, S] core state, carried across fragments
        A = 4
        T = rollout
        # Preallocated fragment buffers; a fragment is a fresh copy of these (it leaves the process).
        self._buf = dict(
            obs=np.zeros((T, B, D), np.float32), actions=np.zeros((T, B, A), np.float32),
            log_probs=np.zeros((T, B), np.float32), values=np.zeros((T, B), np.float32),
            rewards=np.zeros((T, B), np.float32),
            terminated=np.zeros((T, B), bool), truncated=np.zeros((T, B), bool),
        )

    def pid(self) -> int:
        return os.getpid()

    # ------------------------------------------------------------------ weights
    def set_weights(self, version: int, state_dict: Dict[str, torch.Tensor],
                    env_schedule: Optional[Dict[str, float]] = None) -> None:
        """Load a published policy version; ``env_schedule`` (published with it) sets the training schedule's
        environment values, e.g. ``{"collision_scale": 0.3}`` (``env.reward.collision_anneal_steps``)."""
        self.model.load_state_dict(state_dict)
        self.policy_version = version
        if env_schedule and "collision_scale" in env_schedule:
            self.env.set_collision_scale(env_schedule["collision_scale"])

    # ------------------------------------------------------------------ sampling
    @torch.no_grad()
    def collect(self) -> Dict[str, Any]:
        buf, T = self._buf, self.rollout
        final_obs, final_idx, episode_stats = [], [], []
        env_time = inference_time = 0.0
        rnn_state = self.state.numpy().astype(np.float32)  # [B, S] before step 0
        for t in range(T):
            t0 = time.perf_counter()
            obs_t = torch.from_numpy(self.obs)
            actions, log_probs, values = self._sample(obs_t)  # [B, A], [B], [B]
            t1 = time.perf_counter()
            buf["obs"][t] = self.obs
            buf["actions"][t] = actions
            buf["log_probs"][t] = log_probs
            buf["values"][t] = values
            obs, rew, term, trunc = self.env.step(actions)
            buf["rewards"][t] = rew
            buf["terminated"][t] = term
            buf["truncated"][t] = trunc
            done = np.flatnonzero(term | trunc)
            if done.size:
                self.state[torch.from_numpy(done)] = 0.0  # a new episode starts with a fresh core state
                final_obs.append(self.env.final_obs[done].copy())
                final_idx.append(np.stack([np.full_like(done, t), done], axis=1))
                episode_stats.extend(self.env.pop_episode_stats())
            self.obs = obs.copy()
            t2 = time.perf_counter()
            inference_time += t1 - t0
            env_time += t2 - t1
        D = self.env.obs_dim
        return dict(
            {k: v.copy() for k, v in buf.items()},
            final_obs=np.concatenate(final_obs) if final_obs else np.zeros((0, D), np.float32),
            final_idx=np.concatenate(final_idx).astype(np.int64) if final_idx else np.zeros((0, 2), np.int64),
            last_obs=self.obs.copy(),
            rnn_state=rnn_state,
            policy_version=np.full(T, self.policy_version, np.int64),
            num_agents=self.env.num_agents,
            collision_scale=self.env.collision_scale,  # the training schedule's value it was collected with
            episode_stats=episode_stats,
            worker_id=self.worker_id,
            env_time_s=env_time,
            inference_time_s=inference_time,
            num_agent_steps=T * self.env.num_drones,
        )

    def _sample(self, obs: torch.Tensor) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        # the critic runs only when behaviour values are stored (value clipping): about half the inference cost
        swarm = swarm_observations(obs, self.env.num_agents) if self.store_values and self.model.central else None
        with autocast(self.precision, obs.device):  # the model returns fp32 means and values either way
            actions, log_probs, values, self.state = self.model.act(
                obs, generator=self.generator, with_value=self.store_values, swarm_obs=swarm, state=self.state)
        return actions.numpy(), log_probs.numpy(), values.numpy()

    def collect_with_weights(self, weights: Optional[Tuple]) -> Dict[str, Any]:
        """Pick up newer weights (if given) between fragments, then sample one fragment."""
        if weights is not None and weights[0] != self.policy_version:
            self.set_weights(*weights)
        return self.collect()
