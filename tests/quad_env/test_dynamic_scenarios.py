"""Goal motion of the dynamic scenarios, the formation generators and `mix`.

Scenarios are driven directly (reset, then update with a step counter), without physics: what is tested
is where the goals are at every control step.
"""
import numpy as np
import pytest

from quad_env import SCENARIOS, EnvConfig, VecQuadEnv, make_scenario
from quad_env.rng import seed_streams
from quad_env.scenarios import FORMATION_NAMES, MIX_SCENARIOS, place_formation

DT = 0.01
BOX_LO, BOX_HI = np.array([-4.5, -4.5, 0.5]), np.array([4.5, 4.5, 9.5])


def drive(name, n=4, num_envs=3, steps=1600, seed=0):
    """Goals [steps + 1, E, N, 3] (index t = goal of control step t, 0 = after reset), jump flags [steps, E]
    and the scenario."""
    sc = make_scenario(name, EnvConfig(num_agents=n, scenario=name))
    sc.allocate(num_envs)
    goal, center = np.zeros((num_envs * n, 3)), np.zeros((num_envs, 3))
    rng = seed_streams(seed, num_envs)
    sc.reset(np.ones(num_envs, bool), goal, center, rng)
    goals, jumps = [goal.copy()], []
    step = np.zeros(num_envs, np.int64)
    for _ in range(steps):
        sc.update(goal, step, rng)
        goals.append(goal.copy())
        jumps.append(sc.jumped.copy())
        sc.jumped[:] = 0  # the environment clears it every step
        step += 1
    return np.array(goals).reshape(steps + 1, num_envs, n, 3), np.array(jumps, bool), sc


def nearest(g):
    d = np.linalg.norm(g[:, None] - g[None], axis=-1) + np.eye(len(g)) * 1e9
    return d.min(1)


def change_steps(goals, e):
    """Steps t at which swarm e's goals differ from the step before."""
    return np.flatnonzero(np.any(goals[1:, e] != goals[:-1, e], axis=(1, 2))) + 1


# ---------------------------------------------------------------- formations
@pytest.mark.parametrize("n", [1, 2, 3, 8, 17, 64, 128])
@pytest.mark.parametrize("kind", range(len(FORMATION_NAMES)))
def test_formations_any_size_spacing_plane_and_room(kind, n):
    spacing = 0.5
    goal, center = np.zeros((n, 3)), np.zeros((1, 3))
    shrink = place_formation(kind, n, spacing, 0.0, 0.0, 2.0, BOX_LO, BOX_HI, np.zeros((n, 3)), goal, 0, center, 0)
    assert np.all(goal >= BOX_LO - 1e-9) and np.all(goal <= BOX_HI + 1e-9)
    assert shrink == 1.0  # spacing 0.5 fits the room for N <= 128
    off = goal - center[0]
    name = FORMATION_NAMES[kind]
    if n >= 2:
        nn = nearest(goal)
        np.testing.assert_allclose(nn.min(), spacing, rtol=1e-9)  # no two goals closer than the spacing
        if name != "sphere":
            np.testing.assert_allclose(nn.max(), spacing, rtol=1e-9)  # lattice / ring: every neighbour at it
    if name in ("circle", "grid"):
        np.testing.assert_allclose(off[:, 2], 0.0, atol=1e-12)
    if name in ("circle_xz", "grid_xz"):
        np.testing.assert_allclose(off[:, 1], 0.0, atol=1e-12)
        assert n < 3 or np.ptp(off[:, 2]) > 0  # (two points lie on the horizontal axis)
    if name in ("circle_yz", "grid_yz"):
        np.testing.assert_allclose(off[:, 0], 0.0, atol=1e-12)
        assert n < 3 or np.ptp(off[:, 2]) > 0  # (two points lie on the horizontal axis)
    if name == "sphere" and n >= 2:
        r = np.linalg.norm(off, axis=1)
        np.testing.assert_allclose(r, r[0], rtol=1e-9)  # all on one sphere around the centre
    if name == "cube" and n >= 8:
        c = int(np.ceil(round(n ** (1 / 3), 9)))
        assert all(len(np.unique(np.round(off[:, k], 6))) == c for k in (0, 1))
    assert len(np.unique(np.round(goal, 6), axis=0)) == n  # distinct goals


