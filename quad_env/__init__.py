"""quad_env: a numba-JIT multi-quadrotor swarm environment (Crazyflie 2.0 dynamics).

``VecQuadEnv`` steps E swarms x N drones in one kernel (rollout workers); ``QuadSwarmEnv`` (gymnasium
style) and ``QuadSwarmParallelEnv`` (PettingZoo) wrap one swarm and are imported on first use.
"""
from quad_env.jit_cache import keyed_cache

with keyed_cache():  # every module that defines numba kernels: compiled code cached per version of the sources
    from quad_env import kernels, obstacles, replay, rng, scenarios  # noqa: F401
from quad_env.config import EnvConfig, PhysicsConfig, RewardConfig
from quad_env.obs_layout import FIELD_KINDS, Field, ObsLayout
from quad_env.params import REWARD_TERMS
from quad_env.scenarios import SCENARIOS, make_scenario, register_scenario
from quad_env.vec_env import DroneState, VecQuadEnv

__all__ = ["EnvConfig", "RewardConfig", "PhysicsConfig", "ObsLayout", "Field", "FIELD_KINDS", "REWARD_TERMS",
           "SCENARIOS", "make_scenario", "register_scenario", "VecQuadEnv", "DroneState", "QuadSwarmEnv",
           "QuadSwarmParallelEnv", "QuadDroneEnv", "QuadSwarmVectorEnv"]


def __getattr__(name):
    # The adapters import gymnasium and pettingzoo: only when asked for.
    if name in ("QuadSwarmEnv", "QuadSwarmParallelEnv", "QuadDroneEnv", "QuadSwarmVectorEnv"):
        from quad_env import adapters
        return getattr(adapters, name)
    raise AttributeError(f"module 'quad_env' has no attribute {name!r}")
