"""Reward terms on hand-computed cases; collisions are penalised once per contact (per drone entering contact
in the paper's collision form, per new pair in the "pairwise" one); the paper's proximity sum runs over the
observed neighbours only."""
import numpy as np
import pytest

from quad_env import REWARD_TERMS, VecQuadEnv

DT = 0.01  # control dt


def test_reward_terms_hand_computed(quiet_cfg):
    cfg = quiet_cfg(num_agents=3, num_neighbors=2, drag_coeff=0.0)
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    hover = 1 / 1.9
    # drones 0, 1: resting on the floor 0.1 m apart, motors off; drone 2: hovering at z = 5, yawing at 3 rad/s
    env.set_state(pos=[[0, 0, 0.046], [0.1, 0, 0.046], [2, 2, 5]], vel=np.zeros((3, 3)),
                  rot=np.tile(np.eye(3), (3, 1, 1)), omega=[[0, 0, 0], [0, 0, 0], [0, 0, 3.0]],
                  motor=[[0, 0, 0, 0], [0, 0, 0, 0], [np.sqrt(hover)] * 4],
                  goal=[[0, 0, 1.046], [0.1, 2, 0.046], [2, 2, 4.5]])
    a_hover = 2 * hover - 1
    actions = np.array([[-1.0] * 4, [-1.0] * 4, [a_hover] * 4])
    _, rew, _, _ = env.step(actions)
    t = env.reward_terms
    prox = 1 - 0.1 / 0.184
    expected = {
        "pos": [-0.5 * DT * 1.0, -0.5 * DT * 2.0, -0.5 * DT * 0.5],
        "collision": [0.0, 0.0, 0.0],
        "proximity": [-5 * DT * prox, -5 * DT * prox, 0.0],
        "omega": [0.0, 0.0, -0.01 * DT * 3.0],
        "action": [-0.05 * DT * 2.0, -0.05 * DT * 2.0, -0.05 * DT * 2 * abs(a_hover)],
        "floor": [0.0, 0.0, 0.0],  # shaping terms are off by default (the paper's reward)
        "tilt": [0.0, 0.0, 0.0],
    }
    assert set(t) == set(REWARD_TERMS)
    for name, values in expected.items():
        np.testing.assert_allclose(t[name], values, rtol=1e-6, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(rew, sum(np.asarray(v) for v in expected.values()), rtol=1e-6)
    np.testing.assert_allclose(rew, sum(t[k] for k in REWARD_TERMS), rtol=1e-6)
    assert rew.dtype == np.float32 and all(v.dtype == np.float32 for v in t.values())


def test_actions_are_clipped_before_the_action_penalty(quiet_cfg):
    env = VecQuadEnv(quiet_cfg(num_agents=1, num_neighbors=0), num_envs=1, seed=0)
    env.step(np.full((1, 4), 7.0))
    assert env.reward_terms["action"][0] == pytest.approx(-0.05 * DT * 2.0, rel=1e-6)


def test_coefficients_come_from_the_config(quiet_cfg):
    cfg = quiet_cfg(num_agents=1, num_neighbors=0, reward=dict(pos=2.0, action=0.0))
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    env.set_state(pos=[[0, 0, 0.046]], vel=np.zeros((1, 3)), rot=[np.eye(3)], motor=np.zeros((1, 4)),
                  goal=[[0, 3, 4.046]])
    env.step(-np.ones((1, 4)))
    assert env.reward_terms["pos"][0] == pytest.approx(-2.0 * DT * 5.0, rel=1e-6)
    assert env.reward_terms["action"][0] == 0.0


def test_floor_and_tilt_shaping_terms(quiet_cfg):
    """Two drones on the floor (one level, one resting is always levelled) and one in the air tilted by
    60 degrees about x: the floor term hits only the grounded drones, the tilt term is 1 - cos(tilt)."""
    cfg = quiet_cfg(num_agents=3, num_neighbors=0, drag_coeff=0.0, reward=dict(floor=2.0, tilt=0.7))
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    c, s = np.cos(np.pi / 3), np.sin(np.pi / 3)
    tilted = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    env.set_state(pos=[[0, 0, 0.046], [1, 0, 0.046], [2, 2, 5]], vel=np.zeros((3, 3)),
                  rot=[np.eye(3), np.eye(3), tilted], omega=np.zeros((3, 3)), motor=np.zeros((3, 4)),
                  goal=[[0, 0, 1], [1, 0, 1], [2, 2, 5]])
    env.step(-np.ones((3, 4)))  # motors off: the grounded drones stay, the tilted one falls but keeps its attitude
    t = env.reward_terms
    np.testing.assert_allclose(t["floor"], [-2.0 * DT, -2.0 * DT, 0.0], rtol=1e-6)
    np.testing.assert_allclose(t["tilt"], [0.0, 0.0, -0.7 * DT * (1 - c)], rtol=1e-5, atol=1e-9)


def _hover_step_terms(quiet_cfg, pos, goal, reward):
    """Reward terms of one hover step of three level, still drones at ``pos`` with goals ``goal`` (their sum checked
    against the reward)."""
    hover = 1 / 1.9
    env = VecQuadEnv(quiet_cfg(num_agents=3, num_neighbors=0, drag_coeff=0.0, reward=reward), num_envs=1, seed=0)
    env.set_state(pos=pos, vel=np.zeros((3, 3)), rot=np.tile(np.eye(3), (3, 1, 1)), omega=np.zeros((3, 3)),
                  motor=np.full((3, 4), np.sqrt(hover)), goal=goal)
    _, rew, _, _ = env.step(np.full((3, 4), 2 * hover - 1))
    np.testing.assert_allclose(rew, sum(env.reward_terms[k] for k in REWARD_TERMS), rtol=1e-6)
    return env.reward_terms


@pytest.mark.parametrize("radius", [0.5, 1.2])
def test_goal_bonus_inside_its_radius_only(quiet_cfg, radius):
    """Three hovering drones 0.3, 0.7 and 1.5 m from their goals: the bonus c dt goes to those strictly inside
    ``goal_radius``; off by default (the paper's reward)."""
    pos = np.array([[0, 0, 2.0], [2, 0, 2.0], [0, 2, 2.0]])
    goal = pos + np.array([[0.3, 0, 0], [0, 0.7, 0], [0, 0, 1.5]])

    def goal_term(**reward):
        return _hover_step_terms(quiet_cfg, pos, goal, reward)["goal"]

    inside = np.array([0.3, 0.7, 1.5]) < radius  # one hover step moves a drone by < 1e-3 m
    np.testing.assert_allclose(goal_term(goal=2.0, goal_radius=radius), 2.0 * DT * inside, rtol=1e-6)
    assert (goal_term() == 0).all()


def test_height_term_charges_the_vertical_offset_alone(quiet_cfg):
    """Three hovering drones offset from their goals by 0.3 m sideways, 0.4 m above and 1.5 m below (and 0.2 m
    sideways): the term is -c dt |z - z^d|, nothing for the sideways part; off by default (the paper's reward)."""
    pos = np.array([[0, 0, 2.0], [2, 0, 2.0], [0, 2, 2.0]])
    goal = pos - np.array([[0.3, 0, 0], [0, 0, 0.4], [0.2, 0, -1.5]])

    def terms(**reward):
        return _hover_step_terms(quiet_cfg, pos, goal, reward)

    with_height = terms(height=0.8)  # one hover step moves a drone by < 1e-3 m
    np.testing.assert_allclose(with_height["height"], -0.8 * DT * np.array([0.0, 0.4, 1.5]), atol=1e-6)
    np.testing.assert_allclose(with_height["pos"], -0.5 * DT * np.array([0.3, 0.4, np.hypot(0.2, 1.5)]), rtol=1e-3)
    assert (terms()["height"] == 0).all()
    with pytest.raises(ValueError, match="env.reward.height must be >= 0"):
        quiet_cfg(reward=dict(height=-1.0)).validate()


def test_centre_term_charges_the_swarms_mean_offset_not_its_spread(quiet_cfg):
    """Three hovering drones on a 0.3-m ring about one shared goal: the ring centred on it costs nothing (c1 still
    charges each drone its 0.3 m); the same ring 0.2 m too high costs every drone -c dt 0.2 (c1: each drone only
    sqrt(0.3^2 + 0.2^2) - 0.3 = 0.06 m more); with a goal per drone, the norm of the mean offset. Off by default."""
    ring = 0.3 * np.array([[1.0, 0, 0], [-0.5, np.sqrt(0.75), 0], [-0.5, -np.sqrt(0.75), 0]])
    goal = np.tile([1.0, 1.0, 2.0], (3, 1))

    def terms(pos, goal, **reward):
        return _hover_step_terms(quiet_cfg, pos, goal, reward)

    centred = terms(goal + ring, goal, centre=0.8)  # one hover step moves a drone by < 1e-3 m
    np.testing.assert_allclose(centred["centre"], 0.0, atol=1e-5)
    np.testing.assert_allclose(centred["pos"], -0.5 * DT * 0.3, rtol=1e-3)
    lifted = terms(goal + ring + [0, 0, 0.2], goal, centre=0.8)
    np.testing.assert_allclose(lifted["centre"], -0.8 * DT * 0.2, rtol=1e-3)
    np.testing.assert_allclose(lifted["pos"], -0.5 * DT * np.hypot(0.3, 0.2), rtol=1e-3)
    pos = np.array([[0, 0, 2.0], [2, 0, 2.0], [0, 2, 2.0]])
    own_goals = pos - np.array([[0.3, 0, 0], [0, 0, 0.6], [0.3, 0, -1.5]])  # mean offset (0.2, 0, -0.3)
    np.testing.assert_allclose(terms(pos, own_goals, centre=0.8)["centre"], -0.8 * DT * np.hypot(0.2, 0.3), rtol=1e-3)
    assert (terms(pos, own_goals)["centre"] == 0).all()
    with pytest.raises(ValueError, match="env.reward.centre must be >= 0"):
        quiet_cfg(reward=dict(centre=-1.0)).validate()


def test_goal_radius_must_be_positive(quiet_cfg):
    with pytest.raises(ValueError, match="env.reward.goal_radius"):
        quiet_cfg(reward=dict(goal=1.0, goal_radius=0.0)).validate()
    with pytest.raises(ValueError, match="env.reward.goal must be >= 0"):
        quiet_cfg(reward=dict(goal=-1.0)).validate()


def approach(quiet_cfg, restitution, steps=30):
    """Two hovering drones 0.3 m apart flying at each other at 0.5 m/s each; returns the collision terms."""
    cfg = quiet_cfg(num_agents=2, num_neighbors=1, drag_coeff=0.0,
                    physics=dict(collision_restitution=restitution))
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    hover = 1 / 1.9
    env.set_state(pos=[[0, 0, 5], [0.3, 0, 5]], vel=[[0.5, 0, 0], [-0.5, 0, 0]], rot=np.tile(np.eye(3), (2, 1, 1)),
                  omega=np.zeros((2, 3)), motor=np.full((2, 4), np.sqrt(hover)), goal=[[0, 0, 5], [0.3, 0, 5]])
    hits, dists = [], []
    for _ in range(steps):
        env.step(np.full((2, 4), 2 * hover - 1))
        hits.append(env.reward_terms["collision"].copy())
        s = env.get_state()
        dists.append(np.linalg.norm(s.pos[1] - s.pos[0]))
    return np.array(hits), np.array(dists)


def test_collision_penalised_once_per_contact_then_bounce(quiet_cfg):
    hits, dists = approach(quiet_cfg, restitution=0.75)
    assert (hits == -5.0).sum(0).tolist() == [1, 1]  # each drone: -5 exactly once
    assert set(np.unique(hits)) == {0.0, -5.0}
    first = np.flatnonzero(hits[:, 0])[0]
    assert dists[first] <= 0.092 < dists[first - 1]  # at the first step within the contact distance
    assert dists[-1] > 0.092  # they bounced apart


def test_lingering_contact_is_not_penalised_again(quiet_cfg):
    hits, dists = approach(quiet_cfg, restitution=0.0)  # fully inelastic: they stay touching
    assert (dists[-10:] <= 0.092).all()
    assert (hits == -5.0).sum(0).tolist() == [1, 1]


def test_pairwise_proximity_term_counts_every_close_drone(quiet_cfg):
    env = VecQuadEnv(quiet_cfg(num_agents=3, num_neighbors=0, reward=dict(collision_form="pairwise")), num_envs=1,
                     seed=0)
    env.set_state(pos=[[0, 0, 0.046], [0.1, 0, 0.046], [0, 0.15, 0.046]], vel=np.zeros((3, 3)),
                  rot=np.tile(np.eye(3), (3, 1, 1)), motor=np.zeros((3, 4)), goal=np.zeros((3, 3)))
    env.step(-np.ones((3, 4)))
    d12 = np.hypot(0.1, 0.15)
    pen = lambda d: max(0.0, 1 - d / 0.184)  # noqa: E731
    expected = -5 * DT * np.array([pen(0.1) + pen(0.15), pen(0.1) + pen(d12), pen(0.15) + pen(d12)])
    np.testing.assert_allclose(env.reward_terms["proximity"], expected, rtol=1e-6)


def hover_swarm(quiet_cfg, form, pos, vel, num_neighbors=2):
    """Level drones at ``pos`` with velocities ``vel``, motors at hover, goals where they are."""
    n = len(pos)
    cfg = quiet_cfg(num_agents=n, num_neighbors=num_neighbors, drag_coeff=0.0, downwash=False,
                    physics=dict(collision_restitution=0.0), reward=dict(collision_form=form))
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    hover = 1 / 1.9
    env.set_state(pos=pos, vel=vel, rot=np.tile(np.eye(3), (n, 1, 1)), omega=np.zeros((n, 3)),
                  motor=np.full((n, 4), np.sqrt(hover)), goal=pos)
    env.hover_action = np.full((n, 4), 2 * hover - 1)
    return env


@pytest.mark.parametrize("form,expected", [("paper", [-5.0, -5.0, -5.0]), ("pairwise", [-10.0, -5.0, -5.0])])
def test_touching_two_drones_at_once(quiet_cfg, form, expected):
    """Drones 1 and 2 fly into drone 0 from both sides and touch it in the same step: the paper charges c2
    once per drone that enters contact, the pairwise form once per new pair (drone 0 is in two)."""
    env = hover_swarm(quiet_cfg, form, pos=[[0, 0, 5], [0.1, 0, 5], [-0.1, 0, 5]],
                      vel=[[0, 0, 0], [-2.0, 0, 0], [2.0, 0, 0]])
    env.step(env.hover_action)
    d = np.linalg.norm(env.get_state().pos[1:] - env.get_state().pos[0], axis=1)
    assert (d <= 0.092).all()
    np.testing.assert_allclose(env.reward_terms["collision"], expected)


@pytest.mark.parametrize("form,expected", [("paper", [0.0, 0.0, -5.0]), ("pairwise", [-5.0, 0.0, -5.0])])
def test_a_second_contact_while_touching(quiet_cfg, form, expected):
    """Drone 0 already touches drone 1 (at rest, 0.05 m apart) when drone 2 flies into it: in the paper's form
    drone 0's collision status does not change, so only drone 2 pays."""
    env = hover_swarm(quiet_cfg, form, pos=[[0, 0, 5], [0.05, 0, 5], [-0.1, 0, 5]],
                      vel=[[0, 0, 0], [0, 0, 0], [2.0, 0, 0]])
    env.step(env.hover_action)
    d = np.linalg.norm(env.get_state().pos[1:] - env.get_state().pos[0], axis=1)
    assert (d <= 0.092).all()
    np.testing.assert_allclose(env.reward_terms["collision"], expected)
    env.step(env.hover_action)  # still touching both: nothing more in either form
    np.testing.assert_allclose(env.reward_terms["collision"], 0.0)


@pytest.mark.parametrize("form", ["paper", "pairwise"])
@pytest.mark.parametrize("sensing_radius", [None, 0.13])
def test_proximity_over_the_k_nearest_in_the_paper_form(quiet_cfg, form, sensing_radius):
    """Four drones on the floor, all within d_p = 0.184 m of drone 0 and K = 2: in the paper's form each drone
    sums over its 2 nearest drones within the sensing radius (its observed neighbours), in the pairwise
    form over all of them."""
    xy = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.12], [-0.135, 0.0]])
    pos = np.concatenate([xy, np.full((4, 1), 0.046)], axis=1)
    cfg = quiet_cfg(num_agents=4, num_neighbors=2, sensing_radius=sensing_radius,
                    reward=dict(collision_form=form))
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    env.set_state(pos=pos, vel=np.zeros((4, 3)), rot=np.tile(np.eye(3), (4, 1, 1)), motor=np.zeros((4, 4)),
                  goal=np.zeros((4, 3)))
    env.step(-np.ones((4, 4)))
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    pen = np.maximum(0.0, 1 - d / 0.184)
    np.fill_diagonal(pen, 0.0)
    assert (pen[0, 1:] > 0).all()  # drone 0 has 3 drones inside d_p, one more than K
    if form == "pairwise":
        expected = pen.sum(1)
    else:
        radius = np.inf if sensing_radius is None else sensing_radius
        expected = np.zeros(4)
        for i in range(4):
            others = [j for j in np.argsort(d[i], kind="stable") if j != i][:2]
            expected[i] = sum(pen[i, j] for j in others if d[i, j] <= radius)
        assert expected[0] < pen[0].sum()
    np.testing.assert_allclose(env.reward_terms["proximity"], -5 * DT * expected, rtol=1e-6)


