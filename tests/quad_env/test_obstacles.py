"""Obstacles: cylinder physics and contacts, the obstacle field, layouts, the obstacle scenarios, metrics."""
import math

import numpy as np
import pytest

from quad_env import EnvConfig, RewardConfig, VecQuadEnv, make_scenario
from quad_env.params import KERNEL_TERMS, pack_params
from quad_env.kernels import (
    NUM_ACC, NUM_AGENT_ACC, EpisodeMetrics, Obstacles, StepOutput, SwarmState, step_with_metrics_kernel,
)
from quad_env.obstacles import (
    INDEX_SLOTS, OBSTACLE_CLEARANCE, draw_obstacles, index_obstacles, lookup_pad, obstacle_centers,
)
from quad_env.reference import cylinder_axes, reference_obstacle_field, reference_step_obstacles
from quad_env.rng import seed_streams

RADIUS = 0.3  # default diameter 0.6 m
CONTACT = RADIUS + 0.092 / 2  # a drone touches a cylinder at this axis distance
GRACE = 150


def one_cylinder(E=1, ix=4, iy=4, G=8):
    """A grid with one cylinder; cell (4, 4) of the default 8 x 8 grid of 1 m cells has its axis at (0.5, 0.5)."""
    grid = np.zeros((E, G, G), np.uint8)
    grid[:, ix, iy] = 1
    return grid


def obstacle_index(grid, cfg):
    """The obstacle field's lookup index of the layouts ``grid`` [E, G, G]."""
    E = grid.shape[0]
    L = cfg.obstacle_grid_cells + 2 * lookup_pad(cfg)
    index = np.zeros((E, L, L, INDEX_SLOTS + 1), np.uint8)
    index_obstacles(np.ones(E, bool), grid, index, -4.0, 1.0, RADIUS, cfg.obstacle_sdf_max, lookup_pad(cfg), 0.1 + 1e-6,
                    4)
    return index


def axis_distance(pos, axis=(0.5, 0.5)):
    return np.hypot(pos[..., 0] - axis[0], pos[..., 1] - axis[1])


@pytest.fixture
def cyl_env(hover_env):
    """Hovering drones (noise off, no drag) in a room with one cylinder, axis (0.5, 0.5)."""

    def make(n=1, **kw):
        env = hover_env(n=n, obstacles=True, **kw)
        env.set_obstacles(one_cylinder())
        return env

    return make


def fly_at(env, start, vel):
    s = env.get_state()
    pos = s.pos.copy()
    pos[0] = start
    v = np.zeros_like(s.vel)
    v[0] = vel
    env.set_state(pos=pos, vel=v, goal=pos)


# ---------------------------------------------------------------- physics and contacts
@pytest.mark.parametrize("restitution", [0.0, 0.5])
def test_a_drone_flying_at_a_cylinder_stops_at_its_surface_and_counts_one_contact(cyl_env, restitution):
    env = cyl_env(physics=dict(wall_restitution=restitution))
    fly_at(env, [-0.1, 0.5, 5.0], [2.0, 0.0, 0.0])  # 0.6 m from the axis, flying at it at 2 m/s
    dists, vx, coll = [], [], []
    for _ in range(40):
        s = env.simulate(env.hover_action)
        dists.append(axis_distance(s.pos[0]))
        vx.append(s.vel[0, 0])
        coll.append(env.reward_terms["collision"][0])
    dists, vx, coll = np.array(dists), np.array(vx), np.array(coll)
    hit = int(np.argmax(vx < 1.0))  # the step of the contact
    assert 10 <= hit <= 14  # 0.254 m to the contact circle at 2 m/s: about 13 steps
    assert dists.min() >= CONTACT - 1e-12  # never inside
    np.testing.assert_allclose(vx[hit:], -restitution * 2.0, atol=1e-9)  # radial speed reversed and damped
    if restitution == 0.0:
        np.testing.assert_allclose(dists[hit:], CONTACT, atol=1e-12)  # stopped on the surface
    stats = env.episode_stats(0)
    assert stats["obstacle_collisions"] == 1 and stats["collisions"] == 1  # once, although it stays there
    np.testing.assert_allclose(coll[hit], -5.0, rtol=1e-6)  # -5 per new contact ...
    assert np.all(coll[:hit] == 0) and np.all(coll[hit + 1:] == 0)  # ... and only then


