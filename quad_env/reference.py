"""Plain-numpy float64 reference of one noise-free control step (for tests; slow, not for training).

Written from the model equations with numpy matrix algebra, independently of the kernels' hand-unrolled
code, so the tests can check the kernels against it (``tests/quad_env/test_reference.py``).
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import numpy as np

from quad_env.config import REWARD_TERMS, EnvConfig
from quad_env.params import KERNEL_TERMS

# Motor positions (x, y) over arm_xy and spin signs: (+x,-y), (-x,-y), (-x,+y), (+x,+y).
MOTOR_XY = np.array([[1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])
MOTOR_SPIN = np.array([-1.0, 1.0, -1.0, 1.0])


def hat(w: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] cross-product matrices."""
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def rodrigues(w: np.ndarray, dt: float) -> np.ndarray:
    """exp(dt [w]_x) for [M, 3] rates."""
    angle = np.linalg.norm(w, axis=-1) * dt  # [M]
    safe = np.where(angle > 0, angle, 1.0)
    K = hat(w * dt / safe[:, None])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    E = np.eye(3) + s * K + (1 - c) * (K @ K)
    return np.where((angle > 1e-12 * dt)[:, None, None], E, np.eye(3))


def cylinder_axes(grid: np.ndarray, cfg: EnvConfig) -> np.ndarray:
    """Axes (x, y) of the cylinders of one swarm's occupancy grid [G, G]: [C, 2]."""
    G, cell = cfg.obstacle_grid_cells, cfg.obstacle_cell_size
    centres = (np.arange(G) + 0.5) * cell - 0.5 * G * cell  # [G]
    ix, iy = np.nonzero(grid)
    return np.stack([centres[ix], centres[iy]], axis=1)


def reference_obstacle_field(xy: np.ndarray, axes: np.ndarray, cfg: EnvConfig) -> np.ndarray:
    """Obstacle field of drones at ``xy`` [M, 2] among cylinders ``axes`` [C, 2]: [M, 9], entry 3 a + b at the
    point xy + ((a - 1) h, (b - 1) h), h = 0.1 m; distance to the nearest surface, clipped to sdf_max."""
    offsets = np.array([[da, db] for da in (-0.1, 0.0, 0.1) for db in (-0.1, 0.0, 0.1)])  # [9, 2]
    points = xy[:, None, :] + offsets[None]  # [M, 9, 2]
    if len(axes) == 0:
        return np.full(points.shape[:2], cfg.obstacle_sdf_max)
    dist = np.linalg.norm(points[:, :, None, :] - axes[None, None], axis=-1) - cfg.obstacle_diameter / 2  # [M, 9, C]
    return np.minimum(dist.min(-1), cfg.obstacle_sdf_max)


def reference_push_out(pos: np.ndarray, vel: np.ndarray, axes: np.ndarray, cfg: EnvConfig):
    """Drones closer than (diameter + collision_dist) / 2 to their nearest cylinder axis go back onto that
    circle and their inward radial velocity is reversed times the wall restitution. Returns a bool [M] of
    the drones that touched (pos and vel are changed in place)."""
    if len(axes) == 0:
        return np.zeros(len(pos), bool)
    reach = (cfg.obstacle_diameter + cfg.physics.collision_dist) / 2
    rel = pos[:, None, :2] - axes[None]  # [M, C, 2]
    d = np.linalg.norm(rel, axis=-1)  # [M, C]
    nearest = d.argmin(1)
    rows = np.arange(len(pos))
    d_near, rel_near = d[rows, nearest], rel[rows, nearest]
    touch = d_near < reach
    safe = np.where(d_near > 0, d_near, 1.0)
    n = np.where((d_near > 0)[:, None], rel_near / safe[:, None], np.array([1.0, 0.0]))  # [M, 2] outward
    pos[touch, :2] = axes[nearest[touch]] + reach * n[touch]
    vn = (vel[:, :2] * n).sum(1)
    inward = touch & (vn < 0)
    vel[inward, :2] -= (1 + cfg.physics.wall_restitution) * vn[inward, None] * n[inward]
    return touch


def touching_drones(contact: np.ndarray) -> np.ndarray:
    """Pair contact memory [E, N, N] (pairs a < b) -> bool [E, N]: the drones touching some drone."""
    pairs = (contact != 0) & np.triu(np.ones(contact.shape[1:], bool), 1)
    return pairs.any(2) | pairs.any(1)


def reference_step(state: Dict[str, np.ndarray], actions: np.ndarray, cfg: EnvConfig, step_count: np.ndarray,
                   contact: np.ndarray) -> Tuple[Dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray,
                                                 np.ndarray]:
    """One control step of all swarms with every noise source off and no obstacles.

    Args:
        state: dict of float64 arrays pos, vel, rot, omega, motor, goal (shapes as ``DroneState``).
        actions: [M, 4]; step_count: [E] control steps done before this one; contact: [E, N, N] (a < b).
    Returns:
        new_state, obs [M, D] (float64), rew [M], terms [KERNEL_TERMS, M] (the step kernel's rows of
        ``REWARD_TERMS``: all but "crash", which VecQuadEnv adds), new_contact [E, N, N].
    """
    return reference_step_obstacles(state, actions, cfg, step_count, contact, None, None)[:5]


