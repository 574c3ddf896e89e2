"""Observation contents, neighbour selection and masking, and the SE(3) layout transform."""
import numpy as np
import pytest

from quad_env import ObsLayout, VecQuadEnv


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def make_env(quiet_cfg, n, k=6, **kw):
    return VecQuadEnv(quiet_cfg(num_agents=n, num_neighbors=k, **kw), num_envs=1, seed=0)


def line_state(env, xs):
    """Drones on the x axis at z = 3, each with its own rotation, rates, velocity and goal."""
    n = len(xs)
    rng = np.random.default_rng(0)
    pos = np.stack([np.asarray(xs, float), np.zeros(n), np.full(n, 3.0)], 1)
    state = dict(pos=pos, vel=rng.normal(size=(n, 3)), rot=np.stack([random_rotation(rng) for _ in range(n)]),
                 omega=rng.normal(size=(n, 3)), goal=pos + rng.normal(size=(n, 3)))
    env.set_state(**state)
    return state


def test_self_block_is_the_drone_state(quiet_cfg):
    env = make_env(quiet_cfg, 3, k=2)
    st = line_state(env, [0.0, 1.0, 2.5])
    f = env.layout.split(env.observe().astype(np.float64))
    np.testing.assert_allclose(f["self.rel_goal"], st["pos"] - st["goal"], atol=1e-6)
    np.testing.assert_allclose(f["self.vel"], st["vel"], atol=1e-6)
    np.testing.assert_allclose(ObsLayout.as_matrix(f["self.rot"]), st["rot"], atol=1e-6)  # row-major R
    np.testing.assert_allclose(f["self.omega"], st["omega"], atol=1e-6)
    assert env.observe().dtype == np.float32 and env.observe().shape == (3, env.layout.dim)


def test_neighbours_sorted_by_distance_with_full_state(quiet_cfg):
    env = make_env(quiet_cfg, 5, k=3)
    st = line_state(env, [0.0, 4.0, -1.0, 2.5, 1.5])  # from drone 0: 2 (1.0), 4 (1.5), 3 (2.5), 1 (4.0)
    f = env.layout.split(env.observe().astype(np.float64))
    order = [2, 4, 3]
    np.testing.assert_allclose(f["neighbor.rel_pos"][0], st["pos"][order] - st["pos"][0], atol=1e-6)
    np.testing.assert_allclose(f["neighbor.rel_vel"][0], st["vel"][order] - st["vel"][0], atol=1e-6)
    np.testing.assert_allclose(ObsLayout.as_matrix(f["neighbor.rot"][0]), st["rot"][order], atol=1e-6)
    np.testing.assert_allclose(f["neighbor.omega"][0], st["omega"][order], atol=1e-6)
    np.testing.assert_allclose(f["neighbor.goal_offset"][0], st["goal"][order] - st["pos"][order], atol=1e-6)
    np.testing.assert_array_equal(f["mask"], 1.0)
    # brute force for every drone: the K nearest by distance
    for i in range(5):
        d = np.abs(st["pos"][:, 0] - st["pos"][i, 0])
        d[i] = np.inf
        expect = np.argsort(d, kind="stable")[:3]
        np.testing.assert_allclose(f["neighbor.rel_pos"][i], st["pos"][expect] - st["pos"][i], atol=1e-6)


def test_ties_go_to_the_lower_index(quiet_cfg):
    env = make_env(quiet_cfg, 5, k=2)
    st = line_state(env, [0.0, -1.0, 1.0, 2.0, -2.0])  # drones 1 and 2 tie for drone 0, and 3 and 4
    f = env.layout.split(env.observe().astype(np.float64))
    np.testing.assert_allclose(f["neighbor.rel_pos"][0], st["pos"][[1, 2]] - st["pos"][0], atol=1e-6)
    env = make_env(quiet_cfg, 5, k=4)
    st = line_state(env, [0.0, -1.0, 1.0, 2.0, -2.0])
    f = env.layout.split(env.observe().astype(np.float64))
    np.testing.assert_allclose(f["neighbor.rel_pos"][0], st["pos"][[1, 2, 3, 4]] - st["pos"][0], atol=1e-6)


def test_missing_neighbours_are_masked_and_zero(quiet_cfg):
    env = make_env(quiet_cfg, 3, k=6)  # only 2 real neighbours
    line_state(env, [0.0, 1.0, 2.0])
    f = env.layout.split(env.observe())
    np.testing.assert_array_equal(f["mask"], np.tile([1, 1, 0, 0, 0, 0], (3, 1)))
    nb = env.layout.neighbors(env.observe())
    assert np.all(nb[:, 2:] == 0) and np.all(np.abs(nb[:, :2]).sum(-1) > 0)


def test_single_drone_and_zero_slots(quiet_cfg):
    env = make_env(quiet_cfg, 1, k=6)
    line_state(env, [0.0])
    assert np.all(env.layout.split(env.observe())["mask"] == 0)
    env = make_env(quiet_cfg, 4, k=0)
    line_state(env, [0.0, 1.0, 2.0, 3.0])
    assert env.obs_dim == 18 and env.observe().shape == (4, 18)


