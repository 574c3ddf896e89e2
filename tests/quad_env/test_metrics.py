"""Episode metrics (the paper's Table 1 columns) on hand-built trajectories.

Drones hover in place (all noise off, hover thrust) and ``set_state`` puts them where a case needs them;
``simulate`` steps the episode clock. The last-N-seconds distances are checked against a float64 numpy
recomputation of a random-action episode.
"""
import numpy as np

from quad_env import VecQuadEnv
from quad_env.kernels import SUCCESS_RADIUS, SUCCESS_WINDOW

GRACE = 150  # 1.5 s of 0.01 s control steps


def hold(env, steps, goal=None, pos=None, vel=None):
    """``steps`` control steps of hovering; ``pos``/``goal``/``vel`` are re-imposed before each step."""
    for _ in range(steps):
        if pos is not None or goal is not None or vel is not None:
            env.set_state(pos=pos, goal=goal, vel=vel)
        env.simulate(env.hover_action)


def test_success_needs_a_full_window_below_half_a_metre(hover_env):
    env = hover_env(n=3)
    pos = env.get_state().pos
    goal = pos + np.array([[0.4, 0, 0], [0.6, 0, 0], [0.0, 0.0, 0.45]])  # within, outside, within
    hold(env, SUCCESS_WINDOW - 1, goal=goal, pos=pos)
    s = env.episode_stats(0)
    np.testing.assert_array_equal(s["agent_success"], [False, False, False])  # window not yet full
    hold(env, 1, goal=goal, pos=pos)
    s = env.episode_stats(0)
    np.testing.assert_array_equal(s["agent_success"], [True, False, True])
    np.testing.assert_allclose(s["success_rate"], 2 / 3)
    # once reached, moving away later does not undo it (reached "at some time after the last goal change")
    hold(env, 10, goal=pos + 3.0, pos=pos)
    np.testing.assert_array_equal(env.episode_stats(0)["agent_success"], [True, False, True])


def test_success_is_a_windowed_mean(hover_env):
    env = hover_env(n=1)
    pos = env.get_state().pos
    dists = [0.9, 0.3, 0.3, 0.3, 0.3]  # mean 0.42 < 0.5 although the first step is far
    for d in dists:
        env.set_state(pos=pos, goal=pos + [[d, 0, 0]])
        env.simulate(env.hover_action)
    assert np.mean(dists) < SUCCESS_RADIUS and env.episode_stats(0)["success_rate"] == 1.0
    env2 = hover_env(n=1)
    for d in [1.5, 0.3, 0.3, 0.3, 0.3]:  # mean 0.54: not reached
        env2.set_state(pos=pos, goal=pos + [[d, 0, 0]])
        env2.simulate(env2.hover_action)
    assert env2.episode_stats(0)["success_rate"] == 0.0


def test_a_goal_jump_restarts_the_success_window(hover_env):
    env = hover_env(n=2)
    pos = env.get_state().pos
    hold(env, 8, goal=pos, pos=pos)
    assert env.episode_stats(0)["success_rate"] == 1.0
    env.scenario.jumped[0] = 1  # what a dynamic scenario sets when the goals jump
    hold(env, 3, goal=pos, pos=pos)
    assert env.episode_stats(0)["success_rate"] == 0.0  # reached must be earned again after the jump ...
    assert env.scenario.jumped[0] == 0  # ... the flag is consumed
    hold(env, 2, goal=pos, pos=pos)
    assert env.episode_stats(0)["success_rate"] == 1.0  # ... 5 steps after it


def approach(env, a, b):
    """Put drone b 0.1 m beside drone a (just apart) flying into it at 2 m/s: they touch in one step."""
    s = env.get_state()
    pos, vel = s.pos.copy(), np.zeros_like(s.vel)
    pos[b] = pos[a] + [0.1, 0.0, 0.0]
    vel[b] = [-2.0, 0.0, 0.0]
    env.set_state(pos=pos, vel=vel)
    env.simulate(env.hover_action)


def test_collisions_count_after_the_grace_period_and_break_success(hover_env):
    env = hover_env(n=4)  # drones 1 m apart at z = 5, goals where they are
    hold(env, 10)
    approach(env, 0, 1)  # inside the grace period
    s = env.episode_stats(0)
    assert s["collisions"] == 1 and s["collisions_after_grace"] == 0 and s["inter_collision_rate"] == 0.0
    pos = env.get_state().pos
    pos[1] = pos[0] + [0.0, 2.0, 0.0]  # separate them again
    env.set_state(pos=pos, goal=pos, vel=np.zeros((4, 3)))
    hold(env, GRACE - 12)
    assert int(env._step_count[0]) == GRACE - 1
    approach(env, 2, 3)  # step GRACE: still in the grace period (the first 1.5 s)
    assert env.episode_stats(0)["collisions_after_grace"] == 0
    pos = env.get_state().pos
    pos[3] = pos[2] + [0.0, 2.0, 0.0]
    env.set_state(pos=pos, goal=pos, vel=np.zeros((4, 3)))
    approach(env, 2, 3)  # step GRACE + 1: counts
    s = env.episode_stats(0)
    assert s["collisions"] == 3 and s["collisions_after_grace"] == 1
    np.testing.assert_array_equal(s["agent_collided"], [False, False, True, True])
    assert s["inter_collision_rate"] == 0.5
    # every drone reached its goal (they hovered on it), but 2 and 3 collided after the grace period
    np.testing.assert_array_equal(s["agent_success"], [True, True, False, False])
    assert s["success_rate"] == 0.5


def test_room_contacts_are_reported_apart_from_collisions(hover_env):
    env = hover_env(n=2)
    hold(env, GRACE + 5)
    s = env.get_state()
    pos, vel = s.pos.copy(), np.zeros_like(s.vel)
    pos[1, 0], vel[1, 0] = 4.995, 2.0  # into the wall at x = 5 m
    env.set_state(pos=pos, vel=vel)
    env.simulate(env.hover_action)
    st = env.episode_stats(0)
    assert st["room_contacts"] == 1 and st["room_contacts_after_grace"] == 1
    assert st["collisions_after_grace"] == 0 and st["inter_collision_rate"] == 0.0


def test_tail_distances_match_a_numpy_recomputation(quiet_cfg):
    cfg = quiet_cfg(num_agents=3, num_neighbors=2, episode_duration=4.0, scenario="dynamic_same_goal")
    env = VecQuadEnv(cfg, num_envs=2, seed=3, auto_reset=False)
    rng = np.random.default_rng(1)
    dist = []  # [T, E] mean distance to goal after each step (float64, from the state)
    for _ in range(cfg.episode_steps):
        env.step(rng.uniform(-0.2, 0.6, (6, 4)))
        s = env.get_state()
        dist.append(np.linalg.norm(s.pos - s.goal, axis=1).reshape(2, 3).mean(1))
    dist = np.array(dist)
    stats = env.pop_episode_stats()
    assert len(stats) == 2
    for e, st in enumerate(stats):
        for key, seconds in (("dist_last_1s", 1), ("dist_last_3s", 3), ("dist_last_5s", 5)):
            np.testing.assert_allclose(st[key], dist[-min(100 * seconds, 400):, e].mean(), rtol=1e-9)
        np.testing.assert_allclose(st["dist_final"], dist[-1, e], rtol=1e-9)
        assert st["scenario"] == "dynamic_same_goal" and st["length"] == 400
        assert 0.0 <= st["success_rate"] <= 1.0 and st["agent_success"].shape == (3,)
