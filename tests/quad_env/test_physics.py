"""Analytic physics cases through the low-level state API (every noise source off)."""
import numpy as np
import pytest

from quad_env import EnvConfig, PhysicsConfig, VecQuadEnv

G = 9.81
DT = 0.005  # physics dt
CTRL_DT = 0.01


def test_crazyflie_constants():
    p = PhysicsConfig()
    assert p.thrust_to_weight * p.mass * p.gravity / 4 == pytest.approx(0.1305, abs=5e-5)
    assert min(1.0, 0.005 / p.motor_time_constant) == pytest.approx(0.1333, abs=1e-4)
    cfg = EnvConfig()
    assert cfg.control_dt == pytest.approx(0.01) and cfg.episode_steps == 1500


def test_free_fall_motors_off(hover_env):
    env = hover_env()
    env.set_state(motor=np.zeros((1, 4)))
    off = -np.ones((1, 4))
    v_prev = env.get_state().vel[0, 2]
    for k in range(1, 101):
        s = env.simulate(off)
        assert (s.vel[0, 2] - v_prev) / CTRL_DT == pytest.approx(-G, abs=1e-9)
        v_prev = s.vel[0, 2]
    n = 200  # physics steps
    assert s.vel[0, 2] == pytest.approx(-G * n * DT, abs=1e-9)
    assert s.pos[0, 2] == pytest.approx(5.0 - G * DT * DT * n * (n - 1) / 2, abs=1e-9)
    assert np.abs(s.vel[0, :2]).max() == 0 and np.abs(s.omega).max() == 0


def test_free_fall_with_linear_drag(hover_env):
    env = hover_env(drag=0.0056)
    env.set_state(motor=np.zeros((1, 4)))
    for _ in range(100):
        s = env.simulate(-np.ones((1, 4)))
    k = 0.0056 / 0.028  # drag / mass
    v_discrete = 0.0
    for _ in range(200):
        v_discrete += DT * (-G - k * v_discrete)
    assert s.vel[0, 2] == pytest.approx(v_discrete, abs=1e-9)
    v_exact = -G / k * (1 - np.exp(-k * 1.0))  # continuous solution after 1 s
    assert s.vel[0, 2] == pytest.approx(v_exact, abs=1e-2)  # Euler error O(dt)
    assert s.vel[0, 2] > -G * 1.0 + 0.5  # drag visibly slows the fall


def test_hover_spun_up_stays_put(hover_env):
    env = hover_env()
    for _ in range(200):
        s = env.simulate(env.hover_action)
    assert np.abs(s.pos[0] - [0, 0, 5]).max() < 1e-9
    assert np.abs(s.vel).max() < 1e-9


def test_hover_after_spin_up_from_motors_off(hover_env):
    env = hover_env()
    env.set_state(motor=np.zeros((1, 4)))
    for _ in range(100):
        s0 = env.simulate(env.hover_action)
    assert s0.vel[0, 2] < -0.1  # it sagged while the motors spun up
    s1 = env.simulate(env.hover_action)
    assert np.abs((s1.vel - s0.vel) / CTRL_DT).max() < 1e-6  # now in equilibrium: a = 0
    np.testing.assert_allclose(s1.motor, np.sqrt(1 / 1.9), atol=1e-9)


def test_full_thrust_accelerates_at_0_9_g(hover_env):
    env = hover_env()
    env.set_state(motor=np.ones((1, 4)))
    s = env.simulate(np.ones((1, 4)))
    assert s.vel[0, 2] / CTRL_DT == pytest.approx(0.9 * G, abs=1e-9)
    assert np.abs(s.vel[0, :2]).max() < 1e-12 and np.abs(s.omega).max() < 1e-12
    # from motors off: after the spin-up the acceleration settles at 0.9 g too
    env = hover_env()
    env.set_state(motor=np.zeros((1, 4)))
    for _ in range(100):
        s0 = env.simulate(np.ones((1, 4)))
    s1 = env.simulate(np.ones((1, 4)))
    assert (s1.vel[0, 2] - s0.vel[0, 2]) / CTRL_DT == pytest.approx(0.9 * G, abs=1e-6)


