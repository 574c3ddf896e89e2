"""Pack an ``EnvConfig`` into the two flat parameter arrays the kernels read.

Kernels take every constant at run time (not as compile-time globals), so one compiled kernel serves
every configuration and the numba cache stays valid when a config changes.
"""
from __future__ import annotations

import numpy as np

from quad_env.config import COLLISION_FORMS, REWARD_TERMS, EnvConfig
from quad_env.obstacles import lookup_pad

# ---------------------------------------------------------------- float parameters (float64 [NUM_F])
F_DT = 0  # physics dt, s
F_CTRL_DT = 1  # control dt, s
F_MASS = 2
F_GRAV = 3
F_IXX = 4
F_IYY = 5
F_IZZ = 6
F_ARM = 7  # motor offset along body x and y, m
F_TMAX = 8  # max thrust per motor, N
F_KTAU = 9  # yaw torque per newton of thrust, m
F_MOTOR_GAIN = 10  # first-order lag gain per physics step
F_OMEGA_MAX = 11
F_OU_THETA = 12
F_OU_SIGMA = 13
F_DRAG = 14  # drag_coeff / mass, 1/s
F_FLOOR_Z = 15
F_ROOM_HALF = 16
F_ROOM_H = 17
F_WALL_REST = 18
F_COLL_DIST = 19
F_COLL_REST = 20
F_COLL_KICK = 21
F_DW_ACC = 22
F_DW_LEN = 23
F_DW_RAD = 24
F_SENSE_R = 25  # inf when unlimited
F_NOISE_POS = 26
F_NOISE_VEL = 27
F_NOISE_OMEGA = 28
F_C_POS = 29
F_C_COLL = 30
F_C_PROX = 31
F_PROX_DIST = 32
F_C_OMEGA = 33
F_C_ACTION = 34
F_OBST_ORIGIN = 35  # x (= y) of the obstacle grid's lower corner, m
F_OBST_CELL = 36  # cell side, m
F_OBST_R = 37  # cylinder radius, m
F_OBST_CONTACT_R = 38  # axis distance at which a drone touches a cylinder: radius + collision_dist / 2, m
F_OBST_SDF_MAX = 39  # the obstacle field is clipped to at most this, m
F_C_OBST = 40  # penalty per new drone-obstacle contact
F_OBST_LOOKUP_ORIGIN = 41  # x (= y) of the lower corner of the obstacle field's lookup grid (covers the room), m
F_C_FLOOR = 42
F_C_TILT = 43
F_C_GOAL = 44
F_GOAL_R = 45  # radius of the "goal" bonus, m
F_C_HEIGHT = 46
F_C_CENTRE = 47
NUM_F = 48

# ---------------------------------------------------------------- int parameters (int64 [NUM_I])
I_N = 0  # drones per swarm
I_K = 1  # neighbour slots
I_SUBSTEPS = 2
I_EP_STEPS = 3  # control steps per episode
I_FULL_NB = 4  # 1: "full" neighbour blocks (21), 0: "pos_vel" (6)
I_THRUST_NOISE = 5
I_SENSOR_NOISE = 6
I_COLL_KICK = 7  # 1: random body-rate kick on collisions
I_DOWNWASH = 8
I_REORTHO = 9  # re-orthonormalise every this many control steps
I_TAIL_STEPS = 10  # control steps in the last 5 s (episode stat dist_last_5s)
I_OBS_DIM = 11
I_NB_DIM = 12  # entries per neighbour block
I_TAIL1_STEPS = 13  # control steps in the last 1 s (dist_last_1s)
I_TAIL3_STEPS = 14  # control steps in the last 3 s (dist_last_3s)
I_GRACE_STEPS = 15  # collisions in the first this many control steps (1.5 s) do not count for the metrics
I_OBSTACLES = 16  # 1: cylinders (physics, contacts, obstacle field)
I_OBST_CELLS = 17  # cells per side of the obstacle grid
I_OBST_LOOKUP = 18  # cells per side of the lookup grid (quad_env.obstacles.index_obstacles)
I_COLL_FORM = 19  # reward.collision_form: COLL_FORM_PAPER or COLL_FORM_PAIRWISE
NUM_I = 20

COLL_FORM_PAPER = 0  # c2 once per drone entering contact, c3 over the observed neighbours
COLL_FORM_PAIRWISE = 1  # c2 per new touching pair, c3 over every other drone

METRIC_GRACE_S = 1.5  # grace period of the collision metrics, s
SDF_SPACING = 0.1  # the obstacle field samples a 3 x 3 horizontal grid this far apart (m) around the drone

# Rows of the reward ``terms`` array [len(REWARD_TERMS), M], from the one list (``quad_env.config.REWARD_TERMS``).
T_POS = REWARD_TERMS.index("pos")
T_COLLISION = REWARD_TERMS.index("collision")
T_PROXIMITY = REWARD_TERMS.index("proximity")
T_OMEGA = REWARD_TERMS.index("omega")
T_ACTION = REWARD_TERMS.index("action")
T_FLOOR = REWARD_TERMS.index("floor")
T_TILT = REWARD_TERMS.index("tilt")
T_GOAL = REWARD_TERMS.index("goal")
T_HEIGHT = REWARD_TERMS.index("height")
T_CENTRE = REWARD_TERMS.index("centre")
T_CRASH = REWARD_TERMS.index("crash")
KERNEL_TERMS = T_CRASH  # the step kernel writes rows [0, KERNEL_TERMS); "crash" (the last) is VecQuadEnv's


