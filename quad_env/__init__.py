"""quad_env: a numba-JIT multi-quadrotor swarm environment (Crazyflie 2.0 dynamics)."""
from quad_env.config import EnvConfig, RewardConfig
from quad_env.obs_layout import FIELD_KINDS, Field, ObsLayout

__all__ = ["EnvConfig", "RewardConfig", "ObsLayout", "Field", "FIELD_KINDS"]