def test_pure_yaw_torque_spins_about_z_only(hover_env):
    env = hover_env()
    tmax = 1.9 * 0.028 * G / 4
    t_hi, t_lo = 0.6 * 0.028 * G / 2, 0.4 * 0.028 * G / 2  # spin +1 motors (1, 3) stronger; sum = weight
    cmd = np.array([t_lo, t_hi, t_lo, t_hi]) / tmax
    env.set_state(motor=np.sqrt(cmd)[None])
    action = (2 * cmd - 1)[None]
    n = 20
    for _ in range(n):
        s = env.simulate(action)
    alpha = 0.006 * 2 * (t_hi - t_lo) / 2.656e-5  # tau_z / I_zz
    assert np.abs(s.omega[0, :2]).max() < 1e-12
    assert s.omega[0, 2] == pytest.approx(alpha * 2 * n * DT, rel=1e-9)
    yaw = alpha * DT * DT * np.arange(1, 2 * n + 1).sum()  # rotation uses the updated rate
    c, si = np.cos(yaw), np.sin(yaw)
    np.testing.assert_allclose(s.rot[0], [[c, -si, 0], [si, c, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(s.pos[0], [0, 0, 5], atol=1e-9)


def test_roll_torque_sign_and_axis(hover_env):
    """Motors 2, 3 sit at +y: more thrust there rolls the drone about +x (and nothing else)."""
    env = hover_env()
    hover = 1 / 1.9
    cmd = np.array([hover, hover, hover * 1.1, hover * 1.1])
    env.set_state(motor=np.sqrt(cmd)[None])
    s = env.simulate((2 * cmd - 1)[None])
    assert s.omega[0, 0] > 0
    assert abs(s.omega[0, 1]) < 1e-12 and abs(s.omega[0, 2]) < 1e-12


@pytest.mark.parametrize("w0,expected", [([100.0, 0, 0], [40.0, 0, 0]), ([0, 0, -70.0], [0, 0, -40.0])])
def test_body_rates_are_clipped(hover_env, w0, expected):
    env = hover_env()
    env.set_state(omega=np.array([w0]))
    s = env.simulate(env.hover_action)
    np.testing.assert_allclose(s.omega[0], expected, atol=1e-9)


def _tumble(env, actions):
    """Fly one drone through all actions, put back mid-air at rest every 50 steps (it stays clear of the floor
    and walls); return the worst |R^T R - I| after any step and the largest body rate seen."""
    worst, fastest = 0.0, 0.0
    for t, action in enumerate(actions):
        if t % 50 == 0:
            env.set_state(pos=[[0.0, 0.0, 5.0]], vel=[[0.0, 0.0, 0.0]])
        s = env.simulate(action)
        rot = s.rot[0]  # float64 copy of the simulator's (float32 or float64) rotation
        worst = max(worst, float(np.abs(rot.T @ rot - np.eye(3)).max()))
        fastest = max(fastest, float(np.abs(s.omega[0]).max()))
    return worst, fastest


def _tumble_env(dtype, reortho):
    cfg = EnvConfig(num_agents=1, num_neighbors=0, sim_dtype=dtype, episode_duration=1e4,
                    physics=PhysicsConfig(reortho_interval=reortho))
    return VecQuadEnv(cfg, num_envs=1, seed=0)


@pytest.mark.parametrize("dtype,tol", [("float64", 5e-14), ("float32", 2e-6)])
def test_rotation_stays_orthonormal_over_1e5_steps(dtype, tol):
    actions = np.random.default_rng(0).uniform(-1, 1, (100_000, 1, 4))
    env = _tumble_env(dtype, reortho=50)
    worst, fastest = _tumble(env, actions)
    assert fastest > 10  # it really tumbled
    assert worst < tol
    assert np.linalg.det(env.get_state().rot[0]) == pytest.approx(1.0, abs=tol)


def test_without_reorthonormalisation_float32_drifts():
    """The check above can fail: switch the re-orthonormalisation off and float32 rotations drift."""
    actions = np.random.default_rng(0).uniform(-1, 1, (20_000, 1, 4))
    worst, _ = _tumble(_tumble_env("float32", reortho=10 ** 9), actions)
    assert worst > 2e-6


def test_floor_lands_the_drone_keeping_yaw(hover_env):
    env = hover_env()
    yaw, tilt = 0.7, 0.3
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    # rolling about body x keeps the heading (first column of R), so the landing yaw is known
    env.set_state(pos=[[1.0, 2.0, 0.06]], vel=[[1.0, 0.5, -3.0]], rot=[rz @ rx], omega=[[3.0, 0.0, 0.0]],
                  motor=np.zeros((1, 4)))
    s = env.simulate(-np.ones((1, 4)))
    assert s.pos[0, 2] == pytest.approx(0.046)
    assert np.abs(s.vel).max() == 0 and np.abs(s.omega).max() == 0
    np.testing.assert_allclose(s.rot[0], rz, atol=1e-12)
    for _ in range(10):  # stays put with the motors off
        s = env.simulate(-np.ones((1, 4)))
    assert s.pos[0, 2] == pytest.approx(0.046) and np.abs(s.vel).max() == 0
    env.set_state(motor=np.ones((1, 4)))  # full thrust takes off again
    for _ in range(10):
        s = env.simulate(np.ones((1, 4)))
    assert s.pos[0, 2] > 0.05 and s.vel[0, 2] > 0


@pytest.mark.parametrize("axis,start,v", [(0, 4.999, 2.0), (0, -4.999, -2.0), (1, 4.999, 2.0), (2, 9.999, 2.0)])
def test_walls_and_ceiling_bounce_back_damped(hover_env, axis, start, v):
    env = hover_env()
    pos = np.array([[0.0, 0.0, 5.0]])
    pos[0, axis] = start
    vel = np.zeros((1, 3))
    vel[0, axis] = v
    env.set_state(pos=pos, vel=vel)
    s = env.simulate(env.hover_action)
    limit = 10.0 if axis == 2 else 5.0
    # clamped to the wall in the first physics step, then moving back for the second
    assert abs(s.pos[0, axis]) == pytest.approx(limit - 0.5 * abs(v) * DT, abs=1e-12)
    assert s.vel[0, axis] == pytest.approx(-0.5 * v, abs=1e-9)


def test_downwash_pushes_the_drone_below(hover_env):
    env = hover_env(n=3, downwash=True)
    # drone 1 is 0.35 m right below drone 0; drone 2 is 0.35 m below and 0.15 m to the side of drone 0
    env.set_state(pos=[[0, 0, 5.0], [0, 0, 4.65], [0.15, 3.0, 4.65]])
    s = env.simulate(env.hover_action)
    assert s.vel[1, 2] == pytest.approx(-2.5 * (1 - 0.35 / 0.7) * CTRL_DT, abs=1e-9)
    assert abs(s.vel[0, 2]) < 1e-9 and abs(s.vel[2, 2]) < 1e-9
    env = hover_env(n=2, downwash=False)
    env.set_state(pos=[[0, 0, 5.0], [0, 0, 4.65]])
    s = env.simulate(env.hover_action)
    assert np.abs(s.vel).max() < 1e-9


def test_downwash_follows_the_rotor_axis(hover_env):
    """A drone rolled by 90 degrees blows sideways: the drone beside it (not below) is pushed."""
    env = hover_env(n=3, downwash=True)
    roll = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])  # body z -> world -y
    env.set_state(pos=[[0, 0, 5.0], [0, 0.3, 5.0], [0, 0, 4.7]], rot=[roll, np.eye(3), np.eye(3)],
                  motor=np.zeros((3, 4)))
    s = env.simulate(-np.ones((3, 4)))  # motors off: everything else falls alike
    dv = 2.5 * (1 - 0.3 / 0.7) * CTRL_DT
    assert s.vel[1, 1] == pytest.approx(dv, abs=1e-9)  # pushed along -(body z of drone 0) = +y
    assert s.vel[2, 1] == pytest.approx(0.0, abs=1e-12) and s.vel[2, 2] == pytest.approx(s.vel[0, 2], abs=1e-12)


def test_collision_response_exchanges_normal_velocity(hover_env):
    env = hover_env(n=2)
    env.set_state(pos=[[0, 0, 5.0], [0.1, 0, 5.0]], vel=[[1.0, 0.3, 0], [-1.0, 0.3, 0]])
    s = env.simulate(env.hover_action)  # now 0.08 m apart: touching and approaching
    np.testing.assert_allclose(s.vel[0], [-0.75, 0.3, 0], atol=1e-9)
    np.testing.assert_allclose(s.vel[1], [0.75, 0.3, 0], atol=1e-9)
    assert np.abs(s.omega).max() < 1e-12  # kick off with noise off


def test_collision_kick_spins_the_drones_with_noise_on(hover_env):
    env = hover_env(n=2, physics={"collision_kick": 5.0})
    env.set_state(pos=[[0, 0, 5.0], [0.1, 0, 5.0]], vel=[[1.0, 0, 0], [-1.0, 0, 0]])
    s = env.simulate(env.hover_action, noise=True)
    assert np.linalg.norm(s.omega[0]) > 0.5 and np.linalg.norm(s.omega[1]) > 0.5
    assert not np.allclose(s.omega[0], s.omega[1])
    np.testing.assert_allclose(s.vel[0], [-0.75, 0, 0], atol=1e-9)  # the exchange itself is not random
