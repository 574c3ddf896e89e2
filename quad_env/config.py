"""Environment configuration: one dataclass, every field documented.

The trainer nests this dataclass as ``env`` in its config tree, so ``env.num_agents=16`` on a
command line sets ``EnvConfig.num_agents``. Field names are part of the public config API.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Optional, Tuple

from quad_env.obs_layout import ObsLayout

SIM_DTYPES = ("float32", "float64")
NAN_POLICIES = ("raise", "reset")
COLLISION_FORMS = ("paper", "pairwise")
# The reward terms: the one list. Order of the kernels' ``terms`` rows (``quad_env.params.T_*``), of
# ``VecQuadEnv.reward_terms`` and of the accumulator columns; a term's coefficient is the RewardConfig field of
# its name. The kernel writes all but "crash", which VecQuadEnv adds (floor contacts) and must stay last.
REWARD_TERMS = ("pos", "collision", "proximity", "omega", "action", "floor", "tilt", "goal", "height", "centre",
                "crash")


@dataclass
class RewardConfig:
    """Reward coefficients (paper, Appendix III). Per-step terms are multiplied by the control dt."""

    pos: float = 0.5
    """c1: weight of -||x_i - x_i^d|| (times dt)."""
    collision: float = 5.0
    """c2: drone-drone collision penalty (not times dt), charged as ``collision_form`` says; drone-obstacle
    contacts: ``obstacle_collision``."""
    proximity: float = 5.0
    """c3: weight of -sum_j [1 - ||x_i - x_j|| / d_p]_+ (times dt), j over the drones ``collision_form`` says."""
    collision_form: str = "paper"
    """How c2 and c3 are charged. "paper" (the paper's R^c): c2 once when drone i goes from touching no drone
    to touching some drone (within ``physics.collision_dist``; touching a second drone while still touching
    one costs nothing), and the c3 sum runs over drone i's neighbourhood N_i, the K nearest drones within
    ``sensing_radius`` that fill its observation's neighbour slots (none when ``num_neighbors`` = 0).
    "pairwise" (this project's earlier reward): c2 per new touching pair (a drone hitting two drones at once
    pays twice), and the c3 sum runs over every other drone of the swarm."""
    proximity_dist: float = 0.184
    """d_p in metres: the smooth proximity penalty starts below this centre distance (2 x collision distance)."""
    omega: float = 0.01
    """c4: weight of -||omega_i|| (times dt)."""
    action: float = 0.05
    """c5: weight of -||u_i|| on the raw action in [-1, 1]^4 (times dt)."""
    floor: float = 0.0
    """Shaping, not in the paper (0 = the paper's reward): per-step penalty while a drone is on the floor
    (times dt), like QuadSwarm's "crash" term. Without it, landing scores better than uncontrolled flight,
    which traps a policy learning from scratch (see the README's quickstart section)."""
    tilt: float = 0.0
    """Shaping, not in the paper (0 = the paper's reward): weight of -(1 - cos tilt) = -(1 - R_zz), the
    tilt of the drone's thrust axis from vertical (times dt)."""
    goal: float = 0.0
    """Shaping, not in the paper (0 = the paper's reward): bonus per step (times dt) while a drone is within
    ``goal_radius`` of its goal. The paper's c1 pulls with the same force at every distance, so nothing in its
    reward asks for the success radius (README, "The quality goal")."""
    goal_radius: float = 0.5
    """Radius of the ``goal`` bonus, m (default: the success radius of the Suc metric)."""
    height: float = 0.0
    """Shaping, not in the paper (0 = the paper's reward): weight of -|z_i - z_i^d|, the vertical part of the
    distance to the goal alone (times dt). Eight drones sharing one goal hover as a flat ring, and a ring lifted
    by h keeps each drone at sqrt(r^2 + h^2) of the goal: c1 charges the swarm's height error only at second order
    (README, "The quality goal"); this term charges it at first order without pulling the ring together."""
    centre: float = 0.0
    """Shaping, not in the paper (0 = the paper's reward): weight of -||mean_j (x_j - x_j^d)||, the swarm's mean
    offset from its goals (times dt), the same for every drone of the swarm. Drones sharing one goal hover as a ring,
    and c1 charges the ring's centre offset c only at second order (about c^2 / 2r per drone); this term charges it
    at first order, and it does not pull the drones together: spreading out about the goal costs nothing here
    (README, "The quality goal"). Zero whenever every drone is at its own goal, whatever the scenario."""
    crash: float = 0.0
    """Shaping, not in the paper (0 = the paper's reward): penalty per new floor contact (not times dt);
    the cost of a crash when ``env.respawn_on_floor`` puts the drone straight back in the air."""
    obstacle_collision: float = 5.0
    """Penalty per *new* drone-obstacle contact (not times dt); it enters the "collision" reward term."""
    collision_anneal_steps: int = 0
    """Training schedule, not in the paper (0 = off, the paper's reward throughout): the trainer scales the
    collision penalties (``collision``, ``proximity``, ``obstacle_collision``) by min(1, agent steps / this),
    from 0 to their full values, as QuadSwarm anneals its collision penalty. Evaluation always uses the full
    values."""


@dataclass
class PhysicsConfig:
    """Quadrotor and room model. Defaults: Crazyflie 2.0 (the QuadSwarm simulator's numbers).

    Change these to validate the model against another airframe's flight logs (see ``VecQuadEnv.simulate``).
    """

    mass: float = 0.028
    """Drone mass, kg."""
    inertia: Tuple[float, float, float] = (1.367e-5, 1.436e-5, 2.656e-5)
    """Principal moments of inertia (body x, y, z), kg m^2."""
    arm_xy: float = 0.0325
    """Motor offset along body x and y, m: motors at (+-arm_xy, +-arm_xy), x-configuration."""
    thrust_to_weight: float = 1.9
    """Total maximum thrust over weight (0.1305 N per motor for the defaults)."""
    torque_to_thrust: float = 0.006
    """Rotor drag torque about body z per newton of thrust, m."""
    motor_time_constant: float = 0.0375
    """First-order lag of the normalised rotor speed sqrt(cmd), s (gain physics_dt / this, capped at 1)."""
    omega_max: float = 40.0
    """Body rates are clipped to +-omega_max, rad/s."""
    gravity: float = 9.81
    """m/s^2."""
    thrust_noise_theta: float = 0.15
    """Ornstein-Uhlenbeck mean reversion per physics step of the multiplicative thrust noise."""
    thrust_noise_sigma: float = 0.01
    """Ornstein-Uhlenbeck standard deviation per physics step of the multiplicative thrust noise."""
    sensor_noise_pos: float = 0.005
    """Std of the Gaussian noise on the drone's own observed position, m."""
    sensor_noise_vel: float = 0.01
    """Std of the Gaussian noise on the drone's own observed velocity, m/s."""
    sensor_noise_omega: float = 1.75e-4
    """Std of the Gaussian noise on the drone's own observed body rates, rad/s."""
    downwash_accel: float = 2.5
    """Downwash acceleration at contact, m/s^2; it decays linearly to 0 at ``downwash_length``."""
    downwash_length: float = 0.7
    """Reach of the downwash below a drone, along its rotor axis, m."""
    downwash_radius: float = 0.1
    """Radius of the downwash cylinder around the rotor axis, m."""
    collision_dist: float = 0.092
    """Centre distance at or below which two drones touch, m."""
    collision_restitution: float = 0.75
    """Fraction of the exchanged normal velocity kept after a drone-drone collision."""
    collision_kick: float = 5.0
    """Std of the random body-rate kick per axis after a drone-drone collision, rad/s (0 = none)."""
    wall_restitution: float = 0.5
    """Fraction of the normal speed kept when bouncing off a wall or the ceiling."""
    floor_z: float = 0.046
    """Height of the drone centre when resting on the floor, m; at or below it the drone lands."""
    room_half_width: float = 5.0
    """Walls at x, y = +-room_half_width, m."""
    room_height: float = 10.0
    """Ceiling height, m."""
    reortho_interval: int = 50
    """Rotations are re-orthonormalised every this many control steps."""

    def validate(self) -> "PhysicsConfig":
        for name in ("mass", "arm_xy", "thrust_to_weight", "motor_time_constant", "omega_max", "gravity",
                     "collision_dist", "room_half_width", "room_height"):
            if not getattr(self, name) > 0:
                raise ValueError(f"env.physics.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("torque_to_thrust", "thrust_noise_theta", "thrust_noise_sigma", "sensor_noise_pos",
                     "sensor_noise_vel", "sensor_noise_omega", "downwash_accel", "downwash_length",
                     "downwash_radius", "collision_kick"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"env.physics.{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("collision_restitution", "wall_restitution"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"env.physics.{name} must be in [0, 1], got {getattr(self, name)!r}")
        if len(tuple(self.inertia)) != 3 or not all(float(v) > 0 for v in self.inertia):
            raise ValueError(f"env.physics.inertia must be 3 positive numbers, got {self.inertia!r}")
        if not 0 <= self.floor_z < self.room_height:
            raise ValueError(f"env.physics.floor_z must be in [0, room_height), got {self.floor_z!r}")
        if not isinstance(self.reortho_interval, int) or self.reortho_interval < 1:
            raise ValueError(f"env.physics.reortho_interval must be an int >= 1, got {self.reortho_interval!r}")
        return self


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
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    """Airframe, motor, noise, contact and room constants (Crazyflie 2.0 defaults)."""
    respawn_on_floor: bool = False
    """Training aid, not in the paper: a drone that touches the floor is respawned in the same step (a new
    point of the scenario's spawn box, at rest, motors off), paying ``reward.crash``. A policy learning
    from scratch crashes within ~1.5 s; without this, most of a 15 s episode is spent lying on the floor,
    where actions teach nothing. The episode goes on (no termination). Keep it off for evaluation."""
    sim_dtype: str = "float64"
    """Floating type of the simulator state: "float64" (default: as fast as float32 on x86 here, since the
    kernels compute in float64 anyway) or "float32" (half the state memory). Observations and rewards are
    float32 either way."""
    obstacles: bool = False
    """Vertical cylinders from floor to ceiling, drawn anew every episode: drones bounce off them (like off a
    wall), each new contact costs ``reward.obstacle_collision`` and counts as a collision, and every
    observation gains the 9-entry obstacle field (``ObsLayout(obstacle_obs=True)``, see ``obs_layout()``).
    The scenarios o_random and o_static_same_goal need it."""
    obstacle_density: float = 0.2
    """Probability that a cell of the obstacle grid holds a cylinder (each cell independently, per episode)."""
    obstacle_diameter: float = 0.6
    """Cylinder diameter, m. A drone must fit between two neighbouring cylinders:
    obstacle_diameter + physics.collision_dist < obstacle_cell_size."""
    obstacle_grid_cells: int = 8
    """Cells per side of the square obstacle grid, centred in the room (8 x 8 cells of 1 m: an 8 x 8 m area)."""
    obstacle_cell_size: float = 1.0
    """Side of a grid cell, m; an occupied cell has a cylinder on its centre."""
    obstacle_sdf_max: float = 2.0
    """The obstacle field (signed distances to the nearest cylinder surface) is clipped to at most this, m."""
    replay_prob: float = 0.0
    """Collision replay (QuadSwarm): probability that an automatic reset restarts a swarm from a stored state
    1.5 s before a past collision instead of a fresh spawn. 0 = off. Explicit ``reset()`` calls and envs with
    ``auto_reset=False`` (evaluation) never replay."""
    replay_buffer_size: int = 64
    """Stored pre-collision swarm states per VecQuadEnv (oldest overwritten first)."""
    nan_policy: str = "raise"
    """What a non-finite drone state does: "raise" (FloatingPointError naming the swarm) or "reset"
    (the swarm is reset, its rows are truncated, a RuntimeWarning is issued and the episode's stats carry
    ``diverged=True``)."""

    def __post_init__(self):
        # Config files give nested sections as plain dicts; accept them.
        if isinstance(self.reward, dict):
            self.reward = RewardConfig(**self.reward)
        if isinstance(self.physics, dict):
            self.physics = PhysicsConfig(**self.physics)
        self.physics.inertia = tuple(float(v) for v in self.physics.inertia)

    @property
    def control_dt(self) -> float:
        return self.physics_dt * self.substeps

    @property
    def episode_steps(self) -> int:
        return int(round(self.episode_duration / self.control_dt))

    def obs_layout(self) -> ObsLayout:
        """The observation layout of this config (the obstacle field only with ``obstacles``)."""
        return ObsLayout(self.num_neighbors, self.neighbor_obs, obstacle_obs=self.obstacles)

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
        if self.sim_dtype not in SIM_DTYPES:
            raise ValueError(f"env.sim_dtype must be one of {list(SIM_DTYPES)}, got {self.sim_dtype!r}")
        if self.nan_policy not in NAN_POLICIES:
            raise ValueError(f"env.nan_policy must be one of {list(NAN_POLICIES)}, got {self.nan_policy!r}")
        if self.episode_steps < 1:
            raise ValueError(f"env.episode_duration must last at least one control step, got {self.episode_duration!r}")
        if not isinstance(self.respawn_on_floor, bool):
            raise ValueError(f"env.respawn_on_floor must be true or false, got {self.respawn_on_floor!r}")
        if not isinstance(self.scenario, str):
            raise ValueError(f"env.scenario must be a scenario name (str), got {self.scenario!r}")
        self._validate_obstacles_and_replay()
        if self.respawn_on_floor and self.obstacles:
            raise ValueError("env.respawn_on_floor is not supported with env.obstacles=true yet (a respawn point "
                             "could lie inside a cylinder): switch one of them off")
        for name in (*REWARD_TERMS, "obstacle_collision"):
            if not getattr(self.reward, name) >= 0:
                raise ValueError(f"env.reward.{name} must be >= 0, got {getattr(self.reward, name)!r}")
        if not isinstance(self.reward.collision_anneal_steps, int) or self.reward.collision_anneal_steps < 0:
            raise ValueError(f"env.reward.collision_anneal_steps must be an int >= 0, "
                             f"got {self.reward.collision_anneal_steps!r}")
        if self.reward.collision_form not in COLLISION_FORMS:
            raise ValueError(f"env.reward.collision_form must be one of {list(COLLISION_FORMS)}, "
                             f"got {self.reward.collision_form!r}")
        if not self.reward.proximity_dist > 0:
            raise ValueError(f"env.reward.proximity_dist must be > 0, got {self.reward.proximity_dist!r}")
        if not 0 < self.reward.goal_radius < float("inf"):
            raise ValueError(f"env.reward.goal_radius must be a finite number > 0, got {self.reward.goal_radius!r}")
        self.physics.validate()
        return self

    def _validate_obstacles_and_replay(self) -> None:
        if not isinstance(self.obstacles, bool):
            raise ValueError(f"env.obstacles must be True or False, got {self.obstacles!r}")
        if not 0 <= self.obstacle_density <= 1:
            raise ValueError(f"env.obstacle_density must be in [0, 1], got {self.obstacle_density!r}")
        if not isinstance(self.obstacle_grid_cells, int) or not 1 <= self.obstacle_grid_cells <= 256:
            raise ValueError(f"env.obstacle_grid_cells must be an int in [1, 256], got {self.obstacle_grid_cells!r}")
        if not self.obstacle_cell_size > 0:
            raise ValueError(f"env.obstacle_cell_size must be > 0, got {self.obstacle_cell_size!r}")
        if not self.obstacle_diameter > 0:
            raise ValueError(f"env.obstacle_diameter must be > 0, got {self.obstacle_diameter!r}")
        if not self.obstacle_diameter + self.physics.collision_dist < self.obstacle_cell_size:
            raise ValueError(f"env.obstacle_diameter must be < env.obstacle_cell_size - env.physics.collision_dist "
                             f"(a drone fits between two cylinders), got {self.obstacle_diameter!r} with cells of "
                             f"{self.obstacle_cell_size!r} m")
        if self.obstacle_grid_cells * self.obstacle_cell_size > 2 * self.physics.room_half_width:
            raise ValueError(f"env.obstacle_grid_cells * env.obstacle_cell_size must fit in the room "
                             f"(<= {2 * self.physics.room_half_width} m), got "
                             f"{self.obstacle_grid_cells} x {self.obstacle_cell_size} m")
        if not self.obstacle_sdf_max > 0:
            raise ValueError(f"env.obstacle_sdf_max must be > 0, got {self.obstacle_sdf_max!r}")
        if not 0 <= self.replay_prob <= 1:
            raise ValueError(f"env.replay_prob must be in [0, 1], got {self.replay_prob!r}")
        if not isinstance(self.replay_buffer_size, int) or self.replay_buffer_size < 1:
            raise ValueError(f"env.replay_buffer_size must be an int >= 1, got {self.replay_buffer_size!r}")

    def to_dict(self) -> dict:
        return asdict(self)
