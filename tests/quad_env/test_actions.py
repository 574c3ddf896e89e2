"""One action check for every API: the same errors (naming agent, shape, dtype), the same clipping, the same
trajectory whatever the memory order or float width of the same values."""
from __future__ import annotations

import numpy as np
import pytest

from quad_env import EnvConfig, VecQuadEnv
from quad_env.actions import check_actions
from quad_env.adapters import QuadDroneEnv, QuadSwarmEnv, QuadSwarmParallelEnv, QuadSwarmVectorEnv

CFG = dict(num_agents=2, num_neighbors=1, thrust_noise=False, sensor_noise=False)


@pytest.mark.parametrize("bad, error, fragment", [
    (np.zeros((2, 4), complex), TypeError, "complex"),
    (np.array([["0.1"] * 4] * 2), TypeError, "real numbers"),
    (np.zeros((2, 4), bool), TypeError, "bool"),
    (np.array([[object()] * 4] * 2), TypeError, "object"),
    (np.zeros((2, 3)), ValueError, r"shape \(2, 4\), got \(2, 3\)"),
    (np.array([[0, 0, np.nan, 0], [0, 0, 0, 0]]), ValueError, r"NaN or inf \(rows \[0\]\)"),
])
def test_check_actions_refuses_with_a_specific_message(bad, error, fragment):
    with pytest.raises(error, match=fragment):
        check_actions(bad, (2, 4))


def test_huge_finite_actions_are_clipped_in_every_api_not_called_inf():
    """A finite 1e300 is a (clipped) full command everywhere, never 'NaN or inf' after a float32 cast."""
    huge, one = np.full(4, 1e300), np.ones(4)
    for name, make, wrap in [
        ("vec", lambda: VecQuadEnv(EnvConfig(**CFG), num_envs=1, seed=0), lambda a: np.stack([a, a])),
        ("gym", lambda: QuadSwarmEnv(EnvConfig(**CFG), seed=0), lambda a: np.stack([a, a])),
        ("vector", lambda: QuadSwarmVectorEnv(EnvConfig(**CFG), seed=0), lambda a: np.stack([a, a])),
        ("pettingzoo", lambda: QuadSwarmParallelEnv(EnvConfig(**CFG), seed=0),
         lambda a: {"drone_0": a, "drone_1": a}),
    ]:
        obs = []
        for action in (huge, one):
            env = make()
            env.reset(seed=1)
            out = env.step(wrap(action))
            obs.append(out[0]["drone_0"] if name == "pettingzoo" else out[0][0])
        np.testing.assert_array_equal(obs[0], obs[1], err_msg=name)


def test_one_drone_env_clips_and_checks_too():
    env = QuadDroneEnv(EnvConfig(**{**CFG, "num_agents": 1, "num_neighbors": 0}), seed=0)
    env.reset(seed=2)
    a = env.step(np.full(4, 1e300))[0]
    env.reset(seed=2)
    b = env.step(np.ones(4))[0]
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match=r"action must have shape \(4,\), got \(3,\)"):
        env.step(np.zeros(3))
    with pytest.raises(TypeError, match="complex"):
        env.step(np.zeros(4, complex))


def test_pettingzoo_names_the_agent_and_refuses_unknown_agents():
    env = QuadSwarmParallelEnv(EnvConfig(**CFG), seed=0)
    env.reset(seed=0)
    ok = {"drone_0": np.zeros(4), "drone_1": np.zeros(4)}
    with pytest.raises(ValueError, match=r"unknown agents \['drone_7'\]"):
        env.step({**ok, "drone_7": np.full(4, np.nan)})
    with pytest.raises(ValueError, match=r"action of 'drone_1' must have shape \(4,\), got \(5,\)"):
        env.step({**ok, "drone_1": np.zeros(5)})
    with pytest.raises(ValueError, match=r"action of 'drone_0' contain NaN or inf"):
        env.step({**ok, "drone_0": np.array([0, np.inf, 0, 0])})
    with pytest.raises(TypeError, match=r"action of 'drone_0' must be real numbers"):
        env.step({**ok, "drone_0": np.array(["1", "0", "0", "0"])})


def test_memory_order_and_float_width_do_not_change_the_trajectory():
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (2, 4)).astype(np.float32) for _ in range(20)]
    final = {}
    for name, convert in [("c32", lambda a: a), ("f64_c", lambda a: a.astype(np.float64)),
                          ("f64_fortran", lambda a: np.asfortranarray(a.astype(np.float64))),
                          ("f32_fortran", lambda a: np.asfortranarray(a)),
                          ("f64_strided", lambda a: np.repeat(a.astype(np.float64), 2, axis=1)[:, ::2])]:
        env = VecQuadEnv(EnvConfig(**CFG), num_envs=1, seed=3)
        env.reset()
        for a in actions:
            obs, *_ = env.step(convert(a))
        final[name] = obs.copy()
    for name in ("f64_fortran", "f64_strided"):
        np.testing.assert_array_equal(final[name], final["f64_c"], err_msg=name)
    np.testing.assert_array_equal(final["f32_fortran"], final["f64_c"])  # float32 -> float64 is exact
