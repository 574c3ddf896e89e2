"""Environment configuration: one dataclass, every field documented.

The trainer nests this dataclass as ``env`` in its config tree, so ``env.num_agents=16`` on a
command line sets ``EnvConfig.num_agents``. Field names are part of the public config API.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Optional


@dataclass
class RewardConfig:
    """Reward coefficients (paper, Appendix III). Per-step terms are multiplied by the control dt."""

    pos: float = 0.5
    """c1: weight of -||x_i - x_i^d|| (times dt)."""
    collision: float = 5.0
    """c2: penalty per *new* drone-drone (or drone-obstacle) contact (not times dt)."""
    proximity: float = 5.0
    """c3: weight of -sum_j [1 - ||x_i - x_j|| / d_p]_+ (times dt)."""
    proximity_dist: float = 0.184
    """d_p in metres: the smooth proximity penalty starts below this centre distance (2 x collision distance)."""
    omega: float = 0.01
    """c4: weight of -||omega_i|| (times dt)."""
    action: float = 0.05
    """c5: weight of -||u_i|| on the raw action in [-1, 1]^4 (times dt)."""


@dataclass
class EnvConfig:
    """Quadrotor swarm environment."""

    num_agents: int = 8
    """N, drones per swarm (>= 1)."""
    num_neighbors: int = 6
    """K, neighbour slots in each observation (>= 0); fewer real neighbours are masked."""
    neighbor_obs: str = "full"
    """Neighbour state: "full" (paper, 21 per neighbour) or "pos_vel" (QuadSwarm baseline, 6)."""
    sensing_radius: Optional[float] = None
    """Neighbours farther than this (metres) are masked out; None = unlimited."""
    scenario: str = "static_same_goal"
    """Scenario name; see ``quad_env.scenarios.SCENARIOS``."""
    episode_duration: float = 15.0
    """Episode length in seconds; the end is a truncation, never a termination."""
    physics_dt: float = 0.005
    """Physics integration step in seconds."""
    substeps: int = 2
    """Physics steps per control step (control dt = physics_dt * substeps = 0.01 s)."""
    thrust_noise: bool = True
    """Ornstein-Uhlenbeck thrust noise (theta 0.15, sigma 0.01), multiplicative on the motor command."""
    sensor_noise: bool = True
    """Gaussian observation noise (pos 0.005 m, vel 0.01 m/s, body rates 1.75e-4 rad/s)."""
    drag_coeff: float = 0.0056
    """Linear aerodynamic drag force per unit velocity, N/(m/s): F = -drag_coeff * v.
    Default: gym-pybullet-drones' Crazyflie drag coefficient (9.18e-7 N/(rad/s)/(m/s)) at hover rotor speed."""
    downwash: bool = True
    """Downwash from drones above (within 0.7 m along the rotor axis and 0.1 m radially)."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Reward coefficients."""

    @property
    def control_dt(self) -> float:
        return self.physics_dt * self.substeps

    @property
    def episode_steps(self) -> int:
        return int(round(self.episode_duration / self.control_dt))

    def validate(self) -> "EnvConfig":
        """Raise ValueError naming the offending key if a value is out of range."""
        if not isinstance(self.num_agents, int) or self.num_agents < 1:
            raise ValueError(f"env.num_agents must be an int >= 1, got {self.num_agents!r}")
        if not isinstance(self.num_neighbors, int) or self.num_neighbors < 0:
            raise ValueError(f"env.num_neighbors must be an int >= 0, got {self.num_neighbors!r}")
        if self.neighbor_obs not in ("full", "pos_vel"):
            raise ValueError(f"env.neighbor_obs must be one of ['full', 'pos_vel'], got {self.neighbor_obs!r}")
        if self.sensing_radius is not None and not self.sensing_radius > 0:
            raise ValueError(f"env.sensing_radius must be > 0 or None, got {self.sensing_radius!r}")
        if not self.episode_duration > 0:
            raise ValueError(f"env.episode_duration must be > 0, got {self.episode_duration!r}")
        if not self.physics_dt > 0:
            raise ValueError(f"env.physics_dt must be > 0, got {self.physics_dt!r}")
        if not isinstance(self.substeps, int) or self.substeps < 1:
            raise ValueError(f"env.substeps must be an int >= 1, got {self.substeps!r}")
        if self.drag_coeff < 0:
            raise ValueError(f"env.drag_coeff must be >= 0, got {self.drag_coeff!r}")
        return self

    def to_dict(self) -> dict:
        return asdict(self)
