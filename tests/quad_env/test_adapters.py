"""The gymnasium-style single-swarm env and the PettingZoo ParallelEnv adapter."""
import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from quad_env import REWARD_TERMS, EnvConfig
from quad_env.adapters import QuadSwarmEnv, QuadSwarmParallelEnv


def test_gym_style_env_episode():
    cfg = EnvConfig(num_agents=3, num_neighbors=2, episode_duration=0.1)  # 10 steps
    env = QuadSwarmEnv(cfg, seed=0)
    obs, info = env.reset(seed=4)
    assert obs.shape == (3, env.layout.dim) and obs.dtype == np.float32 and info["scenario"] == "static_same_goal"
    assert env.observation_space.contains(obs)
    for t in range(10):
        obs, rew, term, trunc, info = env.step(env.action_space.sample())
        assert rew.shape == (3,) and term.shape == (3,) and trunc.shape == (3,)
        np.testing.assert_allclose(sum(info["reward_terms"].values()), rew, rtol=1e-5, atol=1e-7)
        assert trunc.all() == (t == 9) and not term.any()
    assert info["episode"]["length"] == 10
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((3, 4)))
    first, _ = env.reset(seed=4)
    again, _ = QuadSwarmEnv(cfg, seed=99).reset(seed=4)
    np.testing.assert_array_equal(first, again)  # reset(seed=) fixes the episode


def test_gym_env_returns_copies():
    env = QuadSwarmEnv(EnvConfig(num_agents=2), seed=0)
    obs, _ = env.reset()
    obs2, *_ = env.step(np.zeros((2, 4)))
    assert not np.shares_memory(obs, obs2)


def test_pettingzoo_parallel_api():
    env = QuadSwarmParallelEnv(EnvConfig(num_agents=3, num_neighbors=2, episode_duration=0.2), seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the API test reports problems as warnings
        parallel_api_test(env, num_cycles=50)


def test_pettingzoo_agents_and_truncation():
    env = QuadSwarmParallelEnv(EnvConfig(num_agents=2, episode_duration=0.02), seed=0)
    obs, infos = env.reset(seed=1)
    assert env.agents == ["drone_0", "drone_1"] and set(obs) == set(env.agents)
    assert env.observation_space("drone_0").shape == (env.layout.dim,)
    with pytest.raises(ValueError, match="missing actions"):
        env.step({"drone_0": np.zeros(4)})
    env.step({a: np.zeros(4) for a in env.agents})
    _, rew, term, trunc, info = env.step({a: np.zeros(4) for a in env.agents})
    assert all(trunc.values()) and not any(term.values()) and env.agents == []
    assert set(info["drone_0"]) == set(REWARD_TERMS)
