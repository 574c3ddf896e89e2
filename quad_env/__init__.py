"""quad_env: a numba-JIT multi-quadrotor swarm environment (Crazyflie 2.0 dynamics).

``VecQuadEnv`` steps E swarms x N drones in one kernel (rollout workers); ``QuadDroneEnv`` /
``QuadSwarmVectorEnv`` (gymnasium) and ``QuadSwarmParallelEnv`` (PettingZoo) wrap it.

Importing the package loads only the configuration and the observation layout (what ``encoders`` and
``swarm_appo.config`` need); the simulator (numba and its kernels), the scenarios and the adapters (gymnasium,
pettingzoo) load on first use of their names. The kernels cache under a hash of the sources
(``quad_env.jit_cache``), whichever way their modules are imported.
"""
import importlib

from quad_env.config import REWARD_TERMS, EnvConfig, PhysicsConfig, RewardConfig
from quad_env.obs_layout import FIELD_KINDS, Field, ObsLayout

_LAZY = {  # name -> the module that defines it, imported on first access
    "SCENARIOS": "quad_env.scenarios", "make_scenario": "quad_env.scenarios",
    "register_scenario": "quad_env.scenarios",
    "VecQuadEnv": "quad_env.vec_env", "DroneState": "quad_env.vec_env",
    "QuadSwarmEnv": "quad_env.adapters", "QuadSwarmParallelEnv": "quad_env.adapters",
    "QuadDroneEnv": "quad_env.adapters", "QuadSwarmVectorEnv": "quad_env.adapters",
}

__all__ = ["EnvConfig", "RewardConfig", "REWARD_TERMS", "PhysicsConfig", "ObsLayout", "Field", "FIELD_KINDS", *_LAZY]


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'quad_env' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