def reference_step_obstacles(state: Dict[str, np.ndarray], actions: np.ndarray, cfg: EnvConfig,
                             step_count: np.ndarray, contact: np.ndarray, obstacles: Optional[np.ndarray],
                             obstacle_contact: Optional[np.ndarray]):
    """``reference_step`` with the cylinders ``obstacles`` [E, G, G] (None: none) and the drones' obstacle
    contact memory ``obstacle_contact`` [M] (touching at the last step). Returns
    new_state, obs, rew, terms, new_contact, new_obstacle_contact [M] (bool)."""
    p, rc = cfg.physics, cfg.reward
    N, K = cfg.num_agents, cfg.num_neighbors
    M = actions.shape[0]
    E = M // N
    dt, ctrl_dt = cfg.physics_dt, cfg.control_dt
    J = np.diag(p.inertia)
    Jinv = np.diag(1.0 / np.asarray(p.inertia))
    tmax = p.thrust_to_weight * p.mass * p.gravity / 4
    gain = min(1.0, dt / p.motor_time_constant)
    pos, vel = state["pos"].copy(), state["vel"].copy()
    rot, omega = state["rot"].copy(), state["omega"].copy()
    motor, goal = state["motor"].copy(), state["goal"].copy()

    u = np.clip(actions.astype(np.float64), -1, 1)
    cmd = (u + 1) / 2  # [M, 4]
    with_obstacles = obstacles is not None
    axes = [cylinder_axes(obstacles[e], cfg) if with_obstacles else np.zeros((0, 2)) for e in range(E)]
    touched_obstacle = np.zeros(M, bool)
    arms = np.concatenate([MOTOR_XY * p.arm_xy, np.zeros((4, 1))], axis=1)  # [4, 3]
    for _ in range(cfg.substeps):
        motor = motor + gain * (np.sqrt(cmd) - motor)
        T = tmax * np.clip(motor ** 2, 0, 1)  # [M, 4]
        forces = np.zeros((M, 4, 3))
        forces[..., 2] = T
        tau = np.cross(arms[None], forces).sum(1)  # [M, 3]
        tau[:, 2] += p.torque_to_thrust * (T * MOTOR_SPIN).sum(1)
        thrust_world = rot @ np.array([0.0, 0.0, 1.0]) * T.sum(1, keepdims=True)
        acc = thrust_world / p.mass - np.array([0, 0, p.gravity]) - cfg.drag_coeff / p.mass * vel
        Jw = omega @ J
        omega_dot = (tau - np.cross(omega, Jw)) @ Jinv
        pos = pos + dt * vel
        vel = vel + dt * acc
        omega = np.clip(omega + dt * omega_dot, -p.omega_max, p.omega_max)
        rot = rot @ rodrigues(omega, dt)
        # floor: land (rest, level keeping yaw) unless taking off
        on_floor = pos[:, 2] <= p.floor_z
        pos[:, 2] = np.where(on_floor, p.floor_z, pos[:, 2])
        land = on_floor & (vel[:, 2] <= 0)
        yaw = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
        level = np.zeros((M, 3, 3))
        level[:, 0, 0], level[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
        level[:, 1, 0], level[:, 1, 1] = np.sin(yaw), np.cos(yaw)
        level[:, 2, 2] = 1
        vel[land] = 0
        omega[land] = 0
        relevel = land & (rot[:, 2, 2] != 1.0)  # a drone resting level keeps its rotation
        rot[relevel] = level[relevel]
        ceiling = ~on_floor & (pos[:, 2] > p.room_height)
        vel[:, 2] = np.where(ceiling & (vel[:, 2] > 0), -p.wall_restitution * vel[:, 2], vel[:, 2])
        pos[:, 2] = np.where(ceiling, p.room_height, pos[:, 2])
        for ax in (0, 1):
            hi, lo = pos[:, ax] > p.room_half_width, pos[:, ax] < -p.room_half_width
            out_vel = (hi & (vel[:, ax] > 0)) | (lo & (vel[:, ax] < 0))
            vel[:, ax] = np.where(out_vel, -p.wall_restitution * vel[:, ax], vel[:, ax])
            pos[:, ax] = np.clip(pos[:, ax], -p.room_half_width, p.room_half_width)
        for e in range(E):  # cylinders, after the walls
            rows = slice(e * N, (e + 1) * N)
            p_e, v_e = pos[rows], vel[rows]
            touched_obstacle[rows] |= reference_push_out(p_e, v_e, axes[e], cfg)

    steps = step_count + 1
    for e in range(E):
        if steps[e] % p.reortho_interval == 0:
            R = rot[e * N:(e + 1) * N]
            rot[e * N:(e + 1) * N] = 1.5 * R - 0.5 * R @ np.swapaxes(R, 1, 2) @ R

    # ---- pair effects, in the kernel's order (a < b), since collision responses compound
    touched_before = touching_drones(contact)  # [E, N]
    contact = contact.copy()
    new_coll = np.zeros(M)
    prox = np.zeros(M)
    for e in range(E):
        for a in range(N):
            for b in range(a + 1, N):
                i, j = e * N + a, e * N + b
                delta = pos[j] - pos[i]
                d = np.linalg.norm(delta)
                prox[[i, j]] += max(0.0, 1 - d / rc.proximity_dist)
                if d <= p.collision_dist:
                    if not contact[e, a, b]:
                        contact[e, a, b] = 1
                        new_coll[[i, j]] += 1
                    n = delta / d if d > 0 else np.array([0.0, 0.0, 1.0])
                    ua, ub = vel[i] @ n, vel[j] @ n
                    if ub - ua < 0:
                        vel[i] += (p.collision_restitution * ub - ua) * n
                        vel[j] += (p.collision_restitution * ua - ub) * n
                else:
                    contact[e, a, b] = 0
                if cfg.downwash:
                    for up, down, sign in ((i, j, 1.0), (j, i, -1.0)):
                        axis = rot[up][:, 2]
                        depth = -sign * (delta @ axis)
                        radial2 = d * d - depth * depth
                        if 0 < depth < p.downwash_length and radial2 < p.downwash_radius ** 2:
                            vel[down] -= p.downwash_accel * (1 - depth / p.downwash_length) * ctrl_dt * axis

    entered_contact = (touching_drones(contact) & ~touched_before).reshape(M)  # the paper's c2 indicator

    # ---- observations
    nb_dim = 21 if cfg.neighbor_obs == "full" else 6
    D = 18 + K * (nb_dim + 1) + (9 if cfg.obstacles else 0)
    obs = np.zeros((M, D))
    if with_obstacles:
        for e in range(E):
            rows = slice(e * N, (e + 1) * N)
            obs[rows, D - 9:] = reference_obstacle_field(pos[rows, :2], axes[e], cfg)
    previous = np.zeros(M, bool) if obstacle_contact is None else obstacle_contact.astype(bool)
    new_obstacle = touched_obstacle & ~previous
    obs[:, 0:3] = pos - goal
    obs[:, 3:6] = vel
    obs[:, 6:15] = rot.reshape(M, 9)
    obs[:, 15:18] = omega
    sense = np.inf if cfg.sensing_radius is None else cfg.sensing_radius
    prox_neighbours = np.zeros(M)  # the paper's c3 sum: over the observed neighbours only
    for e in range(E):
        idx = np.arange(e * N, (e + 1) * N)
        for a in range(N):
            i = idx[a]
            others = idx[idx != i]
            d2 = ((pos[others] - pos[i]) ** 2).sum(1)
            order = np.lexsort((others, d2))  # by distance, then by index
            chosen = [others[o] for o in order[:K] if d2[o] <= sense ** 2]
            for j in chosen:
                prox_neighbours[i] += max(0.0, 1 - np.linalg.norm(pos[j] - pos[i]) / rc.proximity_dist)
            for k, j in enumerate(chosen):
                off = 18 + k * nb_dim
                block = [pos[j] - pos[i], vel[j] - vel[i]]
                if nb_dim == 21:
                    block += [rot[j].reshape(9), omega[j], goal[j] - pos[j]]
                obs[i, off:off + nb_dim] = np.concatenate(block)
                obs[i, 18 + K * nb_dim + k] = 1.0

    # ---- reward terms: one formula per kernel-written name of REWARD_TERMS, stacked in that order
    paper = rc.collision_form == "paper"
    formulas = {
        "pos": -rc.pos * ctrl_dt * np.linalg.norm(pos - goal, axis=1),
        "collision": -rc.collision * (entered_contact if paper else new_coll) - rc.obstacle_collision * new_obstacle,
        "proximity": -rc.proximity * ctrl_dt * (prox_neighbours if paper else prox),
        "omega": -rc.omega * ctrl_dt * np.linalg.norm(omega, axis=1),
        "action": -rc.action * ctrl_dt * np.linalg.norm(u, axis=1),
        "floor": -rc.floor * ctrl_dt * (pos[:, 2] <= p.floor_z),
        "tilt": -rc.tilt * ctrl_dt * (1.0 - rot[:, 2, 2]),
        "goal": rc.goal * ctrl_dt * (np.linalg.norm(pos - goal, axis=1) < rc.goal_radius),
        "height": -rc.height * ctrl_dt * np.abs(pos[:, 2] - goal[:, 2]),
        "centre": np.repeat(-rc.centre * ctrl_dt * np.linalg.norm((pos - goal).reshape(E, N, 3).mean(1), axis=1), N),
    }
    terms = np.stack([formulas[name] for name in REWARD_TERMS[:KERNEL_TERMS]])
    new_state = dict(pos=pos, vel=vel, rot=rot, omega=omega, motor=motor, goal=goal)
    return new_state, obs, terms.sum(0), terms, contact, touched_obstacle