def test_a_drone_pressing_on_a_cylinder_is_one_contact_and_a_second_approach_another(cyl_env):
    # restitution 0: no bounce, so the drone stays on the surface while its tilted thrust pushes it in
    env = cyl_env(reward=RewardConfig(obstacle_collision=2.0), physics=dict(wall_restitution=0.0))
    pitch = 0.3  # thrust tilted towards +x: the drone keeps accelerating into the cylinder
    rot = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    fly_at(env, [0.5 - CONTACT - 0.01, 0.5, 5.0], [0.5, 0.0, 0.0])
    env.set_state(rot=rot[None])
    coll = []
    for _ in range(50):
        s = env.simulate(env.hover_action)
        coll.append(env.reward_terms["collision"][0])
        assert axis_distance(s.pos[0]) >= CONTACT - 1e-12
    assert axis_distance(s.pos[0]) < CONTACT + 0.01  # still pressing on it, after 50 steps ...
    assert env.episode_stats(0)["obstacle_collisions"] == 1  # ... counted as one contact (one onset), not 50
    np.testing.assert_allclose(sorted(coll)[:2], [-2.0, 0.0], rtol=1e-6)  # reward.obstacle_collision, once
    # fly away level, then at the other side of the cylinder: a new contact
    fly_at(env, [1.5, 0.5, 5.0], [-3.0, 0.0, 0.0])
    env.set_state(rot=np.eye(3)[None])
    for _ in range(30):
        env.simulate(env.hover_action)
    assert env.episode_stats(0)["obstacle_collisions"] == 2


