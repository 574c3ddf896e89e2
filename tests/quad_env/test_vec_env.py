"""VecQuadEnv: API contract, bad input, seeding, auto-reset, episode stats and the NaN policy."""
import numpy as np
import pytest

from quad_env import REWARD_TERMS, SCENARIOS, EnvConfig, VecQuadEnv


def rollout(env, steps, seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        obs, rew, term, trunc = env.step(scale * rng.uniform(-1, 1, (env.num_drones, 4)))
        out.append((obs.copy(), rew.copy(), term.copy(), trunc.copy(), env.final_obs.copy()))
    return out


def test_shapes_dtypes_and_attributes():
    cfg = EnvConfig(num_agents=4, num_neighbors=2)
    env = VecQuadEnv(cfg, num_envs=3, seed=1)
    assert (env.num_envs, env.num_agents, env.num_drones) == (3, 4, 12)
    assert env.obs_dim == env.layout.dim == 18 + 2 * 21 + 2
    assert env.layout.num_neighbors == 2 and env.layout.neighbor_obs == "full"
    obs = env.reset()
    assert obs.shape == (12, env.obs_dim) and obs.dtype == np.float32
    obs2, rew, term, trunc = env.step(np.zeros((12, 4), np.float32))
    assert obs2 is obs  # preallocated buffer, overwritten in place
    assert rew.shape == (12,) and rew.dtype == np.float32
    assert term.dtype == bool and trunc.dtype == bool and not term.any() and not trunc.any()
    assert env.final_obs.shape == (12, env.obs_dim) and env.final_obs.dtype == np.float32
    assert list(env.reward_terms) == list(REWARD_TERMS)
    np.testing.assert_allclose(sum(env.reward_terms.values()), rew, rtol=1e-5, atol=1e-7)
    assert "static_same_goal" in SCENARIOS and "static_diff_goal" in SCENARIOS


def test_step_before_reset_works():
    env = VecQuadEnv(EnvConfig(num_agents=2), num_envs=1, seed=0)
    obs, *_ = env.step(np.zeros((2, 4)))
    assert np.isfinite(obs).all()


def test_float64_int_and_non_contiguous_actions_accepted():
    """Each form steps exactly like its C-contiguous float64 copy."""
    a = np.random.default_rng(0).uniform(-1, 1, (4, 8))[:, ::2]  # non-contiguous float64
    obs = {}
    for name, first, second in (("views", a, np.zeros((4, 4), np.int64)),
                                ("copies", np.ascontiguousarray(a), np.zeros((4, 4), np.float64))):
        env = VecQuadEnv(EnvConfig(num_agents=2, thrust_noise=False, sensor_noise=False), num_envs=2, seed=0)
        env.step(first)
        obs[name] = env.step(second)[0].copy()
    np.testing.assert_array_equal(obs["views"], obs["copies"])


@pytest.mark.parametrize("bad,msg", [
    (np.zeros((5, 4)), "shape"),
    (np.zeros((4, 3)), "shape"),
    (np.zeros(16), "shape"),
    (np.array([[0, 0, np.nan, 0]] + [[0] * 4] * 3, float), "NaN"),
    (np.array([[0, 0, 0, np.inf]] + [[0] * 4] * 3, float), "NaN or inf"),
])
def test_bad_actions_raise(bad, msg):
    env = VecQuadEnv(EnvConfig(num_agents=2), num_envs=2, seed=0)
    with pytest.raises(ValueError, match=msg):
        env.step(bad)


def test_bad_config_raises_naming_the_key():
    with pytest.raises(ValueError, match="unknown scenario 'nope'; valid: .*static_diff_goal.*static_same_goal"):
        VecQuadEnv(EnvConfig(scenario="nope"), num_envs=1, seed=0)
    with pytest.raises(ValueError, match="env.num_agents"):
        VecQuadEnv(EnvConfig(num_agents=0), num_envs=1, seed=0)
    with pytest.raises(ValueError, match="env.num_neighbors"):
        VecQuadEnv(EnvConfig(num_neighbors=-1), num_envs=1, seed=0)
    with pytest.raises(ValueError, match="num_envs"):
        VecQuadEnv(EnvConfig(), num_envs=0, seed=0)
    with pytest.raises(ValueError, match="env.sim_dtype"):
        VecQuadEnv(EnvConfig(sim_dtype="float16"), num_envs=1, seed=0)
    with pytest.raises(ValueError, match="env.physics.mass"):
        VecQuadEnv(EnvConfig(physics=dict(mass=-1.0)), num_envs=1, seed=0)
    with pytest.raises(ValueError, match="seed"):
        VecQuadEnv(EnvConfig(), num_envs=1, seed=-3)


def test_same_seed_bit_identical_different_seed_differs():
    cfg = EnvConfig(num_agents=4, num_neighbors=3, episode_duration=0.5, scenario="static_diff_goal")
    a = rollout(VecQuadEnv(cfg, num_envs=3, seed=7), 120)  # crosses two auto-resets
    other = VecQuadEnv(cfg, num_envs=3, seed=123)  # another env in the same process must not interfere
    b_env = VecQuadEnv(cfg, num_envs=3, seed=7)
    b = []
    rng_b = np.random.default_rng(0)
    rng_o = np.random.default_rng(1)
    for _ in range(120):
        other.step(rng_o.uniform(-1, 1, (12, 4)))
        obs, rew, term, trunc = b_env.step(rng_b.uniform(-1, 1, (12, 4)))
        b.append((obs.copy(), rew.copy(), term.copy(), trunc.copy(), b_env.final_obs.copy()))
    for x, y in zip(a, b):
        for u, v in zip(x, y):
            np.testing.assert_array_equal(u, v)
    c = rollout(VecQuadEnv(cfg, num_envs=3, seed=8), 120)
    assert not np.array_equal(a[5][0], c[5][0])


def test_reset_with_seed_restarts_the_streams():
    env = VecQuadEnv(EnvConfig(num_agents=3), num_envs=2, seed=0)
    first = env.reset(seed=42).copy()
    rollout(env, 5)
    again = env.reset(seed=42).copy()
    np.testing.assert_array_equal(first, again)


def test_auto_reset_final_obs_and_episode_stats():
    cfg = EnvConfig(num_agents=3, num_neighbors=2, episode_duration=0.05)  # 5 control steps
    auto = VecQuadEnv(cfg, num_envs=2, seed=3)
    manual = VecQuadEnv(cfg, num_envs=2, seed=3, auto_reset=False)
    rng = np.random.default_rng(0)
    rew_sum = np.zeros(6)
    term_sums = {k: np.zeros(6) for k in REWARD_TERMS}
    for t in range(5):
        a = rng.uniform(-1, 1, (6, 4))
        obs, rew, term, trunc = auto.step(a)
        mobs, mrew, _, mtrunc = manual.step(a)
        rew_sum += rew
        for k in REWARD_TERMS:
            term_sums[k] += auto.reward_terms[k]
        np.testing.assert_array_equal(rew, mrew)
        if t < 4:
            assert not trunc.any() and not term.any()
    assert trunc.all() and not term.any() and mtrunc.all()
    np.testing.assert_array_equal(auto.final_obs, mobs)  # the true last observation
    assert not np.array_equal(obs, mobs)  # obs already starts the next episode
    dist = np.linalg.norm(manual.get_state().pos - manual.get_state().goal, axis=1)
    stats = auto.pop_episode_stats()
    assert len(stats) == 2 and auto.pop_episode_stats() == []
    for e, st in enumerate(stats):
        rows = slice(3 * e, 3 * e + 3)
        assert st["scenario"] == "static_same_goal" and st["length"] == 5 and st["diverged"] is False
        assert st["return"] == pytest.approx(rew_sum[rows].sum() / 3, rel=1e-5)
        for k in REWARD_TERMS:
            assert st[f"rew_{k}"] == pytest.approx(term_sums[k][rows].sum() / 3, rel=1e-5, abs=1e-9)
        assert sum(st[f"rew_{k}"] for k in REWARD_TERMS) == pytest.approx(st["return"], rel=1e-6)
        assert st["dist_final"] == pytest.approx(dist[rows].mean(), rel=1e-9)
        np.testing.assert_allclose(st["agent_dist_final"], dist[rows], rtol=1e-12)  # per drone, same state
        assert set(st) >= {"collisions", "room_contacts", "dist_last_5s"}
    with pytest.raises(RuntimeError, match="reset"):
        manual.step(np.zeros((6, 4)))
    _, _, _, trunc = auto.step(np.zeros((6, 4)))
    assert not trunc.any()  # a fresh episode


def test_dist_last_5s_is_the_mean_over_the_tail():
    cfg = EnvConfig(num_agents=2, num_neighbors=1, episode_duration=6.0)
    env = VecQuadEnv(cfg, num_envs=1, seed=0, auto_reset=False)  # keeps the final state readable
    rng = np.random.default_rng(0)
    dists = []
    for _ in range(600):
        env.step(rng.uniform(-1, 1, (2, 4)))
        s = env.get_state()
        dists.append(np.linalg.norm(s.pos - s.goal, axis=1).mean())
    st = env.pop_episode_stats()[0]
    assert st["length"] == 600
    assert st["dist_last_5s"] == pytest.approx(np.mean(dists[100:]), rel=1e-9)  # the last 500 steps
    assert abs(np.mean(dists) - np.mean(dists[100:])) > 1e-3  # (the window matters)
    assert st["dist_final"] == pytest.approx(dists[-1], rel=1e-12)


def test_room_contacts_and_collisions_counted_in_stats(quiet_cfg):
    cfg = quiet_cfg(num_agents=2, num_neighbors=1, episode_duration=0.3, drag_coeff=0.0)
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    hover = 1 / 1.9
    env.set_state(pos=[[0, 0, 5], [0.3, 0, 5]], vel=[[1.0, 0, 0], [-1.0, 0, 0]], rot=np.tile(np.eye(3), (2, 1, 1)),
                  omega=np.zeros((2, 3)), motor=np.full((2, 4), np.sqrt(hover)))
    for _ in range(30):
        env.step(np.full((2, 4), 2 * hover - 1))
    st = env.pop_episode_stats()[0]
    assert st["collisions"] == 1 and st["room_contacts"] == 0
    assert st["rew_collision"] == pytest.approx(-5.0)  # -5 for each of the two drones, mean per agent
    env.set_state(pos=[[0, 0, 0.5], [4.995, 0, 5]], vel=[[0, 0, -1.0], [2.0, 0, 0]], motor=np.zeros((2, 4)))
    for _ in range(30):
        env.step(-np.ones((2, 4)))
    st = env.pop_episode_stats()[0]
    assert st["room_contacts"] == 2  # one floor landing (stays down), one wall hit


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_nan_state_raises_by_default(dtype):
    env = VecQuadEnv(EnvConfig(num_agents=2, sim_dtype=dtype), num_envs=3, seed=0)
    env._vel[3, 1] = np.nan  # swarm 1 (set_state refuses NaN, so poke the buffer)
    with pytest.raises(FloatingPointError, match=r"swarms \[1\]"):
        env.step(np.zeros((6, 4)))
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((6, 4)))
    obs = env.reset()
    assert np.isfinite(obs).all()
    env.step(np.zeros((6, 4)))


