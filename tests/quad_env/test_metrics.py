"""Episode metrics (the paper's Table 1 columns) on hand-built trajectories.

Drones hover in place (all noise off, hover thrust) and ``set_state`` puts them where a case needs them;
``simulate`` steps the episode clock. The last-N-seconds distances are checked against a float64 numpy
recomputation of a random-action episode, success, reached and the contacts against one of episodes flown
by the goal-seeking controller.
"""
import numpy as np
import pytest

from quad_env import VecQuadEnv
from quad_env.controller import GoalSeekingController
from quad_env.kernels import SUCCESS_HOLD_S, SUCCESS_RADIUS, SUCCESS_WINDOW

GRACE = 150  # 1.5 s of 0.01 s control steps


def hold(env, steps, goal=None, pos=None, vel=None):
    """``steps`` control steps of hovering; ``pos``/``goal``/``vel`` are re-imposed before each step."""
    for _ in range(steps):
        if pos is not None or goal is not None or vel is not None:
            env.set_state(pos=pos, goal=goal, vel=vel)
        env.simulate(env.hover_action)


def test_reached_needs_a_full_window_below_half_a_metre(hover_env):
    env = hover_env(n=3)
    pos = env.get_state().pos
    goal = pos + np.array([[0.4, 0, 0], [0.6, 0, 0], [0.0, 0.0, 0.45]])  # within, outside, within
    hold(env, SUCCESS_WINDOW - 1, goal=goal, pos=pos)
    s = env.episode_stats(0)
    np.testing.assert_array_equal(s["agent_reached"], [False, False, False])  # window not yet full
    np.testing.assert_array_equal(s["agent_success"], [True, False, True])  # within at every step so far
    hold(env, 1, goal=goal, pos=pos)
    s = env.episode_stats(0)
    np.testing.assert_array_equal(s["agent_reached"], [True, False, True])
    np.testing.assert_allclose(s["reached_rate"], 2 / 3)
    # once reached, moving away later does not undo it (reached "at some time after the last goal change"),
    # but success (within the radius at every step of the last second) is gone
    hold(env, 10, goal=pos + 3.0, pos=pos)
    s = env.episode_stats(0)
    np.testing.assert_array_equal(s["agent_reached"], [True, False, True])
    np.testing.assert_array_equal(s["agent_success"], [False, False, False])
    assert s["success_rate"] == 0.0


def test_reached_is_a_windowed_mean(hover_env):
    env = hover_env(n=1)
    pos = env.get_state().pos
    dists = [0.9, 0.3, 0.3, 0.3, 0.3]  # mean 0.42 < 0.5 although the first step is far
    for d in dists:
        env.set_state(pos=pos, goal=pos + [[d, 0, 0]])
        env.simulate(env.hover_action)
    assert np.mean(dists) < SUCCESS_RADIUS and env.episode_stats(0)["reached_rate"] == 1.0
    assert env.episode_stats(0)["success_rate"] == 0.0  # the first step was outside the radius
    env2 = hover_env(n=1)
    for d in [1.5, 0.3, 0.3, 0.3, 0.3]:  # mean 0.54: not reached
        env2.set_state(pos=pos, goal=pos + [[d, 0, 0]])
        env2.simulate(env2.hover_action)
    assert env2.episode_stats(0)["reached_rate"] == 0.0


def test_a_goal_jump_restarts_the_reached_window(hover_env):
    env = hover_env(n=2)
    pos = env.get_state().pos
    hold(env, 8, goal=pos, pos=pos)
    assert env.episode_stats(0)["reached_rate"] == 1.0
    env.scenario.jumped[0] = 1  # what a dynamic scenario sets when the goals jump
    hold(env, 3, goal=pos, pos=pos)
    assert env.episode_stats(0)["reached_rate"] == 0.0  # reached must be earned again after the jump ...
    assert env.scenario.jumped[0] == 0  # ... the flag is consumed
    assert env.episode_stats(0)["success_rate"] == 1.0  # (success only asks where the drones are)
    hold(env, 2, goal=pos, pos=pos)
    assert env.episode_stats(0)["reached_rate"] == 1.0  # ... 5 steps after it


def test_success_is_within_the_radius_at_every_step_of_the_last_second(hover_env):
    """A 2 s episode (200 steps; the last second: steps 101-200). Per drone, where it is after each step:
    0 on its goal throughout; 1 on its goal until step 150, then 1 m off; 2 1 m off until step 100 (the
    last step before the last second), then on its goal; 3 the same until step 101; 4 and 5 on their goals
    0.3 m apart, except that 5 is sent into 4 at step 160 (0.2 m from its goal: still within the radius)."""
    env = hover_env(n=6, episode_duration=2.0)
    hold_steps = int(round(SUCCESS_HOLD_S / env.cfg.control_dt))
    assert env.cfg.episode_steps == 200 and hold_steps == 100
    goal = env.get_state().pos
    goal[5] = goal[4] + [0.3, 0.0, 0.0]
    off = np.array([0.0, 1.0, 0.0])
    for t in range(1, 201):  # before control step t
        pos, vel = goal.copy(), np.zeros((6, 3))
        pos[1] += off * (t > 150)
        pos[2] += off * (t <= 100)
        pos[3] += off * (t <= 101)
        if t == 160:
            pos[5], vel[5] = goal[4] + [0.1, 0.0, 0.0], [-2.0, 0.0, 0.0]  # touches drone 4 during this step
        env.set_state(pos=pos, goal=goal, vel=vel)
        env.step(env.hover_action)
    (s,) = env.pop_episode_stats()
    assert s["length"] == 200 and s["collisions_after_grace"] == 1
    np.testing.assert_array_equal(s["agent_collided"], [False, False, False, False, True, True])
    np.testing.assert_array_equal(s["agent_success"], [True, False, True, False, False, False])
    np.testing.assert_array_equal(s["agent_reached"], [True, True, True, True, False, False])
    assert s["success_rate"] == pytest.approx(2 / 6) and s["reached_rate"] == pytest.approx(4 / 6)