def test_formation_larger_than_the_room_is_shrunk_and_moved_inside():
    n = 128
    goal, center = np.zeros((n, 3)), np.zeros((1, 3))
    shrink = place_formation(4, n, 2.0, 0.0, 0.0, 2.0, BOX_LO, BOX_HI, np.zeros((n, 3)), goal, 0, center, 0)
    assert shrink < 1.0  # a 12 x 11 vertical grid at 2 m spacing is 22 m wide
    assert np.all(goal >= BOX_LO - 1e-9) and np.all(goal <= BOX_HI + 1e-9)
    np.testing.assert_allclose(nearest(goal).min(), 2.0 * shrink, rtol=1e-9)


@pytest.mark.parametrize("name", [s for s in SCENARIOS if s != "swarm_vs_swarm"] + ["swarm_vs_swarm"])
def test_every_scenario_keeps_goals_in_the_room_for_128_drones(name):
    goals, _, _ = drive(name, n=128, num_envs=2, steps=1300, seed=3)
    assert np.all(goals >= BOX_LO - 1e-9) and np.all(goals <= BOX_HI + 1e-9)
    assert np.isfinite(goals).all()


# ---------------------------------------------------------------- dynamic scenarios
def test_dynamic_same_goal_jumps_every_4_to_6_s():
    goals, jumps, _ = drive("dynamic_same_goal", steps=2000)
    np.testing.assert_array_equal(goals[0], np.tile([0.0, 0.0, 2.0], (3, 4, 1)))
    assert np.all(goals == goals[:, :, :1])  # one goal shared by the swarm
    for e in range(3):
        changes = change_steps(goals, e)
        jump_steps = np.flatnonzero(jumps[:, e]) + 1
        np.testing.assert_array_equal(changes, jump_steps)  # goals move exactly when a jump is flagged
        assert len(changes) >= 3
        gaps = np.diff(np.concatenate([[1], changes])) * DT
        assert gaps.min() >= 4.0 - 1e-9 and gaps.max() <= 6.0 + 1e-9
        g = goals[changes, e, 0]
        assert np.all(np.abs(g[:, :2]) <= 2.0) and np.all((g[:, 2] >= 1.0) & (g[:, 2] <= 3.0))
    assert len({tuple(goals[-1, e, 0]) for e in range(3)}) == 3  # swarms draw their own goals


def test_dynamic_diff_goal_new_formation_and_centre_at_each_jump():
    goals, jumps, _ = drive("dynamic_diff_goal", n=6, steps=2000)
    for e in range(3):
        changes = change_steps(goals, e)
        np.testing.assert_array_equal(changes, np.flatnonzero(jumps[:, e]) + 1)
        gaps = np.diff(np.concatenate([[1], changes])) * DT
        assert len(changes) >= 3 and gaps.min() >= 4.0 - 1e-9 and gaps.max() <= 6.0 + 1e-9
        for t in np.concatenate([[0], changes]):
            nn = nearest(goals[t, e])
            assert 0.25 - 1e-9 <= nn.min() <= 0.5 + 1e-9
        centres = goals[changes, e].mean(1)
        assert np.all(np.abs(centres[:, :2]) < 2.6) and len(np.unique(np.round(centres, 6), axis=0)) == len(changes)


