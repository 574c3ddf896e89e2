"""Collision replay: a stored pre-collision state restarts episodes with the configured probability."""
import numpy as np
import pytest

from quad_env import VecQuadEnv
from quad_env.replay import LOOKBACK_S, SNAPSHOT_INTERVAL_S

FIELDS = ("pos", "vel", "rot", "omega", "motor", "thrust_noise", "goal")
GRACE = 150
INTERVAL = int(round(SNAPSHOT_INTERVAL_S / 0.01))  # 25 control steps
LOOKBACK = int(round(LOOKBACK_S / 0.01))  # 150


def crash_pairs(env):
    """In every swarm, put drone 1 0.1 m beside drone 0 flying into it at 2 m/s: they touch at the next step."""
    s = env.get_state()
    pos, vel = s.pos.copy(), s.vel.copy()
    N = env.num_agents
    pos[1::N] = pos[0::N] + [0.1, 0.0, 0.0]
    vel[1::N] = [-2.0, 0.0, 0.0]
    env.set_state(pos=pos, vel=vel)


def drifting(hover_env, **kw):
    """Two hovering drones (noise off) drifting at 0.1 m/s, so that every step's state is different."""
    env = hover_env(n=2, **kw)
    env.set_state(vel=np.tile([0.1, 0.05, 0.0], (2, 1)))
    return env


def test_replay_restarts_from_the_state_stored_before_the_collision(hover_env):
    env = drifting(hover_env, replay_prob=1.0, episode_duration=2.5, obstacles=True)
    grid = np.zeros((1, 8, 8), np.uint8)
    grid[0, 0, 7] = 1  # one cylinder, far from the drones, to check the layout comes back with the state
    env.set_obstacles(grid)
    states, collide_at = {}, 190
    for t in range(1, 250):
        if t == collide_at:
            crash_pairs(env)
        if t == collide_at + 10:  # the layout changes after the state was stored: the stored one comes back
            env.set_obstacles(np.roll(grid, 3, axis=1))
        env.step(env.hover_action)
        states[t] = env.get_state()
        assert env.episode_stats(0)["length"] == t
    assert env.episode_stats(0)["collisions_after_grace"] == 1
    stored = (collide_at - LOOKBACK) // INTERVAL * INTERVAL  # 25: the last snapshot 1.5 s or more before
    assert stored == 25
    env.step(env.hover_action)  # step 250 ends the episode: the swarm restarts from the stored state
    stats = env.pop_episode_stats()
    assert len(stats) == 1 and not stats[0]["replayed"]
    now = env.get_state()
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(now, name), getattr(states[stored], name), err_msg=name)
    for t in (stored - 1, stored + 1, stored + INTERVAL):  # (the drift makes every step's positions differ)
        assert not np.array_equal(now.pos, states[t].pos)
    np.testing.assert_array_equal(env.obstacle_grid, grid)  # not a fresh layout
    assert env.episode_stats(0)["length"] == 0  # a whole new episode
    env.step(env.hover_action)
    st = env.episode_stats(0)
    assert st["replayed"] and st["scenario"] == "static_same_goal" and st["length"] == 1
    np.testing.assert_array_equal(env.get_state().goal, states[stored].goal)  # the stored goals stay


def many_crashes(quiet_cfg, prob, seed=0, E=200, episodes=4, **kw):
    """E swarms of 2 drones; in every fresh episode the pairs crash after the grace period. Returns the
    'replayed' flags [episodes, E] and the final observation."""
    cfg = quiet_cfg(num_agents=2, num_neighbors=1, episode_duration=1.7, replay_prob=prob, replay_buffer_size=256,
                    **kw)
    env = VecQuadEnv(cfg, num_envs=E, seed=seed)
    hover = np.full((2 * E, 4), 2.0 / 1.9 - 1.0)
    flags = []
    for _ in range(episodes):
        for t in range(1, 171):
            if t == 160:
                crash_pairs(env)
            env.step(hover)
        stats = env.pop_episode_stats()
        assert len(stats) == E
        flags.append([s["replayed"] for s in stats])
    return np.array(flags), env.observe().copy(), env


def test_replay_happens_with_the_configured_probability_and_is_deterministic(quiet_cfg):
    flags, obs, env = many_crashes(quiet_cfg, 0.3)
    assert not flags[0].any()  # nothing to replay in the first episodes
    fresh = int((~flags).sum())  # each fresh episode stored one state (replayed ones, which crash too, none)
    info = env.replay_info()
    assert fresh > 256 and info["stored"] == 256 and info["next_slot"] == fresh % 256  # oldest overwritten
    share = flags[1:].mean()  # 600 resets
    assert abs(share - 0.3) < 0.075  # 4 standard deviations
    flags2, obs2, _ = many_crashes(quiet_cfg, 0.3)
    np.testing.assert_array_equal(flags, flags2)
    np.testing.assert_array_equal(obs, obs2)
    flags3, _, _ = many_crashes(quiet_cfg, 0.3, seed=1)
    assert (flags3 != flags).any()
    high, _, _ = many_crashes(quiet_cfg, 0.8, E=100, episodes=2)
    assert abs(high[1].mean() - 0.8) < 0.17


def test_no_replay_when_off_on_explicit_resets_and_without_auto_reset(quiet_cfg, hover_env):
    flags, obs_off, env = many_crashes(quiet_cfg, 0.0, E=20, episodes=2)
    assert env.replay_info() is None and not flags.any()
    # replay on, but no collision ever stored: the env is bit-identical to one without replay
    def quiet_run(prob):
        env = VecQuadEnv(quiet_cfg(num_agents=2, num_neighbors=1, episode_duration=0.5, replay_prob=prob),
                         num_envs=3, seed=4)
        rng = np.random.default_rng(0)
        return [env.step(rng.uniform(-1, 1, (6, 4)))[0].copy() for _ in range(120)]
    for a, b in zip(quiet_run(0.0), quiet_run(1.0)):
        np.testing.assert_array_equal(a, b)
    # a full buffer, then an explicit reset: fresh spawns
    _, _, env = many_crashes(quiet_cfg, 1.0, E=10, episodes=1)
    assert env.replay_info()["stored"] == 10
    env.reset()
    assert not env.replay_info()["replaying"].any()
    # auto_reset=False (evaluation): never replays
    env = hover_env(n=2, replay_prob=1.0, episode_duration=1.7)
    env.auto_reset = False
    for t in range(1, 171):
        if t == 160:
            crash_pairs(env)
        env.step(env.hover_action)
    assert env.replay_info()["stored"] == 1
    with pytest.raises(RuntimeError, match="reset"):
        env.step(env.hover_action)
    env.reset()
    assert not env.replay_info()["replaying"].any()