def test_nan_state_resets_the_swarm_with_reset_policy():
    env = VecQuadEnv(EnvConfig(num_agents=2, nan_policy="reset"), num_envs=3, seed=0)
    env.step(np.zeros((6, 4)))
    before = env.step(np.zeros((6, 4)))[0].copy()
    env._omega[2, 0] = np.nan
    with pytest.warns(RuntimeWarning, match=r"swarms \[1\]"):
        obs, rew, term, trunc = env.step(np.zeros((6, 4)))
    assert trunc.tolist() == [False, False, True, True, False, False] and not term.any()
    assert np.all(rew[2:4] == 0) and np.isfinite(obs).all() and np.isfinite(rew).all()
    np.testing.assert_array_equal(env.final_obs[2:4], before[2:4])  # last finite observation
    stats = env.pop_episode_stats()
    assert len(stats) == 1 and stats[0]["diverged"] is True
    assert np.isfinite(env.get_state().pos).all()


def test_set_state_validates_its_input():
    env = VecQuadEnv(EnvConfig(num_agents=2), num_envs=1, seed=0)
    with pytest.raises(ValueError, match="pos must have shape"):
        env.set_state(pos=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        env.set_state(vel=np.full((2, 3), np.nan))
    with pytest.raises(ValueError, match="rotation"):
        env.set_state(rot=np.tile(np.diag([1.0, 1.0, -1.0]), (2, 1, 1)))
    with pytest.raises(ValueError, match="motor"):
        env.set_state(motor=np.full((2, 4), 1.5))
    state = env.get_state()
    state.pos[0] = 123.0  # a copy: the env is untouched
    assert env.get_state().pos[0, 0] != 123.0


def test_simulate_is_deterministic_and_matches_step_without_noise(quiet_cfg):
    cfg = quiet_cfg(num_agents=3, num_neighbors=2)
    a, b = VecQuadEnv(cfg, num_envs=2, seed=0), VecQuadEnv(cfg, num_envs=2, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        act = rng.uniform(-1, 1, (6, 4))
        s = a.simulate(act)
        b.step(act)
        np.testing.assert_array_equal(s.pos, b.get_state().pos)
    noisy = VecQuadEnv(EnvConfig(num_agents=3, num_neighbors=2), num_envs=2, seed=0)
    quiet = VecQuadEnv(EnvConfig(num_agents=3, num_neighbors=2), num_envs=2, seed=0)
    for _ in range(5):
        act = rng.uniform(-1, 1, (6, 4))
        noisy.step(act)
        quiet.simulate(act)
    assert not np.array_equal(noisy.get_state().vel, quiet.get_state().vel)  # thrust noise matters