def test_success_in_an_episode_shorter_than_the_hold(hover_env):
    """An episode of 0.5 s: every one of its steps must be within the radius."""
    env = hover_env(n=2, episode_duration=0.5)
    goal = env.get_state().pos
    for t in range(1, env.cfg.episode_steps + 1):
        pos = goal.copy()
        pos[1, 1] += 0.6 * (t == 1)  # drone 1 is outside after the first step only
        env.set_state(pos=pos, goal=goal, vel=np.zeros((2, 3)))
        env.step(env.hover_action)
    (s,) = env.pop_episode_stats()
    assert s["length"] == 50
    np.testing.assert_array_equal(s["agent_success"], [True, False])
    np.testing.assert_array_equal(s["agent_reached"], [True, True])


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
    assert env.episode_stats(0)["length"] == GRACE - 1
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
    # 0 and 1 hovered on their goals over the last second; 2 and 3 collided after the grace period
    np.testing.assert_array_equal(s["agent_success"], [True, True, False, False])
    np.testing.assert_array_equal(s["agent_reached"], [True, True, False, False])
    assert s["success_rate"] == 0.5 and s["reached_rate"] == 0.5


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


def test_success_and_contacts_match_a_numpy_recomputation(quiet_cfg):
    """Episodes flown by the goal-seeking controller (with random action noise, so that some drones miss and
    some collide): success, reached, IColR and Col recomputed in float64 numpy from the states after every
    step, with the metric definitions (README, "Swarm metrics")."""
    cfg = quiet_cfg(num_agents=6, num_neighbors=2, episode_duration=4.0, scenario="static_diff_goal")
    E, N, T = 4, 6, cfg.episode_steps
    env = VecQuadEnv(cfg, num_envs=E, seed=5, auto_reset=False)
    control = GoalSeekingController(cfg)
    rng = np.random.default_rng(2)
    noise = np.repeat([0.0, 0.15, 0.3, 0.6], N)[:, None]  # per swarm: from clean to sloppy flying
    s = env.get_state()
    pos_t, goal_t = [s.pos], [s.goal]
    for _ in range(T):
        env.step(np.clip(control(env.get_state()) + noise * rng.normal(size=(E * N, 4)), -1, 1))
        s = env.get_state()
        pos_t.append(s.pos)
        goal_t.append(s.goal)
    pos, goal = np.array(pos_t).reshape(T + 1, E, N, 3), np.array(goal_t).reshape(T + 1, E, N, 3)
    dist = np.linalg.norm(pos - goal, axis=-1)[1:]  # [T, E, N] after each step
    pair_d = np.linalg.norm(pos[:, :, :, None] - pos[:, :, None, :], axis=-1)  # [T + 1, E, N, N]
    touching = (pair_d <= cfg.physics.collision_dist) & ~np.eye(N, dtype=bool)
    new = touching[1:] & ~touching[:-1]  # [T, E, N, N] new contact at step t (1-based: index t - 1)
    after_grace = new[150:]  # steps 151 ..
    collided = after_grace.any(axis=(0, 3))  # [E, N]
    hold = int(round(SUCCESS_HOLD_S / cfg.control_dt))
    success = (dist[-hold:] < SUCCESS_RADIUS).all(0) & ~collided
    window = np.stack([dist[k:T - SUCCESS_WINDOW + 1 + k] for k in range(SUCCESS_WINDOW)]).mean(0)
    reached = (window < SUCCESS_RADIUS).any(0) & ~collided  # static goals: no jump
    stats = env.pop_episode_stats()
    for e, st in enumerate(stats):
        np.testing.assert_array_equal(st["agent_collided"], collided[e])
        np.testing.assert_array_equal(st["agent_success"], success[e])
        np.testing.assert_array_equal(st["agent_reached"], reached[e])
        assert st["success_rate"] == pytest.approx(success[e].mean())
        assert st["reached_rate"] == pytest.approx(reached[e].mean())
        assert st["collisions_after_grace"] == int(np.triu(after_grace[:, e], 1).sum())
    # the episodes exercise every outcome: success, reached without success, collided, never near the goal
    assert success.any() and (reached & ~success).any() and collided.any() and (~reached & ~collided).any()
