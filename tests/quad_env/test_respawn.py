"""The crash penalty and the respawn_on_floor training aid (both off in the paper's setting)."""
import numpy as np

from quad_env import REWARD_TERMS, VecQuadEnv
from quad_env.scenarios import SPAWN_HALF, SPAWN_MIN_SEP, SPAWN_MIN_Z

OFF = -np.ones((3, 4))  # motors off: a drone in the air falls


def dropping_env(quiet_cfg, **kw):
    """One swarm of 3 level drones at rest with motors off: drone 0 at 0.1 m (lands within a few steps),
    the others at 3 m (still falling after 0.2 s)."""
    cfg = quiet_cfg(num_agents=3, num_neighbors=2, drag_coeff=0.0, **kw)
    env = VecQuadEnv(cfg, num_envs=1, seed=3)
    env.set_state(pos=[[0, 0, 0.1], [1, 1, 3.0], [-1, 1, 3.0]], vel=np.zeros((3, 3)),
                  rot=np.tile(np.eye(3), (3, 1, 1)), omega=np.zeros((3, 3)), motor=np.zeros((3, 4)),
                  goal=[[0, 0, 2.0]] * 3)
    return env


def run(env, steps):
    """Per-step crash terms [steps, 3], positions [steps, 3, 3] and observations [steps, 3, D]."""
    crash, pos, obs = [], [], []
    for _ in range(steps):
        o, _, _, _ = env.step(OFF)
        crash.append(env.reward_terms["crash"].copy())
        pos.append(env.get_state().pos)
        obs.append(o.copy())
    return np.array(crash), np.array(pos), np.array(obs)


def test_defaults_keep_the_paper_setting(quiet_cfg):
    env = dropping_env(quiet_cfg)
    crash, pos, _ = run(env, 20)
    assert (crash == 0).all()
    assert np.allclose(pos[-1, 0, 2], 0.046)  # drone 0 lands and stays on the floor
    assert env.episode_stats(0)["respawns"] == 0


def test_crash_is_charged_once_per_landing_without_respawn(quiet_cfg):
    env = dropping_env(quiet_cfg, reward=dict(crash=3.0))
    crash, pos, _ = run(env, 20)
    assert crash[:, 0].tolist().count(-3.0) == 1 and crash[:, 0].sum() == -3.0  # once, though it rests there
    assert (crash[:, 1:] == 0).all()
    assert np.allclose(pos[-1, 0, 2], 0.046)
    stats = env.episode_stats(0)
    assert stats["rew_crash"] == -1.0  # -3 shared by 3 agents (per-agent mean)
    # (float32 per-step rewards)
    np.testing.assert_allclose(sum(stats[f"rew_{k}"] for k in REWARD_TERMS), stats["return"], rtol=1e-6)


def test_return_includes_the_crash_penalty(quiet_cfg):
    plain = dropping_env(quiet_cfg)
    charged = dropping_env(quiet_cfg, reward=dict(crash=3.0))
    run(plain, 20)
    run(charged, 20)
    a, b = plain.episode_stats(0), charged.episode_stats(0)
    np.testing.assert_allclose(b["return"], a["return"] - 1.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b["rew_crash"], -1.0)


def test_respawn_puts_the_drone_back_in_the_spawn_box(quiet_cfg):
    env = dropping_env(quiet_cfg, respawn_on_floor=True, reward=dict(crash=3.0))
    center = env._center[0].copy()  # the scenario's spawn centre of swarm 0
    landed_at = None
    for t in range(20):
        obs_now = env.step(OFF)[0].copy()
        if env.reward_terms["crash"][0] != 0:
            landed_at = t
            break
    assert landed_at is not None and env.reward_terms["crash"][0] == -3.0
    s = env.get_state()
    p = s.pos[0]
    assert (np.abs(p[:2] - center[:2]) <= SPAWN_HALF + 1e-12).all()
    assert max(center[2] - SPAWN_HALF, SPAWN_MIN_Z) <= p[2] <= center[2] + SPAWN_HALF
    assert np.linalg.norm(s.pos[1:] - p, axis=1).min() >= SPAWN_MIN_SEP
    assert (s.vel[0] == 0).all() and (s.omega[0] == 0).all() and (s.motor[0] == 0).all()
    np.testing.assert_allclose(s.rot[0][2], [0, 0, 1], atol=1e-12)  # level, random yaw
    # the step's observation already shows the respawned state (no sensor noise here)
    np.testing.assert_array_equal(obs_now, env.observe())
    np.testing.assert_allclose(obs_now[0, :3], p - [0, 0, 2.0], rtol=0, atol=1e-6)  # rel_goal = x - goal
    assert env.episode_stats(0)["respawns"] == 1
    # the other drones were not touched by the respawn: they are still falling from 3 m
    assert (s.pos[1:, 2] < 3.0).all() and (s.vel[1:, 2] < 0).all()


def test_respawn_is_reproducible_by_seed(quiet_cfg):
    cfg = quiet_cfg(num_agents=4, num_neighbors=3, respawn_on_floor=True, reward=dict(crash=1.0),
                    thrust_noise=True, sensor_noise=True)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, -0.5, (300, 8, 4))  # weak thrust: every drone crashes, some several times
    runs = []
    for _ in range(2):
        env = VecQuadEnv(cfg, num_envs=2, seed=11)
        trace = [env.step(a)[0].copy() for a in actions]
        runs.append((np.array(trace), env.episode_stats(0)["respawns"] + env.episode_stats(1)["respawns"]))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1] >= 8


def test_respawn_with_obstacles_is_refused_with_both_keys_named():
    import pytest

    from quad_env import EnvConfig
    with pytest.raises(ValueError, match="env.respawn_on_floor.*env.obstacles"):
        EnvConfig(respawn_on_floor=True, obstacles=True).validate()
