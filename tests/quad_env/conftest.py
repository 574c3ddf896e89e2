"""Shared helpers for the quad_env tests."""
import numpy as np
import pytest

from quad_env import EnvConfig, PhysicsConfig, VecQuadEnv


def _quiet_cfg(physics=None, **kw):
    """Config with every noise source off (thrust, sensor, collision kick)."""
    phys = dict(collision_kick=0.0)
    phys.update(physics or {})
    kw.setdefault("thrust_noise", False)
    kw.setdefault("sensor_noise", False)
    return EnvConfig(physics=PhysicsConfig(**phys), **kw)


@pytest.fixture
def quiet_cfg():
    return _quiet_cfg


@pytest.fixture
def hover_env():
    """Factory: one swarm of ``n`` level drones in mid-air with motors spun up to hover, no drag."""

    def make(n=1, drag=0.0, **kw):
        kw.setdefault("num_neighbors", 0)
        cfg = _quiet_cfg(num_agents=n, drag_coeff=drag, **kw)
        env = VecQuadEnv(cfg, num_envs=1, seed=0)
        hover_cmd = 1.0 / cfg.physics.thrust_to_weight
        pos = np.zeros((n, 3))
        pos[:, 0] = np.arange(n) * 1.0
        pos[:, 2] = 5.0
        env.set_state(pos=pos, vel=np.zeros((n, 3)), rot=np.tile(np.eye(3), (n, 1, 1)), omega=np.zeros((n, 3)),
                      motor=np.full((n, 4), np.sqrt(hover_cmd)), goal=pos)
        env.hover_action = np.full((n, 4), 2 * hover_cmd - 1)
        return env

    return make
