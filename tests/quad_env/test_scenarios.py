"""Scenario registry, goal formations and spawning."""
import numpy as np
import pytest

from quad_env import SCENARIOS, EnvConfig, VecQuadEnv, make_scenario, register_scenario
from quad_env.scenarios import Scenario, formation_offsets


# the paper's scenarios and this project's obstacle and "mix" ones; the registry may grow, never lose one
EXPECTED = ("static_same_goal", "static_diff_goal", "dynamic_same_goal", "dynamic_diff_goal", "ep_lissajous3D",
       "ep_rand_bezier", "swarm_vs_swarm", "swap_goals", "dynamic_formations", "o_random", "o_static_same_goal", "mix")


def test_registry_lists_the_scenarios_and_rejects_unknown_names():
    assert set(EXPECTED) <= set(SCENARIOS) and len(set(SCENARIOS)) == len(SCENARIOS)
    unknown = r"unknown scenario 'swarm_vs'; valid: \['dynamic_diff_goal', .*'swarm_vs_swarm'\]"
    with pytest.raises(ValueError, match=unknown):
        make_scenario("swarm_vs", EnvConfig())
    with pytest.raises(ValueError, match="already registered"):
        @register_scenario
        class Again(Scenario):
            name = "static_same_goal"


def test_static_same_goal_shares_one_fixed_goal():
    env = VecQuadEnv(EnvConfig(num_agents=5, scenario="static_same_goal"), num_envs=3, seed=0)
    goals = env.get_state().goal
    np.testing.assert_array_equal(goals, np.tile([0.0, 0.0, 2.0], (15, 1)))
    rng = np.random.default_rng(0)
    for _ in range(3):
        env.step(rng.uniform(-1, 1, (15, 4)))
    np.testing.assert_array_equal(env.get_state().goal, goals)  # static


@pytest.mark.parametrize("n", [1, 2, 8, 33, 128])
def test_static_diff_goal_formation_spacing(n):
    env = VecQuadEnv(EnvConfig(num_agents=n, scenario="static_diff_goal"), num_envs=4, seed=1)
    goals = env.get_state().goal.reshape(4, n, 3)
    for g in goals:
        np.testing.assert_allclose(g.mean(0)[2], 2.0)
        assert np.abs(g.mean(0)[:2]).max() < 0.5  # centred near (0, 0) (a partial last grid row shifts it)
        if n >= 2:
            d = np.linalg.norm(g[:, None] - g[None], axis=-1) + np.eye(n) * 1e9
            nearest = d.min(1)
            assert nearest.min() >= 0.25 - 1e-9 and nearest.max() <= 0.5 + 1e-9
        assert (np.abs(g[:, :2]) < 4.0).all()  # inside the room
    if n >= 2:
        assert len({tuple(np.round(g[1] - g[0], 6)) for g in goals}) > 1  # formations vary between episodes


def test_formation_offsets_circle_and_grid():
    out = np.zeros((6, 3))
    formation_offsets(0, 6, 0.5, out)  # circle: neighbours 0.5 apart on a radius-0.5 hexagon
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 0.5)
    np.testing.assert_allclose(np.linalg.norm(out[1] - out[0]), 0.5)
    formation_offsets(1, 6, 0.3, out)  # grid 3 x 2
    np.testing.assert_allclose(sorted(set(np.round(out[:, 0], 9))), [-0.3, 0.0, 0.3])
    np.testing.assert_allclose(sorted(set(np.round(out[:, 1], 9))), [-0.15, 0.15])
    big = np.zeros((128, 3))
    formation_offsets(0, 128, 0.25, big)  # a circle of 128 would be 5 m wide: falls back to the grid
    assert np.abs(big).max() < 2.0


@pytest.mark.parametrize("scenario", ["static_same_goal", "static_diff_goal"])
def test_spawn_around_the_centre_at_rest_motors_off_random_yaw(scenario):
    n, e = 32, 4
    env = VecQuadEnv(EnvConfig(num_agents=n, scenario=scenario), num_envs=e, seed=2)
    s = env.get_state()
    assert (np.abs(s.pos[:, :2]) <= 2.0).all() and (s.pos[:, 2] >= 0.75).all() and (s.pos[:, 2] <= 4.0).all()
    assert s.pos[:, 2].std() > 0.5
    for p in s.pos.reshape(e, n, 3):
        d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(n) * 1e9
        assert d.min() >= 0.3
    assert np.all(s.vel == 0) and np.all(s.omega == 0) and np.all(s.motor == 0)
    np.testing.assert_allclose(s.rot[:, 2], np.tile([0, 0, 1.0], (n * e, 1)), atol=1e-12)  # level
    yaw = np.arctan2(s.rot[:, 1, 0], s.rot[:, 0, 0])
    assert yaw.std() > 1.0  # spread over the circle


def test_swarms_get_different_spawns():
    env = VecQuadEnv(EnvConfig(num_agents=4), num_envs=2, seed=0)
    p = env.get_state().pos
    assert not np.allclose(p[:4], p[4:])