def test_lissajous_goal_follows_the_curve_at_most_3_m_per_s():
    goals, jumps, sc = drive("ep_lissajous3D", steps=3000)
    assert not jumps.any()  # continuous motion, never a jump
    assert np.all(goals == goals[:, :, :1])
    np.testing.assert_allclose(goals[0, :, 0], np.tile([-2.0, 0.0, 2.0], (3, 1)), atol=1e-12)
    t = np.arange(3001)[:, None] * DT  # [T, 1]; goal of step t+1 is the curve at t * dt (set before it)
    w, s = sc.omega_e[None], sc.sign[None]
    ref = np.stack([-2 * np.cos(w * t), 2 * s * np.sin(2 * w * t), 2 + np.sin(3 * w * t)], -1)  # [T, E, 3]
    np.testing.assert_allclose(goals[1:, :, 0], ref[:-1], atol=1e-12)
    speed = np.linalg.norm(np.diff(goals[:, :, 0], axis=0), axis=-1) / DT
    assert speed.max() <= 3.0 + 1e-6 and speed.max() > 1.4
    assert np.all((sc.omega_e >= 0.3) & (sc.omega_e <= 0.6))


def test_random_bezier_hops_5_to_10_m_every_5_s_inside_the_room():
    goals, jumps, sc = drive("ep_rand_bezier", num_envs=4, steps=3000, seed=1)
    assert not jumps.any() and np.all(goals == goals[:, :, :1])
    g = goals[:, :, 0]  # [T, E, 3]
    np.testing.assert_allclose(g[0], np.tile([0.0, 0.0, 2.0], (4, 1)))
    knots = g[::500]  # curve ends (= next curve's start) every 5 s
    hops = np.linalg.norm(np.diff(knots, axis=0), axis=-1)
    assert hops.max() <= 10.0 + 1e-9 and np.mean(hops >= 5.0 - 1e-9) >= 0.8  # (clipped at walls if no fit)
    step = np.linalg.norm(np.diff(g, axis=0), axis=-1)
    assert step.max() / DT < 6.0  # continuous: no teleport at the re-plans
    assert np.all(g >= BOX_LO - 1e-9) and np.all(g <= BOX_HI + 1e-9)


def test_swarm_vs_swarm_teams_swap_centres():
    n = 7
    goals, jumps, sc = drive("swarm_vs_swarm", n=n, steps=2000, seed=2)
    a, b = slice(0, 3), slice(3, 7)
    for e in range(3):
        sep = np.linalg.norm(sc.team_center[0, e] - sc.team_center[1, e])
        assert 0.5 - 1e-9 <= sep <= 2.0 + 1e-9
        changes = change_steps(goals, e)
        np.testing.assert_array_equal(changes, np.flatnonzero(jumps[:, e]) + 1)
        gaps = np.diff(np.concatenate([[1], changes])) * DT
        assert len(changes) >= 3 and gaps.min() >= 4.0 - 1e-9 and gaps.max() <= 6.0 + 1e-9
        for t in changes:
            before, after = goals[t - 1, e], goals[t, e]
            shift_a = after[a] - before[a]
            shift_b = after[b] - before[b]
            np.testing.assert_allclose(shift_a, np.broadcast_to(shift_a[0], shift_a.shape), atol=1e-9)  # rigid
            np.testing.assert_allclose(shift_b, np.broadcast_to(shift_b[0], shift_b.shape), atol=1e-9)
            np.testing.assert_allclose(shift_a[0], -shift_b[0], atol=1e-9)  # they trade places
            assert np.linalg.norm(shift_a[0]) >= 0.5 - 1e-9


def test_swarm_vs_swarm_needs_two_drones():
    with pytest.raises(ValueError, match=r"swarm_vs_swarm.*num_agents >= 2"):
        VecQuadEnv(EnvConfig(num_agents=1, scenario="swarm_vs_swarm"), num_envs=1)


