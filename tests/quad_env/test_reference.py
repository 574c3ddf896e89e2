"""The numba step kernel equals the plain-numpy float64 reference on random states (noise off), in both
collision forms of the reward."""
import numpy as np
import pytest

from quad_env import REWARD_TERMS, VecQuadEnv
from quad_env.params import KERNEL_TERMS, T_COLLISION, T_FLOOR, T_PROXIMITY, T_TILT, pack_params
from quad_env.kernels import NUM_ACC, StepOutput, SwarmState, step_kernel
from quad_env.reference import reference_step
from quad_env.rng import seed_streams


def random_rotations(rng, m):
    q, r = np.linalg.qr(rng.normal(size=(m, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q


def random_state(rng, E, N):
    """Random drones packed close enough for collisions, proximity and downwash; some at the floor and walls."""
    M = E * N
    pos = rng.uniform([-0.6, -0.6, 0.0], [0.6, 0.6, 1.2], (M, 3))
    vel = rng.uniform(-3, 3, (M, 3))
    rot = random_rotations(rng, M)
    for e in range(E):
        b = e * N
        pos[b + 1] = pos[b] + rng.normal(size=3) * 0.03  # touching pair
        vel[b + 1] = vel[b] - 2.0 * (pos[b + 1] - pos[b]) / 0.03  # ... approaching
        pos[b + 2] = pos[b + 3] - rot[b + 3][:, 2] * 0.3  # below drone 3's rotor axis: downwash
        pos[b + 3, 2] = max(pos[b + 3, 2], 0.5)
        pos[b + 2] = pos[b + 3] - rot[b + 3][:, 2] * 0.3
        pos[b + 4] = [4.99, -4.99, 0.05]  # corner, near the floor
        vel[b + 4] = [3.0, -3.0, -3.0]
    return dict(pos=pos, vel=vel, rot=rot, omega=rng.uniform(-45, 45, (M, 3)), motor=rng.uniform(0, 1, (M, 4)),
                goal=rng.uniform(-2, 2, (M, 3)))


def kernel_step(env, state, actions, step_count, contact, out_dtype=np.float64):
    """Run the kernel on copies of ``state`` with ``out_dtype`` output buffers (float64: compared to 1e-9), with
    the env config's parameters and every noise source off (``pack_params(..., noise=False)``: the random streams
    are then never read)."""
    s = {k: v.copy() for k, v in state.items()}
    M, D, E = env.num_drones, env.obs_dim, env.num_envs
    fp, ip = pack_params(env.cfg, D, noise=False)
    ou = np.zeros((M, 4), s["pos"].dtype)  # the simulator keeps its noise state in its own dtype
    contact = contact.copy()
    steps = step_count.copy()
    obs, rew, terms = np.zeros((M, D), out_dtype), np.zeros(M, out_dtype), np.zeros((KERNEL_TERMS, M), out_dtype)
    state = SwarmState(pos=s["pos"], vel=s["vel"], rot=s["rot"], omega=s["omega"], motor=s["motor"], ou=ou,
                       goal=s["goal"], contact=contact, room_contact=np.zeros(M, np.uint8), rng=seed_streams(0, E),
                       step_count=steps)
    out = StepOutput(obs=obs, rew=rew, terms=terms, done=np.zeros(E, bool), diverged=np.zeros(E, bool))
    step_kernel(actions, state, fp, ip, out, np.zeros((E, NUM_ACC)))
    return s, obs, rew, terms, contact


CASES = [
    dict(num_agents=5, num_neighbors=3, neighbor_obs="full"),
    dict(num_agents=5, num_neighbors=6, neighbor_obs="pos_vel", sensing_radius=0.5),
    dict(num_agents=6, num_neighbors=2, neighbor_obs="full", drag_coeff=0.02, downwash=False,
         reward=dict(floor=1.5, tilt=0.8, goal=1.2, goal_radius=2.0, height=0.7, centre=0.9)),  # optional shaping
]


def other_form(case, form):
    return {**case, "reward": {**case.get("reward", {}), "collision_form": form}}


@pytest.mark.parametrize("form", ["paper", "pairwise"])
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("steps_done", [0, 49])  # 49: this step re-orthonormalises (every 50)
def test_kernel_matches_numpy_reference(quiet_cfg, case, steps_done, form):
    case = other_form(case, form)
    cfg = quiet_cfg(**case)
    E, N = 3, cfg.num_agents
    env = VecQuadEnv(cfg, num_envs=E, seed=0)
    rng = np.random.default_rng(steps_done + len(case))
    events = dict(collisions=0, floor=0, clipped=0, downwash=0, forms_differ=0, touching_before=0)
    for trial in range(4):
        state = random_state(rng, E, N)
        actions = rng.uniform(-1.3, 1.3, (env.num_drones, 4))
        step_count = np.full(E, steps_done, np.int64)
        # contact memory: none on even trials; on odd ones random pairs, among them the touching pair (0, 1)
        # of some swarms (a drone already touching one that touches another: no new charge in the paper's form)
        contact = np.zeros((E, N, N), np.uint8)
        if trial % 2:
            contact[:] = np.triu(rng.uniform(size=(E, N, N)) < 0.4, 1)
            events["touching_before"] += int(contact[:, 0, 1].sum())
        ks, kobs, krew, kterms, kcontact = kernel_step(env, state, actions, step_count, contact)
        rs, robs, rrew, rterms, rcontact = reference_step(state, actions, cfg, step_count, contact)
        for name in ("pos", "vel", "rot", "omega", "motor"):
            np.testing.assert_allclose(ks[name], rs[name], rtol=0, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(kobs, robs, rtol=0, atol=1e-9)
        np.testing.assert_allclose(kterms, rterms, rtol=0, atol=1e-9)
        np.testing.assert_allclose(krew, rrew, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(kcontact, rcontact)
        events["collisions"] += int((rterms[1] < 0).sum())
        flipped = quiet_cfg(**other_form(case, "pairwise" if form == "paper" else "paper"))
        events["forms_differ"] += int((np.abs(reference_step(state, actions, flipped, step_count, contact)[3]
                                              - rterms)[1:3].max(0) > 1e-9).sum())
        events["floor"] += int((np.abs(rs["pos"][:, 2] - 0.046) < 1e-12).sum())
        events["clipped"] += int((np.abs(rs["omega"]) == 40.0).sum())
        if cfg.downwash:
            no_dw = quiet_cfg(**{**case, "downwash": False})
            events["downwash"] += int((np.abs(reference_step(state, actions, no_dw, step_count, contact)[0]["vel"]
                                              - rs["vel"]).max(1) > 1e-6).sum())
    if not cfg.downwash:
        events.pop("downwash")
    assert all(v > 0 for v in events.values()), events  # the random states exercise every branch


def test_float32_state_tracks_the_reference(quiet_cfg):
    """The float32 fast path runs the same kernel: it agrees with the reference to float32 precision."""
    cfg = quiet_cfg(num_agents=5, num_neighbors=3, sim_dtype="float32")
    env = VecQuadEnv(cfg, num_envs=2, seed=0)
    rng = np.random.default_rng(1)
    state = random_state(rng, 2, 5)
    state["pos"][:, 2] += 1.0  # away from the floor, where rounding may decide landing
    state32 = {k: v.astype(np.float32) for k, v in state.items()}
    actions = rng.uniform(-1, 1, (10, 4)).astype(np.float32)
    contact = np.zeros((2, 5, 5), np.uint8)
    # the simulator's own float32 output buffers: the kernel specialization a float32 env runs (compiled once by
    # quad_env.warmup, not again for this test)
    ks, kobs, _, _, _ = kernel_step(env, state32, actions, np.zeros(2, np.int64), contact, out_dtype=np.float32)
    rs, robs, _, _, _ = reference_step({k: v.astype(np.float64) for k, v in state32.items()}, actions, cfg,
                                       np.zeros(2, np.int64), contact)
    assert ks["pos"].dtype == np.float32
    for name in ("pos", "vel", "rot", "motor"):
        np.testing.assert_allclose(ks[name], rs[name], rtol=1e-5, atol=1e-5, err_msg=name)
    np.testing.assert_allclose(ks["omega"], rs["omega"], rtol=1e-4, atol=1e-3)


def test_reference_catches_a_wrong_kernel_constant(quiet_cfg):
    """The comparison is sharp: a 1% heavier drone in the kernel is detected."""
    cfg = quiet_cfg(num_agents=5, num_neighbors=3)
    env = VecQuadEnv(cfg, num_envs=1, seed=0)
    heavier = quiet_cfg(num_agents=5, num_neighbors=3, physics=dict(mass=0.028 * 1.01))
    rng = np.random.default_rng(3)
    state = random_state(rng, 1, 5)
    actions = rng.uniform(-1, 1, (5, 4))
    contact = np.zeros((1, 5, 5), np.uint8)
    ks, *_ = kernel_step(env, state, actions, np.zeros(1, np.int64), contact)
    rs, *_ = reference_step(state, actions, heavier, np.zeros(1, np.int64), contact)
    assert np.abs(ks["vel"] - rs["vel"]).max() > 1e-6


def touching_pairs(pos, E, N, dist):
    """uint8 [E, N, N]: 1 for the pairs a < b whose centres are within ``dist`` (the contact memory the step kernel
    keeps: it is set from the positions at the end of each step, and by set_state)."""
    p = pos.reshape(E, N, 3)
    d2 = ((p[:, None, :, :] - p[:, :, None, :]) ** 2).sum(-1)  # [E, a, b]: (x_b - x_a)^2 + ..., x first, as the kernel
    return ((d2 <= dist * dist) & np.triu(np.ones((N, N), bool), 1)).astype(np.uint8)


@pytest.mark.parametrize("form", ["paper", "pairwise"])
def test_a_seeded_episode_sums_the_reference_terms(quiet_cfg, form):
    """A fixed-seed episode through ``VecQuadEnv.step`` (the kernels' argument bundles, as in training): at every
    step the reward terms equal the float64 reference recomputed from the state before it, and the episode's
    per-term sums (``rew_<term>``) equal the sums of the reference's terms. A swapped kernel argument fails."""
    cfg = quiet_cfg(num_agents=6, num_neighbors=3, sim_dtype="float64", episode_duration=0.6,  # 60 steps: reortho
                    reward=dict(collision_form=form, floor=1.5, tilt=0.8, goal=1.2, goal_radius=2.0, height=0.7,
                                centre=0.9))
    E, N = 2, cfg.num_agents
    env = VecQuadEnv(cfg, num_envs=E, seed=11)
    rng = np.random.default_rng(5)
    start = random_state(rng, E, N)  # packed: proximity, downwash, walls and floor
    for b in range(0, E * N, N):  # drones 0 and 1 approach, not yet touching: a new collision
        start["pos"][b + 1] = start["pos"][b] + 3.0 * (start["pos"][b + 1] - start["pos"][b])
    env.set_state(**start)
    sums = np.zeros((KERNEL_TERMS, E))
    names = REWARD_TERMS[:KERNEL_TERMS]
    for t in range(cfg.episode_steps):
        s = env.get_state()
        before = dict(pos=s.pos, vel=s.vel, rot=s.rot, omega=s.omega, motor=s.motor, goal=s.goal)
        actions = rng.uniform(-1.2, 1.2, (E * N, 4))
        step_count = np.full(E, t, np.int64)  # steps since the reset (set_state keeps the clock)
        rs, _, rrew, rterms, _ = reference_step(before, actions, cfg, step_count,
                                                touching_pairs(s.pos, E, N, cfg.physics.collision_dist))
        _, rew, _, truncated = env.step(actions)
        terms = np.stack([env.reward_terms[name] for name in names])  # float32 buffers
        np.testing.assert_allclose(terms, rterms, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(rew, rrew, rtol=1e-6, atol=1e-6)
        assert (env.reward_terms["crash"] == 0).all()
        if not truncated.any():  # (the last step auto-resets the swarms)
            np.testing.assert_allclose(env.get_state().pos, rs["pos"], rtol=0, atol=1e-9)
        sums += rterms.reshape(KERNEL_TERMS, E, N).sum(2)
    stats = env.pop_episode_stats()
    assert len(stats) == E and truncated.all()
    for e, st in enumerate(stats):
        for k, name in enumerate(names):
            assert st[f"rew_{name}"] == pytest.approx(sums[k, e] / N, rel=1e-6, abs=1e-9), name
        assert st["rew_crash"] == 0.0
        assert st["return"] == pytest.approx(sums[:, e].sum() / N, rel=1e-6)
    for term in (T_COLLISION, T_PROXIMITY, T_FLOOR, T_TILT):  # the run exercises the event terms
        assert (sums[term] < 0).any(), names[term]