def random_obstacle_state(rng, E, N, grid, cfg):
    """Drones scattered over the obstacle grid, half of them near (or inside) a cylinder, moving at it."""
    M = E * N
    pos = np.column_stack([rng.uniform(-4.5, 4.5, (M, 2)), rng.uniform(0.3, 3.0, M)])
    vel = rng.uniform(-3, 3, (M, 3))
    for e in range(E):
        axes = obstacle_centers(grid[e], cfg)
        for a in range(0, N, 2):
            i = e * N + a
            c = axes[rng.integers(len(axes))]
            ang = rng.uniform(0, 2 * np.pi)
            d = 0.0 if a == 0 else rng.uniform(0.2, CONTACT + 0.03)  # on the axis, inside, or just outside
            pos[i, :2] = c + d * np.array([np.cos(ang), np.sin(ang)])
            vel[i, :2] = -2.0 * np.array([np.cos(ang), np.sin(ang)])  # inwards
    q, r = np.linalg.qr(rng.normal(size=(M, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return dict(pos=pos, vel=vel, rot=q, omega=rng.uniform(-20, 20, (M, 3)), motor=rng.uniform(0, 1, (M, 4)),
                goal=rng.uniform(-2, 2, (M, 3)))


@pytest.mark.parametrize("steps_done", [0, GRACE])
def test_kernel_matches_the_numpy_reference_with_obstacles(quiet_cfg, steps_done):
    cfg = quiet_cfg(num_agents=6, num_neighbors=3, obstacles=True, obstacle_density=0.4,
                    physics=dict(wall_restitution=0.3))
    E, N = 3, 6
    env = VecQuadEnv(cfg, num_envs=E, seed=0)
    rng = np.random.default_rng(7)
    touched = 0
    for trial in range(4):
        grid = (rng.uniform(size=(E, 8, 8)) < 0.4).astype(np.uint8)
        state = random_obstacle_state(rng, E, N, grid, cfg)
        actions = rng.uniform(-1, 1, (E * N, 4))
        prev_contact = (rng.uniform(size=E * N) < 0.3).astype(np.uint8)
        contact = np.zeros((E, N, N), np.uint8)
        # kernel, float64 buffers
        s = {k: v.copy() for k, v in state.items()}
        M, D = E * N, env.obs_dim
        obs, rew, terms = np.zeros((M, D)), np.zeros(M), np.zeros((KERNEL_TERMS, M))
        kcontact, kobst = contact.copy(), prev_contact.copy()
        kstate = SwarmState(pos=s["pos"], vel=s["vel"], rot=s["rot"], omega=s["omega"], motor=s["motor"],
                            ou=np.zeros((M, 4)), goal=s["goal"], contact=kcontact, room_contact=np.zeros(M, np.uint8),
                            rng=seed_streams(0, E), step_count=np.full(E, steps_done, np.int64))
        out = StepOutput(obs=obs, rew=rew, terms=terms, done=np.zeros(E, bool), diverged=np.zeros(E, bool))
        metrics = EpisodeMetrics(acc=np.zeros((E, NUM_ACC)), agent_acc=np.zeros((M, NUM_AGENT_ACC)),
                                 jumped=np.zeros(E, np.uint8))
        step_with_metrics_kernel(actions, kstate, *pack_params(cfg, D, noise=False), out, metrics,
                                 Obstacles(grid=grid, index=obstacle_index(grid, cfg), contact=kobst))
        rs, robs, rrew, rterms, rcontact, robst = reference_step_obstacles(
            state, actions, cfg, np.full(E, steps_done), contact, grid, prev_contact)
        for name in ("pos", "vel", "rot", "omega", "motor"):
            np.testing.assert_allclose(s[name], rs[name], rtol=0, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(obs, robs, rtol=0, atol=1e-9)
        np.testing.assert_allclose(terms, rterms, rtol=0, atol=1e-9)
        np.testing.assert_allclose(rew, rrew, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(kobst, robst)
        np.testing.assert_array_equal(kcontact, rcontact)
        touched += int(robst.sum())
        assert (rterms[1] < 0).any()  # new obstacle contacts were rewarded
    assert touched >= 12  # the cases really hit cylinders


# ---------------------------------------------------------------- the obstacle field
def sdf_row(env, xy, z=5.0):
    s = env.get_state()
    pos = s.pos.copy()
    pos[0, :2], pos[0, 2] = xy, z
    env.set_state(pos=pos)
    return env.layout.split(env.observe())["obstacle.obstacle_sdf"][0]


def test_obstacle_field_matches_hand_computed_distances(cyl_env):
    env = cyl_env()
    # drone 1 m west of the axis (0.5, 0.5): entry 3 a + b samples (-0.5 + (a - 1) 0.1, 0.5 + (b - 1) 0.1)
    r = sdf_row(env, [-0.5, 0.5])
    expected = [math.sqrt(1.1 ** 2 + 0.1 ** 2) - 0.3, 1.1 - 0.3, math.sqrt(1.1 ** 2 + 0.1 ** 2) - 0.3,
                math.sqrt(1.0 ** 2 + 0.1 ** 2) - 0.3, 1.0 - 0.3, math.sqrt(1.0 ** 2 + 0.1 ** 2) - 0.3,
                math.sqrt(0.9 ** 2 + 0.1 ** 2) - 0.3, 0.9 - 0.3, math.sqrt(0.9 ** 2 + 0.1 ** 2) - 0.3]
    np.testing.assert_allclose(r, expected, atol=1e-6)
    # next to the surface (0.35 m from the axis, 0.05 m outside it): the near grid points are inside
    r = sdf_row(env, [0.85, 0.5])
    np.testing.assert_allclose(r[1], 0.25 - 0.3, atol=1e-6)  # (0.75, 0.5): 0.05 m deep
    np.testing.assert_allclose(r[4], 0.05, atol=1e-6)
    np.testing.assert_allclose(r[7], 0.45 - 0.3, atol=1e-6)
    # far away (outside the grid): every entry clipped to obstacle_sdf_max
    np.testing.assert_array_equal(sdf_row(env, [4.6, -4.6]), np.full(9, 2.0, np.float32))
    # a second, nearer cylinder wins: axis (-1.5, 0.5), 0.5 m west of the drone at (-1, 0.5)
    grid = one_cylinder()
    grid[0, 2, 4] = 1
    env.set_obstacles(grid)
    np.testing.assert_allclose(sdf_row(env, [-1.0, 0.5])[4], 0.5 - 0.3, atol=1e-6)


FINE_GRID = dict(obstacle_grid_cells=18, obstacle_cell_size=0.5, obstacle_diameter=0.3)  # > 16 cells: uint16 index


@pytest.mark.parametrize("density,sdf_max,grid_kw", [(0.05, 8.0, {}), (0.2, 2.0, {}), (0.6, 0.5, {}), (0.0, 2.0, {}),
                                                     (0.2, 2.0, FINE_GRID)])
def test_obstacle_field_equals_a_brute_force_reference_everywhere(quiet_cfg, density, sdf_max, grid_kw):
    """The kernel reads a per-cell candidate index (or scans rings of cells and stops early, where a cell has
    too many candidates); the reference takes every cylinder."""
    E, N = 3, 60
    cfg = quiet_cfg(num_agents=N, num_neighbors=0, obstacles=True, obstacle_sdf_max=sdf_max, **grid_kw)
    env = VecQuadEnv(cfg, num_envs=E, seed=0)
    rng = np.random.default_rng(int(density * 100))
    G = cfg.obstacle_grid_cells
    grid = (rng.uniform(size=(E, G, G)) < density).astype(np.uint8)
    env.set_obstacles(grid)
    counts = env._obst_index[..., 0].copy()
    assert density == 0.0 or (counts > 0).any()
    for path in ("index", "ring scan"):
        if path == "ring scan":
            env._obst_index[..., 0] = INDEX_SLOTS + 1  # every lookup cell "overflows"
        for trial in range(3):
            pos = np.column_stack([rng.uniform(-5, 5, (E * N, 2)), rng.uniform(0.5, 3, E * N)])
            env.set_state(pos=pos)
            field = env.layout.split(env.observe())["obstacle.obstacle_sdf"]
            for e in range(E):
                rows = slice(e * N, (e + 1) * N)
                expected = reference_obstacle_field(pos[rows, :2], cylinder_axes(grid[e], cfg), cfg)
                np.testing.assert_allclose(field[rows], expected, rtol=0, atol=1e-6, err_msg=path)
        assert density == 0.0 or (field < sdf_max).any()


def test_obstacle_field_clip_follows_the_config(hover_env):
    env = hover_env(obstacles=True, obstacle_sdf_max=0.65)
    env.set_obstacles(one_cylinder())
    np.testing.assert_allclose(sdf_row(env, [-0.5, 0.5]), [0.65] * 3 + [0.65, 0.65, 0.65] + [0.6055385, 0.6, 0.6055385],
                               atol=1e-6)


def test_observation_grows_by_nine_only_with_obstacles():
    base = dict(num_agents=3, num_neighbors=2)
    plain = VecQuadEnv(EnvConfig(**base), num_envs=2, seed=0)
    obst = VecQuadEnv(EnvConfig(obstacles=True, **base), num_envs=2, seed=0)
    assert plain.obs_dim == 18 + 2 * 22 and obst.obs_dim == plain.obs_dim + 9
    assert not plain.layout.obstacle_obs and obst.layout.obstacle_obs
    assert obst.layout == EnvConfig(obstacles=True, **base).obs_layout()
    field = obst.layout.field("obstacle_sdf", "obstacle")
    assert (field.start, field.size, field.kind) == (plain.obs_dim, 9, "scalar")
    obs = obst.observe()
    assert np.all(obs[:, field.start:] <= 2.0) and np.all(obs[:, field.start:] > -RADIUS)


# ---------------------------------------------------------------- layouts
def test_layouts_are_reproducible_by_seed_and_have_the_configured_density():
    def grids(seed, density=0.2, E=150):
        cfg = EnvConfig(num_agents=2, num_neighbors=1, scenario="o_random", obstacles=True, obstacle_density=density)
        return VecQuadEnv(cfg, num_envs=E, seed=seed).obstacle_grid.copy()

    a, b, c = grids(3), grids(3), grids(4)
    np.testing.assert_array_equal(a, b)
    assert (a != c).any()
    assert abs(a.mean() - 0.2) < 0.02  # 9600 cells: 4.9 standard deviations
    assert abs(grids(5, density=0.5).mean() - 0.5) < 0.03
    # o_random clears nothing: the grid is exactly the first draws of each swarm's stream
    expected = np.zeros_like(a)
    draw_obstacles(np.ones(150, bool), expected, seed_streams(3, 150), 0.2)
    np.testing.assert_array_equal(a, expected)


def test_every_episode_draws_a_new_layout():
    cfg = EnvConfig(num_agents=2, num_neighbors=1, scenario="o_random", obstacles=True, episode_duration=0.02)
    env = VecQuadEnv(cfg, num_envs=4, seed=0)
    first = env.obstacle_grid.copy()
    env.step(np.zeros((8, 4)))
    env.step(np.zeros((8, 4)))  # the episodes end and restart
    assert (env.obstacle_grid != first).any()


@pytest.mark.parametrize("scenario", ["o_random", "o_static_same_goal", "static_diff_goal", "mix"])
def test_spawn_points_and_goals_are_clear_of_cylinders(scenario):
    E, N = 40, 8
    cfg = EnvConfig(num_agents=N, num_neighbors=2, scenario=scenario, obstacles=True, obstacle_density=0.5)
    env = VecQuadEnv(cfg, num_envs=E, seed=1)
    s = env.get_state()
    raw = np.zeros_like(env.obstacle_grid)
    draw_obstacles(np.ones(E, bool), raw, seed_streams(1, E), 0.5)
    for e in range(E):
        axes = obstacle_centers(env.obstacle_grid[e], cfg)
        rows = slice(e * N, (e + 1) * N)
        for points in (s.pos[rows], s.goal[rows]):
            d = np.linalg.norm(points[:, None, :2] - axes[None], axis=-1)
            assert d.min() >= RADIUS + OBSTACLE_CLEARANCE
    assert np.all(env.obstacle_grid <= raw)  # cylinders are only ever removed
    removed = int(raw.sum() - env.obstacle_grid.sum())
    if scenario.startswith("o_"):
        assert removed == 0  # spawns and goals lie outside the grid
    else:
        assert removed > 0  # spawn boxes around (0, 0, 2) overlap the grid: some cylinders yield


# ---------------------------------------------------------------- obstacle scenarios
def courses(name, E=60, N=6, steps=120):
    cfg = EnvConfig(num_agents=N, num_neighbors=2, scenario=name, obstacles=True)
    env = VecQuadEnv(cfg, num_envs=E, seed=2)
    s0 = env.get_state()
    rng = np.random.default_rng(0)
    for _ in range(steps):
        env.step(rng.uniform(-1, 1, (E * N, 4)))
    np.testing.assert_array_equal(env.get_state().goal, s0.goal)  # static goals
    assert not env.scenario.dynamic
    return s0.pos.reshape(E, N, 3), s0.goal.reshape(E, N, 3)


def course_frame(spawn, goal):
    """Unit vector from the spawn side to the goal side (a world axis) and the along axis."""
    direction = goal.mean(0)[:2] - spawn.mean(0)[:2]
    k = np.argmax(np.abs(direction))
    across = np.zeros(2)
    across[k] = np.sign(direction[k])
    return across, np.array([-across[1], across[0]])


@pytest.mark.parametrize("name", ["o_random", "o_static_same_goal"])
def test_obstacle_courses_start_and_end_on_opposite_sides_of_the_grid(name):
    spawn, goal = courses(name)
    sides = set()
    for e in range(spawn.shape[0]):
        across, along = course_frame(spawn[e], goal[e])
        sides.add(tuple(across))
        s_across, g_across = spawn[e, :, :2] @ across, goal[e, :, :2] @ across
        assert np.all(s_across <= -4.1 + 1e-9) and np.all(s_across >= -4.9 - 1e-9)  # spawn band
        assert np.all(g_across >= 4.1 - 1e-9) and np.all(g_across <= 4.5 + 1e-9)  # goal band
        assert np.all(np.abs(spawn[e, :, :2] @ along) <= 3.5 + 1e-9)
        assert np.all(np.abs(goal[e, :, :2] @ along) <= 3.5 + 1e-9)
        if name == "o_static_same_goal":
            np.testing.assert_allclose(goal[e], np.tile(goal[e, 0], (6, 1)))
            np.testing.assert_allclose([goal[e, 0, :2] @ across, goal[e, 0, :2] @ along, goal[e, 0, 2]],
                                       [4.3, 0.0, 2.0], atol=1e-12)
        else:
            d = np.linalg.norm(goal[e][:, None] - goal[e][None], axis=-1) + np.eye(6)
            assert d.min() >= 0.3  # own goals, apart
            assert np.all((goal[e, :, 2] >= 1.0) & (goal[e, :, 2] <= 3.0))
    assert len(sides) == 4  # all four directions drawn


def test_obstacle_scenarios_need_obstacles_and_room_around_the_grid():
    with pytest.raises(ValueError, match=r"'o_random'.*env.obstacles=True"):
        VecQuadEnv(EnvConfig(scenario="o_random"), num_envs=1)
    with pytest.raises(ValueError, match="env.obstacle_grid_cells"):
        make_scenario("o_static_same_goal", EnvConfig(obstacles=True, obstacle_grid_cells=10))


def test_mix_joins_the_obstacle_courses_only_with_obstacles():
    with_obst = make_scenario("mix", EnvConfig(num_agents=4, obstacles=True))
    without = make_scenario("mix", EnvConfig(num_agents=4))
    assert set(with_obst.names) - set(without.names) == {"o_random", "o_static_same_goal"}
    env = VecQuadEnv(EnvConfig(num_agents=2, num_neighbors=1, scenario="mix", obstacles=True, episode_duration=0.02),
                     num_envs=20, seed=0)
    names = []
    for _ in range(12):
        env.step(np.zeros((40, 4)))
        names += [s["scenario"] for s in env.pop_episode_stats()]
    assert {"o_random", "o_static_same_goal"} <= set(names)


# ---------------------------------------------------------------- metrics and config
def test_obstacle_contacts_after_the_grace_period_count_as_collisions_and_break_success(cyl_env):
    env = cyl_env(n=2)  # drones at x = 0 and 1, z = 5, on their goals
    for _ in range(GRACE + 5):
        env.simulate(env.hover_action)
    fly_at(env, [-0.1, 0.5, 5.0], [2.0, 0.0, 0.0])
    for _ in range(20):
        env.simulate(env.hover_action)
    s = env.episode_stats(0)
    assert s["obstacle_collisions_after_grace"] == 1 and s["collisions_after_grace"] == 1
    assert s["inter_collision_rate"] == 0.0  # IColR stays drone-drone
    np.testing.assert_array_equal(s["agent_hit_obstacle"], [True, False])
    np.testing.assert_array_equal(s["agent_success"], [False, True])


@pytest.mark.parametrize("kw,key", [
    (dict(obstacle_density=1.5), "env.obstacle_density"),
    (dict(obstacle_diameter=0.95), "env.obstacle_diameter"),
    (dict(obstacle_diameter=0.0), "env.obstacle_diameter"),
    (dict(obstacle_grid_cells=11), "env.obstacle_grid_cells"),
    (dict(obstacle_grid_cells=2.5), "env.obstacle_grid_cells"),
    (dict(obstacle_cell_size=-1.0), "env.obstacle_cell_size"),
    (dict(obstacle_sdf_max=0.0), "env.obstacle_sdf_max"),
    (dict(obstacles="yes"), "env.obstacles"),
    (dict(replay_prob=1.2), "env.replay_prob"),
    (dict(replay_buffer_size=0), "env.replay_buffer_size"),
    (dict(reward=RewardConfig(obstacle_collision=-1.0)), "env.reward.obstacle_collision"),
])
def test_config_errors_name_the_key(kw, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        EnvConfig(**kw).validate()


# ---------------------------------------------------------------- encoders read the obstacle field
def test_every_encoder_builds_an_actor_critic_on_obstacle_observations():
    torch = pytest.importorskip("torch")
    import encoders
    from encoders import ActorCritic
    from encoders.testing import TINY_OPTIONS

    env = VecQuadEnv(EnvConfig(num_agents=4, num_neighbors=3, scenario="o_random", obstacles=True), num_envs=2,
                     seed=0)
    obs = torch.as_tensor(env.observe().copy(), dtype=torch.float64)
    field = env.layout.field("obstacle_sdf", "obstacle")
    for name in encoders.ENCODERS:
        torch.manual_seed(0)
        model = ActorCritic(env.layout, encoder=name, encoder_kwargs=TINY_OPTIONS[name]).double()
        mean, _, value = model(obs)
        assert mean.shape == (8, 4) and value.shape == (8,) and torch.isfinite(mean).all()
        moved = obs.clone()
        moved[:, field.start:field.stop] -= 0.5  # a cylinder closer by: the policy sees it
        assert not torch.allclose(model(moved)[0], mean), name


# ---------------------------------------------------------------- pictures
def test_pictures_draw_the_cylinders_and_mark_every_obstacle_hit(tmp_path, capsys):
    from PIL import Image

    from quad_env.render import main, record_episode, save_animation_gif, save_trajectory_png

    cfg = EnvConfig(num_agents=8, scenario="o_static_same_goal", obstacles=True)
    ep = record_episode(cfg, "controller", steps=300, seed=1)  # flies straight at the goal, through the grid
    assert len(ep.cylinders) >= 5 and ep.cylinder_radius == RADIUS
    assert len(ep.obstacle_hits) == ep.stats["obstacle_collisions"] >= 1  # one mark per new contact
    for t, x, y, z in ep.obstacle_hits:  # marks are drones on a cylinder surface at that step
        d = np.linalg.norm(ep.cylinders[:, None] - np.array([x, y])[None, None], axis=-1).min()
        assert CONTACT - 1e-9 <= d <= CONTACT + 0.05
        assert np.isclose(np.linalg.norm(ep.pos[int(t)] - [x, y, z], axis=1), 0).any()
    png = save_trajectory_png(ep, str(tmp_path / "o.png"))
    gif = save_animation_gif(ep, str(tmp_path / "o.gif"), frame_every=100)
    with Image.open(gif) as im:
        assert im.n_frames == 4
    with open(png, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    paths = main(["--scenario", "o_random", "--out", str(tmp_path), "--steps", "8", "--num-agents", "2",
                  "--frame-every", "4"])  # the o_* scenarios switch obstacles on in the command
    assert all(p.startswith(str(tmp_path)) for p in paths) and "obstacles" in capsys.readouterr().out