@pytest.mark.parametrize("scale", [0.0, 0.3, 1.0])
def test_collision_scale_multiplies_the_collision_penalties_only(quiet_cfg, scale):
    """``set_collision_scale`` (the trainer's annealing, env.reward.collision_anneal_steps) scales c2 and c3 and
    nothing else: the same approach flown at scale 1 and at ``scale`` differs by that factor in those terms."""
    def fly(s):
        cfg = quiet_cfg(num_agents=2, num_neighbors=1, drag_coeff=0.0)
        env = VecQuadEnv(cfg, num_envs=1, seed=0)
        env.set_collision_scale(s)
        hover = 1 / 1.9
        env.set_state(pos=[[0, 0, 5], [0.3, 0, 5]], vel=[[0.5, 0, 0], [-0.5, 0, 0]],
                      rot=np.tile(np.eye(3), (2, 1, 1)), omega=np.zeros((2, 3)), motor=np.full((2, 4), np.sqrt(hover)),
                      goal=[[0, 0, 5], [0.3, 0, 5]])
        terms = []
        for _ in range(40):
            env.step(np.full((2, 4), 2 * hover - 1))
            terms.append({k: v.copy() for k, v in env.reward_terms.items()})
        return {k: np.array([t[k] for t in terms]) for k in REWARD_TERMS}, env

    full, _ = fly(1.0)
    scaled, env = fly(scale)
    assert env.collision_scale == scale
    assert (full["collision"] == -5.0).sum() == 2 and (full["proximity"] < 0).any()  # the approach collides
    for k in REWARD_TERMS:
        factor = scale if k in ("collision", "proximity") else 1.0
        np.testing.assert_allclose(scaled[k], factor * full[k], rtol=1e-6, atol=1e-12, err_msg=k)


def test_collision_scale_outside_0_1_is_refused(quiet_cfg):
    env = VecQuadEnv(quiet_cfg(num_agents=2), num_envs=1, seed=0)
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="collision scale must be in"):
            env.set_collision_scale(bad)
    assert env.collision_scale == 1.0