def test_swap_goals_deals_the_same_goals_anew():
    goals, jumps, _ = drive("swap_goals", n=8, steps=2000, seed=4)
    reassigned = 0
    for e in range(3):
        changes = np.flatnonzero(jumps[:, e]) + 1
        assert set(change_steps(goals, e)) <= set(changes)  # goals only move at a reshuffle
        gaps = np.diff(np.concatenate([[1], changes])) * DT
        assert len(changes) >= 3 and gaps.min() >= 4.0 - 1e-9 and gaps.max() <= 6.0 + 1e-9
        nn = nearest(goals[0, e])
        assert 0.4 - 1e-9 <= nn.min() <= 0.8 + 1e-9
        for t in changes:
            before, after = goals[t - 1, e], goals[t, e]
            np.testing.assert_array_equal(np.unique(before, axis=0), np.unique(after, axis=0))  # same set
            reassigned += int(np.any(before != after))
    assert reassigned >= 6


def test_dynamic_formations_breathe_around_a_fixed_centre():
    goals, jumps, sc = drive("dynamic_formations", n=6, steps=1300, seed=5)
    assert not jumps.any()
    for e in range(3):
        off = goals[:, e] - sc.centers[e]  # [T, N, 3]
        scale = np.linalg.norm(off, axis=(1, 2)) / np.linalg.norm(off[0])
        np.testing.assert_allclose(off, scale[:, None, None] * off[0], atol=1e-9)  # same shape, scaled
        t = np.arange(1301)
        ref = 1.0 - (1.0 - sc.size_lo[e]) * 0.5 * (1.0 - np.cos(2 * np.pi * np.maximum(t - 1, 0) / sc.period[e]))
        np.testing.assert_allclose(scale, ref, atol=1e-9)
        assert 0.3 <= scale.min() <= 0.6 + 1e-9 and 400 <= sc.period[e] <= 600
        assert 0.5 - 1e-9 <= nearest(goals[0, e]).min() <= 1.0 + 1e-9


# ---------------------------------------------------------------- mix
def test_mix_draws_every_scenario_and_names_it_in_the_stats():
    cfg = EnvConfig(num_agents=3, scenario="mix", episode_duration=0.05, num_neighbors=2)
    env = VecQuadEnv(cfg, num_envs=24, seed=0)
    drawn = [env.scenario.episode_name(e) for e in range(24)]
    static = [e for e in range(24) if drawn[e].startswith("static")]
    g0 = env.get_state().goal.reshape(24, 3, 3)
    for _ in range(4):
        env.step(np.zeros((72, 4)))
    g1 = env.get_state().goal.reshape(24, 3, 3)
    np.testing.assert_array_equal(g1[static], g0[static])  # a static draw keeps its goals
    liss = [e for e in range(24) if drawn[e] == "ep_lissajous3D"]
    assert liss and not np.array_equal(g1[liss], g0[liss])  # a pursuit draw moves them
    names = []
    for _ in range(15):
        env.step(np.zeros((72, 4)))
        names += [s["scenario"] for s in env.pop_episode_stats()]
    assert set(names) == set(MIX_SCENARIOS)  # every member drawn (and reported) within a few episodes
    assert drawn == names[:24]  # the stats of the first episodes name what each swarm drew
    one = make_scenario("mix", EnvConfig(num_agents=1, scenario="mix"))
    assert "swarm_vs_swarm" not in one.names and len(one.names) == len(MIX_SCENARIOS) - 1


@pytest.mark.parametrize("name", ["mix", "ep_rand_bezier"])
def test_dynamic_scenarios_are_reproducible(name):
    def run(seed):
        env = VecQuadEnv(EnvConfig(num_agents=3, scenario=name, episode_duration=0.3, num_neighbors=2),
                         num_envs=4, seed=seed)
        rng = np.random.default_rng(0)
        out = []
        for _ in range(70):
            obs, rew, _, _ = env.step(rng.uniform(-1, 1, (12, 4)))
            out.append(obs.copy())
        return np.array(out), env.get_state().goal
    (a, ga), (b, gb), (c, gc) = run(1), run(1), run(2)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ga, gb)
    assert not np.array_equal(ga, gc) and not np.array_equal(a, c)  # another seed: other goals, other flights