def pack_params(cfg: EnvConfig, obs_dim: int, noise: bool = True):
    """Return ``(fparams float64 [NUM_F], iparams int64 [NUM_I])`` for ``cfg``.

    ``noise=False`` switches off thrust noise, sensor noise and the random collision kick whatever the config
    says (the low-level, deterministic stepping mode).
    """
    p, r = cfg.physics, cfg.reward
    f = np.zeros(NUM_F, np.float64)
    f[F_DT] = cfg.physics_dt
    f[F_CTRL_DT] = cfg.control_dt
    f[F_MASS] = p.mass
    f[F_GRAV] = p.gravity
    f[F_IXX], f[F_IYY], f[F_IZZ] = p.inertia
    f[F_ARM] = p.arm_xy
    f[F_TMAX] = p.thrust_to_weight * p.mass * p.gravity / 4.0
    f[F_KTAU] = p.torque_to_thrust
    f[F_MOTOR_GAIN] = min(1.0, cfg.physics_dt / p.motor_time_constant)
    f[F_OMEGA_MAX] = p.omega_max
    f[F_OU_THETA] = p.thrust_noise_theta
    f[F_OU_SIGMA] = p.thrust_noise_sigma
    f[F_DRAG] = cfg.drag_coeff / p.mass
    f[F_FLOOR_Z] = p.floor_z
    f[F_ROOM_HALF] = p.room_half_width
    f[F_ROOM_H] = p.room_height
    f[F_WALL_REST] = p.wall_restitution
    f[F_COLL_DIST] = p.collision_dist
    f[F_COLL_REST] = p.collision_restitution
    f[F_COLL_KICK] = p.collision_kick
    f[F_DW_ACC] = p.downwash_accel
    f[F_DW_LEN] = p.downwash_length
    f[F_DW_RAD] = p.downwash_radius
    f[F_SENSE_R] = np.inf if cfg.sensing_radius is None else cfg.sensing_radius
    f[F_NOISE_POS] = p.sensor_noise_pos
    f[F_NOISE_VEL] = p.sensor_noise_vel
    f[F_NOISE_OMEGA] = p.sensor_noise_omega
    f[F_C_POS] = r.pos
    f[F_C_COLL] = r.collision
    f[F_C_PROX] = r.proximity
    f[F_PROX_DIST] = r.proximity_dist
    f[F_C_OMEGA] = r.omega
    f[F_C_ACTION] = r.action
    f[F_C_FLOOR] = r.floor
    f[F_C_TILT] = r.tilt
    f[F_C_GOAL] = r.goal
    f[F_GOAL_R] = r.goal_radius
    f[F_C_HEIGHT] = r.height
    f[F_C_CENTRE] = r.centre
    f[F_OBST_ORIGIN] = -0.5 * cfg.obstacle_grid_cells * cfg.obstacle_cell_size
    f[F_OBST_CELL] = cfg.obstacle_cell_size
    f[F_OBST_R] = 0.5 * cfg.obstacle_diameter
    f[F_OBST_CONTACT_R] = 0.5 * cfg.obstacle_diameter + 0.5 * p.collision_dist
    f[F_OBST_SDF_MAX] = cfg.obstacle_sdf_max
    f[F_C_OBST] = r.obstacle_collision
    f[F_OBST_LOOKUP_ORIGIN] = f[F_OBST_ORIGIN] - lookup_pad(cfg) * cfg.obstacle_cell_size

    i = np.zeros(NUM_I, np.int64)
    i[I_N] = cfg.num_agents
    i[I_K] = cfg.num_neighbors
    i[I_SUBSTEPS] = cfg.substeps
    i[I_EP_STEPS] = cfg.episode_steps
    i[I_FULL_NB] = 1 if cfg.neighbor_obs == "full" else 0
    i[I_THRUST_NOISE] = int(noise and cfg.thrust_noise)
    i[I_SENSOR_NOISE] = int(noise and cfg.sensor_noise)
    i[I_COLL_KICK] = int(noise and p.collision_kick > 0)
    i[I_DOWNWASH] = int(cfg.downwash)
    i[I_REORTHO] = p.reortho_interval
    i[I_TAIL_STEPS] = min(cfg.episode_steps, int(round(5.0 / cfg.control_dt)))
    i[I_OBS_DIM] = obs_dim
    i[I_NB_DIM] = 21 if cfg.neighbor_obs == "full" else 6
    i[I_TAIL1_STEPS] = min(cfg.episode_steps, int(round(1.0 / cfg.control_dt)))
    i[I_TAIL3_STEPS] = min(cfg.episode_steps, int(round(3.0 / cfg.control_dt)))
    i[I_GRACE_STEPS] = int(round(METRIC_GRACE_S / cfg.control_dt))
    i[I_OBSTACLES] = int(cfg.obstacles)
    i[I_OBST_CELLS] = cfg.obstacle_grid_cells
    i[I_OBST_LOOKUP] = cfg.obstacle_grid_cells + 2 * lookup_pad(cfg)
    i[I_COLL_FORM] = COLLISION_FORMS.index(r.collision_form)  # (the order of COLL_FORM_PAPER, COLL_FORM_PAIRWISE)
    return f, i
