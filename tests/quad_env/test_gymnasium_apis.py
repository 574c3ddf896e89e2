"""The standard APIs, checked by the libraries' own checkers: gymnasium's check_env for one drone, gymnasium's
vector wrappers for a swarm."""
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.wrappers import RecordEpisodeStatistics
from gymnasium.wrappers.vector import RecordEpisodeStatistics as VectorRecordEpisodeStatistics

from quad_env import EnvConfig
from quad_env.adapters import QuadDroneEnv, QuadSwarmVectorEnv

SHORT = dict(episode_duration=0.2)  # 20 control steps


def test_one_drone_passes_gymnasiums_check_env():
    env = QuadDroneEnv(EnvConfig(num_agents=1, **SHORT))
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=3)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32
    obs2, rew, term, trunc, info = env.step(env.action_space.sample())
    assert isinstance(rew, float) and isinstance(term, bool) and isinstance(trunc, bool)


def test_one_drone_works_with_record_episode_statistics():
    env = RecordEpisodeStatistics(QuadDroneEnv(EnvConfig(num_agents=1, **SHORT)))
    env.reset(seed=0)
    total, steps = 0.0, 0
    while True:
        _, rew, term, trunc, info = env.step(np.zeros(4, np.float32))
        total, steps = total + rew, steps + 1
        if term or trunc:
            break
    assert steps == 20 and info["episode"]["l"] == 20 and info["episode"]["r"] == pytest.approx(total, rel=1e-6)
    assert "episode_stats" in info and info["episode_stats"]["length"] == 20


def test_a_swarm_is_refused_by_the_single_drone_env():
    with pytest.raises(ValueError, match="QuadSwarmVectorEnv"):
        QuadDroneEnv(EnvConfig(num_agents=4))


def test_swarm_vector_env_autoresets_in_the_same_step_and_reports_final_obs():
    env = QuadSwarmVectorEnv(EnvConfig(num_agents=3, **SHORT), num_swarms=2, seed=0)
    assert env.num_envs == 6 and env.observation_space.shape == (6, env.single_observation_space.shape[0])
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains(obs)
    for step in range(20):
        obs, rew, term, trunc, infos = env.step(np.zeros((6, 4), np.float32))
        assert rew.shape == (6,) and term.dtype == bool
    assert trunc.all() and infos["_final_obs"].all()  # step 20 ended every episode
    assert not np.array_equal(infos["final_obs"][0], obs[0])  # obs is already the next episode's first one
    assert len(infos["episode_stats"]) == 2
    obs, _, _, trunc, infos = env.step(np.zeros((6, 4), np.float32))
    assert not trunc.any() and "final_obs" not in infos


def test_swarm_vector_env_works_with_gymnasiums_vector_wrapper():
    env = VectorRecordEpisodeStatistics(QuadSwarmVectorEnv(EnvConfig(num_agents=2, **SHORT), num_swarms=1))
    env.reset(seed=0)
    for _ in range(20):
        _, _, _, _, infos = env.step(np.zeros((2, 4), np.float32))
    assert infos["_episode"].all() and np.all(infos["episode"]["l"] == 20)