def test_sensing_radius_masks_far_neighbours(quiet_cfg):
    env = make_env(quiet_cfg, 5, k=3, sensing_radius=1.6)
    st = line_state(env, [0.0, 4.0, -1.0, 2.5, 1.5])
    f = env.layout.split(env.observe().astype(np.float64))
    np.testing.assert_array_equal(f["mask"][0], [1, 1, 0])  # 1.0 and 1.5 m in range; 2.5 m is not
    np.testing.assert_allclose(f["neighbor.rel_pos"][0, :2], st["pos"][[2, 4]] - st["pos"][0], atol=1e-6)
    assert np.all(f["neighbor.rel_pos"][0, 2] == 0)
    np.testing.assert_array_equal(f["mask"][1], [1, 0, 0])  # drone 1 (x = 4) sees only drone 3 (x = 2.5)
    np.testing.assert_allclose(f["neighbor.rel_pos"][1, 0], st["pos"][3] - st["pos"][1], atol=1e-6)


def test_pos_vel_variant(quiet_cfg):
    env = make_env(quiet_cfg, 3, k=2, neighbor_obs="pos_vel")
    st = line_state(env, [0.0, 1.0, 3.0])
    assert env.layout.neighbor_dim == 6 and env.obs_dim == 18 + 2 * 6 + 2
    f = env.layout.split(env.observe().astype(np.float64))
    np.testing.assert_allclose(f["neighbor.rel_pos"][0], st["pos"][[1, 2]] - st["pos"][0], atol=1e-6)
    np.testing.assert_allclose(f["neighbor.rel_vel"][0], st["vel"][[1, 2]] - st["vel"][0], atol=1e-6)


def test_rotating_the_world_transforms_the_observation_by_the_layout(quiet_cfg):
    """World vectors rotate (Q v), rotations are left-multiplied (Q R), body fields do not change."""
    rng = np.random.default_rng(5)
    n = 6
    env = make_env(quiet_cfg, n, k=4, sensing_radius=2.0)
    st = dict(pos=rng.uniform(-1, 1, (n, 3)) + [0, 0, 4], vel=rng.normal(size=(n, 3)),
              rot=np.stack([random_rotation(rng) for _ in range(n)]), omega=rng.normal(size=(n, 3)),
              goal=rng.uniform(-1, 1, (n, 3)) + [0, 0, 4])
    env.set_state(**st)
    obs = env.observe().astype(np.float64).copy()
    Q, t = random_rotation(rng), np.array([0.3, -0.2, 0.1])
    centre = np.array([0, 0, 4.0])
    moved = dict(pos=(st["pos"] - centre) @ Q.T + centre + t, vel=st["vel"] @ Q.T, rot=Q @ st["rot"],
                 omega=st["omega"], goal=(st["goal"] - centre) @ Q.T + centre + t)
    env.set_state(**moved)
    obs_moved = env.observe().astype(np.float64)
    np.testing.assert_allclose(obs_moved, env.layout.transform(obs, Q), atol=2e-6)
    f0, f1 = env.layout.split(obs), env.layout.split(obs_moved)
    np.testing.assert_allclose(f1["self.omega"], f0["self.omega"], atol=1e-6)  # body: invariant
    np.testing.assert_allclose(f1["neighbor.omega"], f0["neighbor.omega"], atol=1e-6)
    np.testing.assert_array_equal(f1["mask"], f0["mask"])
    assert np.abs(f1["self.vel"] - f0["self.vel"]).max() > 0.1  # world vectors really moved
    assert 0 < f0["mask"].sum() < f0["mask"].size  # the sensing radius masked some, not all


def test_sensor_noise_only_on_own_state(quiet_cfg):
    env = make_env(quiet_cfg, 3, k=2, sensor_noise=True)
    st = line_state(env, [0.0, 1.0, 3.0])
    f = env.layout.split(env.observe().astype(np.float64))
    err_pos = f["self.rel_goal"] - (st["pos"] - st["goal"])
    err_w = f["self.omega"] - st["omega"]
    assert 1e-4 < np.abs(err_pos).max() < 0.03 and 0 < np.abs(err_w).max() < 1e-3
    np.testing.assert_allclose(ObsLayout.as_matrix(f["self.rot"]), st["rot"], atol=1e-6)
    np.testing.assert_allclose(f["neighbor.rel_pos"][0], st["pos"][[1, 2]] - st["pos"][0], atol=1e-6)


@pytest.mark.parametrize("radius", [None, 0.6])
def test_k_nearest_at_128_drones_match_brute_force(quiet_cfg, radius):
    n, k = 128, 6
    env = make_env(quiet_cfg, n, k=k, sensing_radius=radius)
    rng = np.random.default_rng(11)
    pos = rng.uniform([-2, -2, 1], [2, 2, 4], (n, 3))
    pos[[7, 5, 9]] = [[0.5, 0.5, 2.0], [0.625, 0.5, 2.0], [0.375, 0.5, 2.0]]  # exact tie: 5 and 9 for drone 7
    assert np.sort(np.linalg.norm(pos - pos[7], axis=1))[3] > 0.125  # nobody else as close
    env.set_state(pos=pos, vel=rng.normal(size=(n, 3)), goal=pos)
    f = env.layout.split(env.observe().astype(np.float64))
    d2 = ((pos[:, None] - pos[None]) ** 2).sum(-1)
    for i in range(n):
        others = np.delete(np.arange(n), i)
        order = others[np.lexsort((others, d2[i, others]))][:k]
        if radius is not None:
            order = order[d2[i, order] <= radius ** 2]
        m = len(order)
        np.testing.assert_array_equal(f["mask"][i], [1] * m + [0] * (k - m))
        np.testing.assert_allclose(f["neighbor.rel_pos"][i, :m], pos[order] - pos[i], atol=1e-6)
    assert f["neighbor.rel_pos"][7, 0] == pytest.approx(pos[5] - pos[7], abs=1e-6)  # lower index first
