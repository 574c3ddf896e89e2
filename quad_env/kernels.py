"""Numba kernels: one call steps every drone of every swarm, in place, with no Python loop.

State arrays (M = E * N drones, drone a of swarm e at row e * N + a; float32 or float64, the kernels
specialise on the dtype)::

    pos   [M, 3]     world position, m
    vel   [M, 3]     world velocity, m/s
    rot   [M, 3, 3]  body -> world rotation
    omega [M, 3]     body rates, rad/s
    motor [M, 4]     normalised rotor speed in [0, 1]; thrust fraction = motor^2
    ou    [M, 4]     Ornstein-Uhlenbeck thrust noise state (multiplies the command)
    goal  [M, 3]     goal position, m

Per swarm: ``contact [E, N, N] uint8`` (pair a < b touching at the last step), ``room_contact [M]``,
``rng [E] uint64`` (SplitMix64 streams, see ``quad_env.rng``), ``step_count [E]`` and the episode
accumulators. Obstacles: ``obst [E, G, G] uint8`` (1 = a cylinder on the centre of grid cell (ix, iy),
cell ix spanning x in [x0 + ix * cell, x0 + (ix + 1) * cell)) and ``obst_contact [M] uint8`` (the drone
touched a cylinder at the last step). Only the cells near a drone are looked at.

The whole-batch kernels (``step_with_metrics_kernel``, ``observe_kernel``, ``spawn_kernel``, ...) take these
arrays in namedtuples, built once with keywords by ``VecQuadEnv``: ``SwarmState`` (the drones and their
per-swarm memories), ``StepOutput``, ``EpisodeMetrics``, ``Obstacles``, ``SpawnBox``; a field is read by name, so
two arrays of one type cannot be swapped at a call. The per-drone helpers below them take plain arrays.

Reward: the terms are ``quad_env.config.REWARD_TERMS`` (one ordered tuple; row ``T_<TERM>`` of ``terms``, from
``quad_env.params``); ``reward_terms`` computes all but "crash" (VecQuadEnv's) for one drone. Episode
accumulator columns: ``ACC_COLUMNS`` and ``AG_COLUMNS`` below, the ``ACC_*`` / ``AG_*`` indices derived from them.

One control step of one swarm (``step_kernel``):
  1. every drone: ``substeps`` physics steps (motor lag, thrust noise, rigid body, floor and walls,
     cylinders);
  2. every 50th step (config): re-orthonormalise the rotations;
  3. one pass over pairs a < b: new contacts, collision response, proximity sums, downwash impulses;
  4. one pass over drones: K nearest neighbours (partial selection), observation row and reward terms
     (``reward.collision_form``: "paper" charges c2 once per drone entering contact and sums c3 over the
     K observed neighbours; "pairwise" charges c2 per new pair and sums c3 over every other drone).
Pair effects (collisions, downwash) act once per control step, as in the QuadSwarm simulator; the
downwash is an impulse ``a * control_dt``.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np

from quad_env.jit_cache import njit  # numba's njit, cached under the sources' hash
from quad_env.params import (
    F_ARM, F_C_ACTION, F_C_CENTRE, F_C_COLL, F_C_FLOOR, F_C_GOAL, F_C_HEIGHT, F_C_TILT, F_C_OMEGA, F_C_POS, F_C_PROX,
    F_COLL_DIST, F_COLL_KICK, F_COLL_REST,
    F_CTRL_DT, F_DRAG, F_DT, F_DW_ACC, F_DW_LEN, F_DW_RAD, F_FLOOR_Z, F_GRAV, F_IXX, F_IYY, F_IZZ, F_KTAU,
    F_MASS, F_MOTOR_GAIN, F_NOISE_OMEGA, F_NOISE_POS, F_NOISE_VEL, F_OMEGA_MAX, F_OU_SIGMA, F_OU_THETA,
    F_PROX_DIST, F_ROOM_H, F_ROOM_HALF, F_SENSE_R, F_TMAX, F_WALL_REST, I_COLL_KICK, I_DOWNWASH, I_EP_STEPS,
    F_GOAL_R, I_FULL_NB, I_GRACE_STEPS, I_K, I_N, I_NB_DIM, I_OBS_DIM, I_REORTHO, I_SENSOR_NOISE, I_SUBSTEPS,
    I_TAIL1_STEPS, I_TAIL3_STEPS, I_TAIL_STEPS, I_THRUST_NOISE, KERNEL_TERMS, F_C_OBST, F_OBST_CELL, F_OBST_CONTACT_R,
    COLL_FORM_PAPER, I_COLL_FORM,
    F_OBST_LOOKUP_ORIGIN, F_OBST_ORIGIN, F_OBST_R, F_OBST_SDF_MAX, I_OBST_CELLS, I_OBST_LOOKUP, I_OBSTACLES,
    REWARD_TERMS, SDF_SPACING, T_ACTION, T_CENTRE, T_COLLISION, T_FLOOR, T_GOAL, T_HEIGHT, T_OMEGA, T_POS, T_PROXIMITY,
    T_TILT,
)

from quad_env.rng import normal_from, normal_pair, uniform

# The whole-batch kernels take their arrays in these bundles (numba passes namedtuples of arrays by field), so two
# arrays of the same type cannot be swapped silently at a call. Build them with keywords; fields hold the arrays
# themselves (no copy): writes go to the caller's arrays.
SwarmState = namedtuple("SwarmState", (
    "pos", "vel", "rot", "omega", "motor", "ou", "goal",  # per drone [M, ...] (module docstring)
    "contact",  # uint8 [E, N, N]: pair a < b touching at the last step
    "room_contact",  # uint8 [M]: touching the floor, a wall or the ceiling at the last step
    "rng",  # uint64 [E]: the swarms' random streams
    "step_count",  # int64 [E]: control steps of the episode so far
))
StepOutput = namedtuple("StepOutput", (
    "obs",  # float [M, D]
    "rew",  # float [M]
    "terms",  # float [>= KERNEL_TERMS, M]: rows T_* of REWARD_TERMS
    "done",  # bool [E]: the episode reached its length (or diverged)
    "diverged",  # bool [E]: a drone's state became non-finite
))
EpisodeMetrics = namedtuple("EpisodeMetrics", (
    "acc",  # float64 [E, NUM_ACC] (ACC_COLUMNS)
    "agent_acc",  # float64 [M, NUM_AGENT_ACC] (AG_COLUMNS)
    "jumped",  # uint8 [E]: set by the scenario (the goals jumped before this step), cleared by the step
))
Obstacles = namedtuple("Obstacles", (
    "grid",  # uint8 [E, G, G]: 1 = a cylinder on cell (ix, iy)
    "index",  # [E, L, L, S]: the obstacle field's lookup index (quad_env.obstacles.index_obstacles)
    "contact",  # uint8 [M]: the drone touched a cylinder at the last step
))
SpawnBox = namedtuple("SpawnBox", (
    "center",  # float64 [E, 3]: the box centre of each swarm
    "half",  # float64 [E, 3]: its half-sizes (x, y, z)
    "min_z",  # float: lowest spawn height, m
    "min_sep",  # float: least distance between spawned drones, m (rejection sampling, 100 tries)
))

# Episode accumulator columns (float64 [E, NUM_ACC]): one name per column, in order; ACC_<NAME> = its index.
ACC_COLUMNS = (
    "return",  # sum over steps and agents of the reward
    *("term_" + t for t in REWARD_TERMS),  # per-term sums, order of REWARD_TERMS
    "collisions",  # new drone-drone contacts (pairs)
    "room",  # new floor / wall / ceiling contacts (drones)
    "dist_tail",  # sum over the last-5-s steps of the mean distance to goal
    "tail_steps",  # number of steps in that sum
    "dist_final",  # mean distance to goal after the latest step
    "dist_tail1",  # sum over the last-1-s steps of the mean distance to goal
    "tail1_steps",
    "dist_tail3",  # sum over the last-3-s steps of the mean distance to goal
    "tail3_steps",
    "coll_grace",  # new drone-drone contacts (pairs) after the grace period
    "room_grace",  # new room contacts (drones) after the grace period
    "obst",  # new drone-obstacle contacts (drones)
    "obst_grace",  # new drone-obstacle contacts (drones) after the grace period
    "respawns",  # drones respawned after touching the floor (env.respawn_on_floor)
)
ACC_RETURN = ACC_COLUMNS.index("return")
ACC_TERMS = ACC_COLUMNS.index("term_" + REWARD_TERMS[0])  # column of term t: ACC_TERMS + T_<t>
ACC_COLLISIONS = ACC_COLUMNS.index("collisions")
ACC_ROOM = ACC_COLUMNS.index("room")
ACC_DIST_TAIL = ACC_COLUMNS.index("dist_tail")
ACC_TAIL_STEPS = ACC_COLUMNS.index("tail_steps")
ACC_DIST_FINAL = ACC_COLUMNS.index("dist_final")
ACC_DIST_TAIL1 = ACC_COLUMNS.index("dist_tail1")
ACC_TAIL1_STEPS = ACC_COLUMNS.index("tail1_steps")
ACC_DIST_TAIL3 = ACC_COLUMNS.index("dist_tail3")
ACC_TAIL3_STEPS = ACC_COLUMNS.index("tail3_steps")
ACC_COLL_GRACE = ACC_COLUMNS.index("coll_grace")
ACC_ROOM_GRACE = ACC_COLUMNS.index("room_grace")
ACC_OBST = ACC_COLUMNS.index("obst")
ACC_OBST_GRACE = ACC_COLUMNS.index("obst_grace")
ACC_RESPAWNS = ACC_COLUMNS.index("respawns")
NUM_ACC = len(ACC_COLUMNS)

# Per-drone episode accumulator columns (float64 [M, NUM_AGENT_ACC]): the success, reached and IColR metrics.
SUCCESS_RADIUS = 0.5  # m: success = within this of the goal at every step of the last SUCCESS_HOLD_S ...
SUCCESS_HOLD_S = 1.0  # ... seconds of the episode (the whole episode if shorter); see VecQuadEnv.episode_stats
SUCCESS_WINDOW = 5  # "reached" (the earlier success): the mean distance over this many steps < SUCCESS_RADIUS
AG_COLUMNS = (
    *(f"ring{k}" for k in range(SUCCESS_WINDOW)),  # the latest distances to goal (ring buffer)
    "since_jump",  # steps recorded since the last goal jump (or the episode start)
    "reached",  # 1 once the windowed mean distance was < SUCCESS_RADIUS since the last goal jump
    "coll_grace",  # new drone-drone contacts of this drone after the grace period
    "obst_grace",  # new drone-obstacle contacts of this drone after the grace period
    "last_out",  # the last control step (episode clock) after which the drone was >= SUCCESS_RADIUS from its goal
)  # ("last_out" 0: never)
AG_RING = AG_COLUMNS.index("ring0")  # SUCCESS_WINDOW columns
AG_SINCE_JUMP = AG_COLUMNS.index("since_jump")
AG_REACHED = AG_COLUMNS.index("reached")
AG_COLL_GRACE = AG_COLUMNS.index("coll_grace")
AG_OBST_GRACE = AG_COLUMNS.index("obst_grace")
AG_LAST_OUT = AG_COLUMNS.index("last_out")
NUM_AGENT_ACC = len(AG_COLUMNS)

# advance_drone's return value: what the drone touched during the control step (bit flags).
TOUCHED_ROOM = 1
TOUCHED_OBSTACLE = 2


# ====================================================================== single drone
@njit(cache=True, inline="always")
def _bounce(p, v, lo, hi, restitution):
    """Keep the coordinate p in [lo, hi]: a drone past a wall is put back on it and its outward speed is
    reversed and damped. Returns (p, v, 1 if it hit)."""
    if p > hi:
        return hi, (-restitution * v if v > 0.0 else v), 1
    if p < lo:
        return lo, (-restitution * v if v < 0.0 else v), 1
    return p, v, 0


@njit(cache=True, inline="always")
def _push_out_of_cylinder(e, px, py, vx, vy, obst, x0, cell, inv_cell, contact_r, n_cells, restitution):
    """A drone whose centre is closer than ``contact_r`` to a cylinder axis is put back on the contact circle
    along the radius, and its inward radial speed is reversed and damped (as at a wall). Config validation
    keeps contact_r below half a cell, so only the cylinder of the drone's own cell can be touched: one
    lookup. Returns (px, py, vx, vy, 1 if it touched)."""
    fx, fy = (px - x0) * inv_cell, (py - x0) * inv_cell
    if not (0.0 <= fx < n_cells and 0.0 <= fy < n_cells):
        return px, py, vx, vy, 0  # outside the grid (or not finite)
    ix, iy = int(fx), int(fy)
    if obst[e, ix, iy] == 0:
        return px, py, vx, vy, 0
    cx, cy = x0 + (ix + 0.5) * cell, x0 + (iy + 0.5) * cell
    dx, dy = px - cx, py - cy
    d2 = dx * dx + dy * dy
    if d2 >= contact_r * contact_r:
        return px, py, vx, vy, 0
    d = np.sqrt(d2)
    nx, ny = (dx / d, dy / d) if d > 0.0 else (1.0, 0.0)
    vn = vx * nx + vy * ny
    if vn < 0.0:  # moving into the cylinder
        vx -= (1.0 + restitution) * vn * nx
        vy -= (1.0 + restitution) * vn * ny
    return cx + contact_r * nx, cy + contact_r * ny, vx, vy, 1


@njit(cache=True, inline="always")
def advance_drone(i, e, action, pos, vel, rot, omega, motor, ou, rng, fp, ip, obst):
    """``substeps`` physics steps of drone ``i`` under ``action[i]``; returns what it touched during them
    (bit flags TOUCHED_ROOM, TOUCHED_OBSTACLE).

    Per physics step (explicit Euler for position, velocity and body rates, exact rotation update):
      motor speed w += gain (sqrt(cmd) - w);  thrust fraction f = clip(w^2 + cmd * ou, 0, 1)
      I w' = tau - w x I w  (rates clipped to +-omega_max);  R <- R exp(dt [w]_x)  (new rates)
      a = R [0, 0, sum T] / m - g e_z - (drag / m) v;  x += dt v;  v += dt a
    then floor (land: zero velocity and rates, level the attitude keeping yaw), walls (bounce) and
    cylinders (``obst``, if obstacles are on: bounce off the surface, like a wall).
    """
    dt = fp[F_DT]
    gain = fp[F_MOTOR_GAIN]
    tmax = fp[F_TMAX]
    arm = fp[F_ARM]
    ktau = fp[F_KTAU]
    inv_m = 1.0 / fp[F_MASS]
    grav = fp[F_GRAV]
    drag = fp[F_DRAG]
    ixx, iyy, izz = fp[F_IXX], fp[F_IYY], fp[F_IZZ]
    wmax = fp[F_OMEGA_MAX]
    theta, sigma = fp[F_OU_THETA], fp[F_OU_SIGMA]
    floor_z, half, height, wall_rest = fp[F_FLOOR_Z], fp[F_ROOM_HALF], fp[F_ROOM_H], fp[F_WALL_REST]
    noise = ip[I_THRUST_NOISE] != 0
    use_obst = ip[I_OBSTACLES] != 0
    x0, cell, contact_r, n_cells = fp[F_OBST_ORIGIN], fp[F_OBST_CELL], fp[F_OBST_CONTACT_R], ip[I_OBST_CELLS]
    inv_cell = 1.0 / cell

    # Commands in [0, 1]; the motors track the rotor speed sqrt(cmd).
    c0 = 0.5 * (min(max(action[i, 0], -1.0), 1.0) + 1.0)
    c1 = 0.5 * (min(max(action[i, 1], -1.0), 1.0) + 1.0)
    c2 = 0.5 * (min(max(action[i, 2], -1.0), 1.0) + 1.0)
    c3 = 0.5 * (min(max(action[i, 3], -1.0), 1.0) + 1.0)
    s0, s1, s2, s3 = np.sqrt(c0), np.sqrt(c1), np.sqrt(c2), np.sqrt(c3)

    # Load the state into registers (written back once at the end).
    w0, w1, w2, w3 = motor[i, 0] * 1.0, motor[i, 1] * 1.0, motor[i, 2] * 1.0, motor[i, 3] * 1.0
    n0, n1, n2, n3 = ou[i, 0] * 1.0, ou[i, 1] * 1.0, ou[i, 2] * 1.0, ou[i, 3] * 1.0
    px, py, pz = pos[i, 0] * 1.0, pos[i, 1] * 1.0, pos[i, 2] * 1.0
    vx, vy, vz = vel[i, 0] * 1.0, vel[i, 1] * 1.0, vel[i, 2] * 1.0
    wx, wy, wz = omega[i, 0] * 1.0, omega[i, 1] * 1.0, omega[i, 2] * 1.0
    r00, r01, r02 = rot[i, 0, 0] * 1.0, rot[i, 0, 1] * 1.0, rot[i, 0, 2] * 1.0
    r10, r11, r12 = rot[i, 1, 0] * 1.0, rot[i, 1, 1] * 1.0, rot[i, 1, 2] * 1.0
    r20, r21, r22 = rot[i, 2, 0] * 1.0, rot[i, 2, 1] * 1.0, rot[i, 2, 2] * 1.0
    touched = 0
    stream = rng[e]  # the swarm's random stream, kept in a register while this drone steps

    for _ in range(ip[I_SUBSTEPS]):
        # ---- motors: first-order lag on rotor speed, multiplicative OU noise on the command
        w0 += gain * (s0 - w0)
        w1 += gain * (s1 - w1)
        w2 += gain * (s2 - w2)
        w3 += gain * (s3 - w3)
        f0, f1, f2, f3 = w0 * w0, w1 * w1, w2 * w2, w3 * w3
        if noise:
            g0, stream = normal_from(stream)
            g1, stream = normal_from(stream)
            g2, stream = normal_from(stream)
            g3, stream = normal_from(stream)
            n0 += -theta * n0 + sigma * g0
            n1 += -theta * n1 + sigma * g1
            n2 += -theta * n2 + sigma * g2
            n3 += -theta * n3 + sigma * g3
            f0 += c0 * n0
            f1 += c1 * n1
            f2 += c2 * n2
            f3 += c3 * n3
        t0 = tmax * min(max(f0, 0.0), 1.0)
        t1 = tmax * min(max(f1, 0.0), 1.0)
        t2 = tmax * min(max(f2, 0.0), 1.0)
        t3 = tmax * min(max(f3, 0.0), 1.0)

        # ---- body-frame torques. Motors (+x,-y), (-x,-y), (-x,+y), (+x,+y); spins [-1, +1, -1, +1].
        tau_x = arm * (-t0 - t1 + t2 + t3)  # sum y_m T_m
        tau_y = arm * (-t0 + t1 + t2 - t3)  # -sum x_m T_m
        tau_z = ktau * (-t0 + t1 - t2 + t3)
        thrust = t0 + t1 + t2 + t3

        # ---- translation (explicit Euler, derivatives at the start of the step)
        ax = r02 * thrust * inv_m - drag * vx
        ay = r12 * thrust * inv_m - drag * vy
        az = r22 * thrust * inv_m - grav - drag * vz
        px += dt * vx
        py += dt * vy
        pz += dt * vz
        vx += dt * ax
        vy += dt * ay
        vz += dt * az

        # ---- body rates: I w' = tau - w x (I w)
        hx, hy, hz = ixx * wx, iyy * wy, izz * wz
        dwx = (tau_x - (wy * hz - wz * hy)) / ixx
        dwy = (tau_y - (wz * hx - wx * hz)) / iyy
        dwz = (tau_z - (wx * hy - wy * hx)) / izz
        wx = min(max(wx + dt * dwx, -wmax), wmax)
        wy = min(max(wy + dt * dwy, -wmax), wmax)
        wz = min(max(wz + dt * dwz, -wmax), wmax)

        # ---- rotation: R <- R exp(dt [w]_x), Rodrigues with the new rates
        wn = np.sqrt(wx * wx + wy * wy + wz * wz)
        if wn > 1e-12:
            ang = wn * dt
            kx, ky, kz = wx / wn, wy / wn, wz / wn
            c = np.cos(ang)
            s = np.sin(ang)
            v = 1.0 - c
            e00 = c + v * kx * kx
            e01 = v * kx * ky - s * kz
            e02 = v * kx * kz + s * ky
            e10 = v * ky * kx + s * kz
            e11 = c + v * ky * ky
            e12 = v * ky * kz - s * kx
            e20 = v * kz * kx - s * ky
            e21 = v * kz * ky + s * kx
            e22 = c + v * kz * kz
            a0 = r00 * e00 + r01 * e10 + r02 * e20
            a1 = r00 * e01 + r01 * e11 + r02 * e21
            a2 = r00 * e02 + r01 * e12 + r02 * e22
            b0 = r10 * e00 + r11 * e10 + r12 * e20
            b1 = r10 * e01 + r11 * e11 + r12 * e21
            b2 = r10 * e02 + r11 * e12 + r12 * e22
            d0 = r20 * e00 + r21 * e10 + r22 * e20
            d1 = r20 * e01 + r21 * e11 + r22 * e21
            d2 = r20 * e02 + r21 * e12 + r22 * e22
            r00, r01, r02 = a0, a1, a2
            r10, r11, r12 = b0, b1, b2
            r20, r21, r22 = d0, d1, d2

        # ---- room: the floor lands the drone, walls and ceiling bounce it back
        if pz <= floor_z:
            touched = 1
            pz = floor_z
            if vz <= 0.0:  # landing or resting (a drone taking off has vz > 0)
                vx, vy, vz = 0.0, 0.0, 0.0
                wx, wy, wz = 0.0, 0.0, 0.0
                if r22 != 1.0:  # level it, keeping the heading (a drone already resting level stays as is)
                    yaw = np.arctan2(r10, r00)
                    cy, sy = np.cos(yaw), np.sin(yaw)
                    r00, r01, r02 = cy, -sy, 0.0
                    r10, r11, r12 = sy, cy, 0.0
                    r20, r21, r22 = 0.0, 0.0, 1.0
        else:
            pz, vz, hit = _bounce(pz, vz, floor_z, height, wall_rest)  # (only the ceiling can be hit here)
            touched |= hit
        px, vx, hit = _bounce(px, vx, -half, half, wall_rest)
        touched |= hit
        py, vy, hit = _bounce(py, vy, -half, half, wall_rest)
        touched |= hit
        if use_obst:
            px, py, vx, vy, hit = _push_out_of_cylinder(e, px, py, vx, vy, obst, x0, cell, inv_cell, contact_r,
                                                        n_cells, wall_rest)
            touched |= TOUCHED_OBSTACLE * hit

    rng[e] = stream
    motor[i, 0], motor[i, 1], motor[i, 2], motor[i, 3] = w0, w1, w2, w3
    ou[i, 0], ou[i, 1], ou[i, 2], ou[i, 3] = n0, n1, n2, n3
    pos[i, 0], pos[i, 1], pos[i, 2] = px, py, pz
    vel[i, 0], vel[i, 1], vel[i, 2] = vx, vy, vz
    omega[i, 0], omega[i, 1], omega[i, 2] = wx, wy, wz
    rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2] = r00, r01, r02
    rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2] = r10, r11, r12
    rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2] = r20, r21, r22
    return touched


@njit(cache=True)
def reorthonormalise(i, rot):
    """One Newton step of the polar decomposition: R <- (3 R - R R^T R) / 2 (symmetric in the axes)."""
    r = rot[i]
    # P = R R^T (symmetric)
    p00 = r[0, 0] * r[0, 0] + r[0, 1] * r[0, 1] + r[0, 2] * r[0, 2]
    p01 = r[0, 0] * r[1, 0] + r[0, 1] * r[1, 1] + r[0, 2] * r[1, 2]
    p02 = r[0, 0] * r[2, 0] + r[0, 1] * r[2, 1] + r[0, 2] * r[2, 2]
    p11 = r[1, 0] * r[1, 0] + r[1, 1] * r[1, 1] + r[1, 2] * r[1, 2]
    p12 = r[1, 0] * r[2, 0] + r[1, 1] * r[2, 1] + r[1, 2] * r[2, 2]
    p22 = r[2, 0] * r[2, 0] + r[2, 1] * r[2, 1] + r[2, 2] * r[2, 2]
    for c in range(3):
        x0, x1, x2 = r[0, c] * 1.0, r[1, c] * 1.0, r[2, c] * 1.0
        r[0, c] = 1.5 * x0 - 0.5 * (p00 * x0 + p01 * x1 + p02 * x2)
        r[1, c] = 1.5 * x1 - 0.5 * (p01 * x0 + p11 * x1 + p12 * x2)
        r[2, c] = 1.5 * x2 - 0.5 * (p02 * x0 + p12 * x1 + p22 * x2)


@njit(cache=True)
def _is_finite_drone(i, pos, vel, rot, omega, motor):
    s = 0.0
    for k in range(3):
        s += pos[i, k] + vel[i, k] + omega[i, k] + rot[i, k, 0] + rot[i, k, 1] + rot[i, k, 2]
    for k in range(4):
        s += motor[i, k]
    return np.isfinite(s)


# ====================================================================== pair effects
@njit(cache=True)
def gather_positions(e, pos, n_agents, px, py, pz):
    """Copy swarm ``e``'s positions into the contiguous scratch rows px, py, pz [N] (float64)."""
    base = e * n_agents
    for a in range(n_agents):
        px[a] = pos[base + a, 0]
        py[a] = pos[base + a, 1]
        pz[a] = pos[base + a, 2]


@njit(cache=True, inline="always")
def _squared_distances(a, first, n_agents, px, py, pz, row):
    """row[b] = |x_b - x_a|^2 for b in [first, N): a branch-free loop the compiler vectorises."""
    xa, ya, za = px[a], py[a], pz[a]
    for b in range(first, n_agents):
        dx = px[b] - xa
        dy = py[b] - ya
        dz = pz[b] - za
        row[b] = dx * dx + dy * dy + dz * dz


@njit(cache=True)
def pair_effects(e, pos, vel, rot, omega, contact, rng, fp, ip, new_coll, coll_pen, touch, prox, px, py, pz, row):
    """Collisions, proximity and downwash over every pair a < b of swarm ``e``.

    Writes ``new_coll [N]`` (new contacts of each drone: touching pairs that were not touching at the last
    step), ``coll_pen [N]`` (what the c2 penalty multiplies: ``new_coll`` in the "pairwise" collision form;
    in the "paper" form 1 if the drone touches some drone now and touched none at the last step, else 0)
    and ``prox [N]`` (sum over every other drone j of [1 - d/d_p]_+: the "pairwise" proximity sum), and
    updates velocities (collision response, downwash) and body rates (collision kick). Returns the
    number of new contacts (pairs). ``px, py, pz`` hold the swarm's positions (``gather_positions``);
    ``row`` (float [N]) and ``touch`` (uint8 [N]: bit 1 touched a drone at the last step, bit 2 touches one now)
    are scratch. Squared distances of a row of pairs are computed in one vectorised loop; only
    pairs within reach of an effect (or still marked touching) take the slow path.

    Collision response of a touching pair that approaches along the unit normal n: the normal velocity
    components are exchanged (equal masses) and scaled by the restitution; each drone gets a random
    body-rate kick (Gaussian, std ``collision_kick`` per axis) when noise is on.
    Downwash: if b lies below a's rotor disc (0 < s < L along -z_a and radial distance < r),
    v_b += -z_a * a0 (1 - s / L) * control_dt; and symmetrically.
    """
    n_agents = ip[I_N]
    base = e * n_agents
    cd = fp[F_COLL_DIST]
    cd2 = cd * cd
    rest = fp[F_COLL_REST]
    kick = fp[F_COLL_KICK]
    use_kick = ip[I_COLL_KICK] != 0
    dp = fp[F_PROX_DIST]
    dp2 = dp * dp
    use_dw = ip[I_DOWNWASH] != 0
    dw_len, dw_rad = fp[F_DW_LEN], fp[F_DW_RAD]
    dw_reach2 = dw_len * dw_len + dw_rad * dw_rad
    dw_rad2 = dw_rad * dw_rad
    dw_gain = fp[F_DW_ACC] * fp[F_CTRL_DT]
    reach2 = max(dp2, cd2)
    if use_dw:
        reach2 = max(reach2, dw_reach2)
    count = 0
    for a in range(n_agents):
        new_coll[a] = 0.0
        prox[a] = 0.0
        touch[a] = 0
    for a in range(n_agents):
        i = base + a
        _squared_distances(a, a + 1, n_agents, px, py, pz, row)
        for b in range(a + 1, n_agents):
            d2 = row[b]
            if d2 >= reach2 and contact[e, a, b] == 0:
                continue  # the common case: far apart, nothing to do
            j = base + b
            dx = px[b] - px[a]
            dy = py[b] - py[a]
            dz = pz[b] - pz[a]
            if d2 < dp2:
                pen = 1.0 - np.sqrt(d2) / dp
                prox[a] += pen
                prox[b] += pen
            if contact[e, a, b] != 0:
                touch[a] |= 1
                touch[b] |= 1
            if d2 <= cd2:
                touch[a] |= 2
                touch[b] |= 2
                if contact[e, a, b] == 0:
                    contact[e, a, b] = 1
                    new_coll[a] += 1.0
                    new_coll[b] += 1.0
                    count += 1
                d = np.sqrt(d2)
                if d > 0.0:
                    nx, ny, nz = dx / d, dy / d, dz / d
                else:
                    nx, ny, nz = 0.0, 0.0, 1.0
                ua = vel[i, 0] * nx + vel[i, 1] * ny + vel[i, 2] * nz
                ub = vel[j, 0] * nx + vel[j, 1] * ny + vel[j, 2] * nz
                if ub - ua < 0.0:  # approaching
                    da = rest * ub - ua
                    db = rest * ua - ub
                    vel[i, 0] += da * nx
                    vel[i, 1] += da * ny
                    vel[i, 2] += da * nz
                    vel[j, 0] += db * nx
                    vel[j, 1] += db * ny
                    vel[j, 2] += db * nz
                    if use_kick:
                        g0, g1 = normal_pair(rng, e)
                        g2, g3 = normal_pair(rng, e)
                        g4, g5 = normal_pair(rng, e)
                        omega[i, 0] += kick * g0
                        omega[i, 1] += kick * g1
                        omega[i, 2] += kick * g2
                        omega[j, 0] += kick * g3
                        omega[j, 1] += kick * g4
                        omega[j, 2] += kick * g5
            else:
                contact[e, a, b] = 0
            if use_dw and d2 < dw_reach2:
                # b below a? s = depth of b along a's -z axis.
                s = -(dx * rot[i, 0, 2] + dy * rot[i, 1, 2] + dz * rot[i, 2, 2])
                if 0.0 < s < dw_len and d2 - s * s < dw_rad2:
                    dv = dw_gain * (1.0 - s / dw_len)
                    vel[j, 0] -= dv * rot[i, 0, 2]
                    vel[j, 1] -= dv * rot[i, 1, 2]
                    vel[j, 2] -= dv * rot[i, 2, 2]
                # a below b? depth of a along b's -z axis.
                s = dx * rot[j, 0, 2] + dy * rot[j, 1, 2] + dz * rot[j, 2, 2]
                if 0.0 < s < dw_len and d2 - s * s < dw_rad2:
                    dv = dw_gain * (1.0 - s / dw_len)
                    vel[i, 0] -= dv * rot[j, 0, 2]
                    vel[i, 1] -= dv * rot[j, 1, 2]
                    vel[i, 2] -= dv * rot[j, 2, 2]
    paper = ip[I_COLL_FORM] == COLL_FORM_PAPER
    for a in range(n_agents):
        if paper:
            coll_pen[a] = 1.0 if touch[a] == 2 else 0.0  # touches a drone now, touched none before
        else:
            coll_pen[a] = new_coll[a]
    return count


# ====================================================================== observation and reward
@njit(cache=True, inline="always")
def _nearer(b0, b1, b2, b3, b4, b5, b6, b7, b8, x, y, h, cx, cy):
    """Squared distances of the 9 grid points around (x, y) to their nearest axis, updated with axis (cx, cy)."""
    dx0, dx1, dx2 = x - h - cx, x - cx, x + h - cx
    dy0, dy1, dy2 = y - h - cy, y - cy, y + h - cy
    sx0, sx1, sx2 = dx0 * dx0, dx1 * dx1, dx2 * dx2
    sy0, sy1, sy2 = dy0 * dy0, dy1 * dy1, dy2 * dy2
    return (min(b0, sx0 + sy0), min(b1, sx0 + sy1), min(b2, sx0 + sy2),
            min(b3, sx1 + sy0), min(b4, sx1 + sy1), min(b5, sx1 + sy2),
            min(b6, sx2 + sy0), min(b7, sx2 + sy1), min(b8, sx2 + sy2))


@njit(cache=True, inline="always")
def _write_field(row, start, radius, smax, b0, b1, b2, b3, b4, b5, b6, b7, b8):
    row[start + 0] = min(np.sqrt(b0) - radius, smax)
    row[start + 1] = min(np.sqrt(b1) - radius, smax)
    row[start + 2] = min(np.sqrt(b2) - radius, smax)
    row[start + 3] = min(np.sqrt(b3) - radius, smax)
    row[start + 4] = min(np.sqrt(b4) - radius, smax)
    row[start + 5] = min(np.sqrt(b5) - radius, smax)
    row[start + 6] = min(np.sqrt(b6) - radius, smax)
    row[start + 7] = min(np.sqrt(b7) - radius, smax)
    row[start + 8] = min(np.sqrt(b8) - radius, smax)


@njit(cache=True, inline="always")
def obstacle_field(e, x, y, obst, obst_index, fp, ip, row, start):
    """The obstacle field of a drone at (x, y): ``row[start + 3 * a + b]`` = signed horizontal distance from the
    point (x + (a - 1) h, y + (b - 1) h), h = SDF_SPACING, to the nearest cylinder surface of swarm ``e``
    (negative inside), clipped to at most ``obstacle_sdf_max``.

    ``obst_index`` (``quad_env.obstacles.index_obstacles``, rebuilt whenever a layout changes) lists, per
    cell of a lookup grid over the room, the few cylinders that can be nearest to a sample point of a drone
    in that cell: one lookup, then 9 squared distances per candidate and 9 square roots. A cell with too many
    candidates (sparse cylinders, large obstacle_sdf_max) says so and the rings of cells are scanned instead.
    """
    cell, radius, smax = fp[F_OBST_CELL], fp[F_OBST_R], fp[F_OBST_SDF_MAX]
    x0, xl, n_cells, n_lookup = fp[F_OBST_ORIGIN], fp[F_OBST_LOOKUP_ORIGIN], ip[I_OBST_CELLS], ip[I_OBST_LOOKUP]
    inv_cell = 1.0 / cell
    fu, fv = (x - xl) * inv_cell, (y - xl) * inv_cell
    if not (0.0 <= fu <= n_lookup and 0.0 <= fv <= n_lookup):  # outside the room (or not finite)
        _obstacle_field_scan(e, x, y, obst, fp, ip, row, start)
        return
    u, v = min(int(fu), n_lookup - 1), min(int(fv), n_lookup - 1)
    count = np.int64(obst_index[e, u, v, 0])
    if count >= obst_index.shape[3]:
        _obstacle_field_scan(e, x, y, obst, fp, ip, row, start)
        return
    h = SDF_SPACING
    shift = 4 if n_cells <= 16 else 8  # quad_env.obstacles.index_spec
    mask = (1 << shift) - 1
    inf = np.inf
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = inf, inf, inf, inf, inf, inf, inf, inf, inf
    for q in range(count):
        c = np.int64(obst_index[e, u, v, 1 + q])  # (ix << shift) | iy
        cx, cy = x0 + ((c >> shift) + 0.5) * cell, x0 + ((c & mask) + 0.5) * cell
        b0, b1, b2, b3, b4, b5, b6, b7, b8 = _nearer(b0, b1, b2, b3, b4, b5, b6, b7, b8, x, y, h, cx, cy)
    _write_field(row, start, radius, smax, b0, b1, b2, b3, b4, b5, b6, b7, b8)


@njit(cache=True)
def _obstacle_field_scan(e, x, y, obst, fp, ip, row, start):
    """``obstacle_field`` without the index.

    Rings of cells around the drone's cell (ring k: Chebyshev cell distance k) are scanned outwards, keeping
    the 9 points' squared distances to their nearest axis. Every axis in ring k or beyond is at least
    (k - 1/2) cell from the drone and a grid point is at most h sqrt(2) from it, so the scan stops once that
    bound exceeds the nearest axis found by 2 h sqrt(2), or exceeds obstacle_sdf_max + radius + h sqrt(2)
    (whatever lies farther is clipped): usually after ring 1 or 2. Only 9 square roots per drone.
    """
    x0, cell, radius, smax = fp[F_OBST_ORIGIN], fp[F_OBST_CELL], fp[F_OBST_R], fp[F_OBST_SDF_MAX]
    n_cells = ip[I_OBST_CELLS]
    h = SDF_SPACING
    spread = h * np.sqrt(2.0)  # grid point to drone, at most
    ci = int(np.floor((x - x0) / cell))  # the drone's cell (may lie outside the grid)
    cj = int(np.floor((y - x0) / cell))
    last_ring = max(max(ci, n_cells - 1 - ci), max(cj, n_cells - 1 - cj))  # beyond it: no grid cell
    inf = np.inf
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = inf, inf, inf, inf, inf, inf, inf, inf, inf
    nearest2 = inf  # squared distance from the drone to the nearest axis found
    for k in range(0, last_ring + 1):
        if k > 0:
            bound = (k - 0.5) * cell - spread  # lower bound of any grid point's distance to a ring-k axis
            if bound - radius >= smax or (nearest2 < inf and bound >= np.sqrt(nearest2) + spread):
                break
        for i in range(max(ci - k, 0), min(ci + k, n_cells - 1) + 1):
            edge_row = i == ci - k or i == ci + k
            step = 1 if edge_row else 2 * k  # inner rows of the ring: only its two side cells
            for j in range(cj - k, cj + k + 1, max(step, 1)):
                if j < 0 or j >= n_cells or obst[e, i, j] == 0:
                    continue
                cx, cy = x0 + (i + 0.5) * cell, x0 + (j + 0.5) * cell
                b0, b1, b2, b3, b4, b5, b6, b7, b8 = _nearer(b0, b1, b2, b3, b4, b5, b6, b7, b8, x, y, h, cx, cy)
                nearest2 = min(nearest2, (x - cx) * (x - cx) + (y - cy) * (y - cy))
    _write_field(row, start, radius, smax, b0, b1, b2, b3, b4, b5, b6, b7, b8)


@njit(cache=True, inline="always")
def reward_coefficients(fp, ip):
    """The reward's per-step weights (times the control dt where the term is per step), read once per swarm:
    (c_pos, c_coll, c_prox, c_omega, c_act, c_floor, c_tilt, floor_z, c_obst, d_p, proximity over the observed
    neighbours only, c_goal, goal radius, c_height, c_centre)."""
    dt = fp[F_CTRL_DT]
    return (fp[F_C_POS] * dt, fp[F_C_COLL], fp[F_C_PROX] * dt, fp[F_C_OMEGA] * dt, fp[F_C_ACTION] * dt,
            fp[F_C_FLOOR] * dt, fp[F_C_TILT] * dt, fp[F_FLOOR_Z], fp[F_C_OBST], fp[F_PROX_DIST],
            ip[I_COLL_FORM] == COLL_FORM_PAPER, fp[F_C_GOAL] * dt, fp[F_GOAL_R], fp[F_C_HEIGHT] * dt,
            fp[F_C_CENTRE] * dt)


@njit(cache=True, inline="always")
def reward_terms(dist, z, dz, wx, wy, wz, u0, u1, u2, u3, r_zz, coll_pen, new_obst, prox, near, centre, coef):
    """One drone's reward terms from scalars of its true state (not the noisy observation), in the order of
    ``REWARD_TERMS`` (all but "crash"): ``dist`` to goal, height ``z`` and its offset ``dz`` = z - z^d, body rates
    ``w*``, raw action ``u*`` (clipped here), ``r_zz`` = R[2, 2] (cos tilt), its new-contact penalty count
    ``coll_pen`` and new obstacle contacts ``new_obst``, and its proximity sums: ``prox`` over every other drone
    ("pairwise" form) and ``near`` over its observed neighbours ("paper" form), the norm ``centre`` of the swarm's
    mean offset from its goals (the same for every drone); ``coef``: the swarm's
    ``reward_coefficients``. Scalars only: array arguments would cost reference counting per drone.
    A new term: its name in ``REWARD_TERMS``, its formula here, its weight in ``reward_coefficients``, its float64
    twin in ``quad_env.reference``, its coefficient in ``RewardConfig`` (packed by ``pack_params``)."""
    (c_pos, c_coll, c_prox, c_omega, c_act, c_floor, c_tilt, floor_z, c_obst, dp, prox_nb, c_goal, goal_r, c_h,
     c_c) = coef
    u0 = min(max(u0, -1.0), 1.0)
    u1 = min(max(u1, -1.0), 1.0)
    u2 = min(max(u2, -1.0), 1.0)
    u3 = min(max(u3, -1.0), 1.0)
    r_pos = -c_pos * dist
    r_coll = -c_coll * coll_pen - c_obst * new_obst
    r_prox = -c_prox * (near if prox_nb else prox)
    r_omega = -c_omega * np.sqrt(wx * wx + wy * wy + wz * wz)
    r_act = -c_act * np.sqrt(u0 * u0 + u1 * u1 + u2 * u2 + u3 * u3)
    r_floor = -c_floor if z <= floor_z else 0.0
    r_tilt = -c_tilt * (1.0 - r_zz)
    r_goal = c_goal if dist < goal_r else 0.0
    r_height = -c_h * abs(dz)
    r_centre = -c_c * centre
    return r_pos, r_coll, r_prox, r_omega, r_act, r_floor, r_tilt, r_goal, r_height, r_centre


@njit(cache=True)
def observe_swarm(e, pos, vel, rot, omega, goal, action, coll_pen, new_obst, prox, px, py, pz, d2row, rng, fp, ip,
                  obs, rew, terms, nb_idx, nb_d2, with_reward, obst, obst_index):
    """Observation rows (and, if ``with_reward``, reward terms) of every drone of swarm ``e``.

    Neighbours: the K nearest other drones by centre distance, ties broken by the lower index: the
    squared distances to all N drones are computed in one vectorised loop (positions from
    ``gather_positions``), then one scan inserts into a K-slot sorted list (O(N K) worst case, O(N)
    typical), never sorting all N.
    Slots beyond the real neighbours or the sensing radius are zero with mask 0. With obstacles on, the
    obstacle field (``obstacle_field``, no sensor noise) ends the row.
    Rewards: ``coll_pen`` [N] multiplies c2 (``pair_effects``), ``new_obst`` [N] (new drone-obstacle contacts)
    the obstacle penalty; the proximity sum is ``prox`` [N] (every other drone) in the "pairwise" collision form
    and, in the "paper" form, runs over the drone's neighbours found here (the K nearest within the sensing
    radius: the drones in its observation's neighbour slots).
    Returns the swarm's mean distance to goal.
    """
    n_agents = ip[I_N]
    k_slots = ip[I_K]
    base = e * n_agents
    full = ip[I_FULL_NB] != 0
    nb_dim = ip[I_NB_DIM]
    mask_start = 18 + k_slots * nb_dim
    sense2 = fp[F_SENSE_R] * fp[F_SENSE_R]
    sensor_noise = ip[I_SENSOR_NOISE] != 0
    sp, sv, sw = fp[F_NOISE_POS], fp[F_NOISE_VEL], fp[F_NOISE_OMEGA]
    use_obst = ip[I_OBSTACLES] != 0
    field_start = mask_start + k_slots
    coef = reward_coefficients(fp, ip)  # once per swarm, not per drone
    centre = 0.0  # ||mean_j (x_j - x_j^d)||: the swarm's offset from its goals, for the "centre" term
    if with_reward and coef[14] != 0.0:
        mx, my, mz = 0.0, 0.0, 0.0
        for a in range(n_agents):
            mx += pos[base + a, 0] - goal[base + a, 0]
            my += pos[base + a, 1] - goal[base + a, 1]
            mz += pos[base + a, 2] - goal[base + a, 2]
        centre = np.sqrt(mx * mx + my * my + mz * mz) / n_agents
    dist_sum = 0.0
    for a in range(n_agents):
        i = base + a
        row = obs[i]
        xi, yi, zi = pos[i, 0] * 1.0, pos[i, 1] * 1.0, pos[i, 2] * 1.0
        gx, gy, gz = xi - goal[i, 0], yi - goal[i, 1], zi - goal[i, 2]
        dist = np.sqrt(gx * gx + gy * gy + gz * gz)
        dist_sum += dist

        # ---- self block: [x - x^d, v, R (row-major), omega]
        ox, oy, oz = gx, gy, gz
        ovx, ovy, ovz = vel[i, 0] * 1.0, vel[i, 1] * 1.0, vel[i, 2] * 1.0
        owx, owy, owz = omega[i, 0] * 1.0, omega[i, 1] * 1.0, omega[i, 2] * 1.0
        if sensor_noise:
            stream = rng[e]
            g0, stream = normal_from(stream)
            g1, stream = normal_from(stream)
            g2, stream = normal_from(stream)
            g3, stream = normal_from(stream)
            g4, stream = normal_from(stream)
            g5, stream = normal_from(stream)
            g6, stream = normal_from(stream)
            g7, stream = normal_from(stream)
            g8, stream = normal_from(stream)
            rng[e] = stream
            ox += sp * g0
            oy += sp * g1
            oz += sp * g2
            ovx += sv * g3
            ovy += sv * g4
            ovz += sv * g5
            owx += sw * g6
            owy += sw * g7
            owz += sw * g8
        row[0], row[1], row[2] = ox, oy, oz
        row[3], row[4], row[5] = ovx, ovy, ovz
        for r in range(3):
            for c in range(3):
                row[6 + 3 * r + c] = rot[i, r, c]
        row[15], row[16], row[17] = owx, owy, owz

        # ---- K nearest neighbours: keep a sorted list of (d2, index); later equal d2 lose ties
        found = 0
        if k_slots > 0:
            _squared_distances(a, 0, n_agents, px, py, pz, d2row)
            d2row[a] = np.nan  # never selects itself (NaN fails every comparison)
            kth = np.inf  # d2 of the K-th slot once the list is full
            for b in range(n_agents):
                d2 = d2row[b]
                if d2 <= sense2 and d2 < kth:  # in range, and beats the K-th (strictly: earlier wins ties)
                    slot = found if found < k_slots else k_slots - 1
                    while slot > 0 and nb_d2[slot - 1] > d2:
                        nb_d2[slot] = nb_d2[slot - 1]
                        nb_idx[slot] = nb_idx[slot - 1]
                        slot -= 1
                    nb_d2[slot] = d2
                    nb_idx[slot] = base + b
                    if found < k_slots:
                        found += 1
                    if found == k_slots:
                        kth = nb_d2[k_slots - 1]
        for k in range(k_slots):
            off = 18 + k * nb_dim
            if k < found:
                j = nb_idx[k]
                row[off + 0] = pos[j, 0] - xi
                row[off + 1] = pos[j, 1] - yi
                row[off + 2] = pos[j, 2] - zi
                row[off + 3] = vel[j, 0] - vel[i, 0]
                row[off + 4] = vel[j, 1] - vel[i, 1]
                row[off + 5] = vel[j, 2] - vel[i, 2]
                if full:
                    for r in range(3):
                        for c in range(3):
                            row[off + 6 + 3 * r + c] = rot[j, r, c]
                    row[off + 15] = omega[j, 0]
                    row[off + 16] = omega[j, 1]
                    row[off + 17] = omega[j, 2]
                    row[off + 18] = goal[j, 0] - pos[j, 0]
                    row[off + 19] = goal[j, 1] - pos[j, 1]
                    row[off + 20] = goal[j, 2] - pos[j, 2]
                row[mask_start + k] = 1.0
            else:
                for q in range(nb_dim):
                    row[off + q] = 0.0
                row[mask_start + k] = 0.0
        if use_obst:
            obstacle_field(e, xi, yi, obst, obst_index, fp, ip, row, field_start)
        else:
            for q in range(field_start, ip[I_OBS_DIM]):
                row[q] = 0.0  # an obstacle layout with obstacles switched off (kernel tests) reads zeros

        if with_reward:
            near = 0.0  # the "paper" proximity sum: over the observed neighbours (the K nearest, in range)
            if coef[10]:  # (the "pairwise" form uses prox instead)
                dp = coef[9]
                for k in range(found):
                    if nb_d2[k] < dp * dp:
                        near += 1.0 - np.sqrt(nb_d2[k]) / dp
            r = reward_terms(dist, zi, gz, omega[i, 0] * 1.0, omega[i, 1] * 1.0, omega[i, 2] * 1.0, action[i, 0] * 1.0,
                             action[i, 1] * 1.0, action[i, 2] * 1.0, action[i, 3] * 1.0, rot[i, 2, 2] * 1.0,
                             coll_pen[a], new_obst[a], prox[a], near, centre, coef)
            terms[T_POS, i], terms[T_COLLISION, i], terms[T_PROXIMITY, i] = r[0], r[1], r[2]
            terms[T_OMEGA, i], terms[T_ACTION, i], terms[T_FLOOR, i], terms[T_TILT, i] = r[3], r[4], r[5], r[6]
            terms[T_GOAL, i], terms[T_HEIGHT, i], terms[T_CENTRE, i] = r[7], r[8], r[9]
            rew[i] = r[0] + r[1] + r[2] + r[3] + r[4] + r[5] + r[6] + r[7] + r[8] + r[9]  # (this order: reproducible)
    return dist_sum / n_agents


# ====================================================================== episode metrics
@njit(cache=True)
def agent_metrics(e, step, pos, goal, new_coll, new_obst, after_grace, jumped, agent_acc, n_agents):
    """Per-drone success bookkeeping of swarm ``e`` after its control step number ``step`` (episode clock).

    Success: a drone at SUCCESS_RADIUS or farther from its goal records ``step`` as its last step outside
    (AG_LAST_OUT); ``VecQuadEnv.episode_stats`` compares it with the start of the last SUCCESS_HOLD_S.
    Reached (the earlier success): the distance to goal enters a ring of the last SUCCESS_WINDOW steps; once
    the ring holds that many steps since the last goal jump and their mean is below SUCCESS_RADIUS, the drone
    has reached its goal. A jump (``jumped[e]``) empties the rings and clears "reached". New drone-drone and
    drone-obstacle contacts after the grace period are counted per drone."""
    base = e * n_agents
    if jumped[e] != 0:
        for a in range(n_agents):
            agent_acc[base + a, AG_SINCE_JUMP] = 0.0
            agent_acc[base + a, AG_REACHED] = 0.0
        jumped[e] = 0
    for a in range(n_agents):
        i = base + a
        dx, dy, dz = pos[i, 0] - goal[i, 0], pos[i, 1] - goal[i, 1], pos[i, 2] - goal[i, 2]
        since = int(agent_acc[i, AG_SINCE_JUMP])
        dist = np.sqrt(dx * dx + dy * dy + dz * dz)
        if not dist < SUCCESS_RADIUS:
            agent_acc[i, AG_LAST_OUT] = step
        agent_acc[i, AG_RING + since % SUCCESS_WINDOW] = dist
        since += 1
        agent_acc[i, AG_SINCE_JUMP] = since
        if since >= SUCCESS_WINDOW:
            total = 0.0
            for k in range(SUCCESS_WINDOW):
                total += agent_acc[i, AG_RING + k]
            if total < SUCCESS_RADIUS * SUCCESS_WINDOW:
                agent_acc[i, AG_REACHED] = 1.0
        if after_grace:
            agent_acc[i, AG_COLL_GRACE] += new_coll[a]
            agent_acc[i, AG_OBST_GRACE] += new_obst[a]


# ====================================================================== whole-batch kernels
@njit(cache=True)
def step_kernel(action, state, fp, ip, out, acc):
    """``step_with_metrics_kernel`` without the per-drone metrics and without obstacles (``ip`` must have them
    off): physics tests, model validation. ``acc``: float64 [E, NUM_ACC]."""
    num_envs, num_drones = state.step_count.shape[0], state.pos.shape[0]
    metrics = EpisodeMetrics(acc, np.zeros((num_drones, NUM_AGENT_ACC), np.float64), np.zeros(num_envs, np.uint8))
    obstacles = Obstacles(np.zeros((num_envs, 1, 1), np.uint8), np.zeros((num_envs, 1, 1, 1), np.uint8),
                          np.zeros(num_drones, np.uint8))
    return step_with_metrics_kernel(action, state, fp, ip, out, metrics, obstacles)


@njit(cache=True)
def step_with_metrics_kernel(action, state, fp, ip, out, metrics, obstacles):
    """One control step of all E swarms (see the module docstring): ``state`` (SwarmState) advances, ``out``
    (StepOutput) is written, ``metrics`` (EpisodeMetrics) accumulate. Returns the number of swarms done.

    ``out.done[e]`` = the episode of swarm e reached its length (truncation). ``out.diverged[e]`` = a drone's
    state became non-finite: that swarm's observation rows keep the previous step's values, its reward
    rows are 0, and it is reported done; the caller decides (raise or reset).
    Episode metrics go to ``metrics.acc [E, NUM_ACC]`` and ``metrics.agent_acc [M, NUM_AGENT_ACC]``;
    ``metrics.jumped[e] = 1`` (set by the scenario: the goals jumped before this step) restarts the swarm's
    "reached" windows and is cleared here. ``obstacles`` (Obstacles): the cylinders, their lookup index and
    the drones touching one.
    """
    pos, vel, rot, omega = state.pos, state.vel, state.rot, state.omega
    motor, ou, goal = state.motor, state.ou, state.goal
    contact, room_contact, rng, step_count = state.contact, state.room_contact, state.rng, state.step_count
    obs, rew, terms, done, diverged = out.obs, out.rew, out.terms, out.done, out.diverged
    acc, agent_acc, jumped = metrics.acc, metrics.agent_acc, metrics.jumped
    obst, obst_index, obst_contact = obstacles.grid, obstacles.index, obstacles.contact
    n_agents = ip[I_N]
    num_envs = step_count.shape[0]
    k_slots = ip[I_K]
    nb_idx = np.zeros(max(k_slots, 1), np.int64)
    nb_d2 = np.zeros(max(k_slots, 1), np.float64)
    new_coll = np.zeros(n_agents, np.float64)
    coll_pen = np.zeros(n_agents, np.float64)
    touch = np.zeros(n_agents, np.uint8)
    new_obst = np.zeros(n_agents, np.float64)  # (stays 0 without obstacles)
    use_obst = ip[I_OBSTACLES] != 0
    prox = np.zeros(n_agents, np.float64)
    px, py, pz = np.zeros(n_agents), np.zeros(n_agents), np.zeros(n_agents)
    row = np.zeros(n_agents)
    n_done = 0
    for e in range(num_envs):
        base = e * n_agents
        step_count[e] += 1
        reortho = step_count[e] % ip[I_REORTHO] == 0
        after_grace = step_count[e] > ip[I_GRACE_STEPS]
        bad = False
        for a in range(n_agents):
            i = base + a
            touched = advance_drone(i, e, action, pos, vel, rot, omega, motor, ou, rng, fp, ip, obst)
            room = touched & TOUCHED_ROOM
            if room != 0 and room_contact[i] == 0:
                acc[e, ACC_ROOM] += 1.0
                if after_grace:
                    acc[e, ACC_ROOM_GRACE] += 1.0
            room_contact[i] = room
            if use_obst:
                hit = 1 if touched & TOUCHED_OBSTACLE else 0
                new_obst[a] = 1.0 if hit > obst_contact[i] else 0.0  # new: not touching at the last step
                if new_obst[a] != 0.0:
                    acc[e, ACC_OBST] += 1.0
                    if after_grace:
                        acc[e, ACC_OBST_GRACE] += 1.0
                obst_contact[i] = hit
            if reortho:
                reorthonormalise(i, rot)
            if not _is_finite_drone(i, pos, vel, rot, omega, motor):
                bad = True
        done[e] = step_count[e] >= ip[I_EP_STEPS]
        if bad:
            diverged[e] = True
            done[e] = True
            for a in range(n_agents):
                rew[base + a] = 0.0
                for t in range(KERNEL_TERMS):
                    terms[t, base + a] = 0.0
            n_done += 1
            continue
        gather_positions(e, pos, n_agents, px, py, pz)
        n_new = pair_effects(e, pos, vel, rot, omega, contact, rng, fp, ip, new_coll, coll_pen, touch, prox, px, py,
                             pz, row)
        acc[e, ACC_COLLISIONS] += n_new
        mean_dist = observe_swarm(e, pos, vel, rot, omega, goal, action, coll_pen, new_obst, prox, px, py, pz, row,
                                  rng, fp, ip, obs, rew, terms, nb_idx, nb_d2, True, obst, obst_index)
        # ---- episode statistics
        for a in range(n_agents):
            i = base + a
            acc[e, ACC_RETURN] += rew[i]
            for t in range(KERNEL_TERMS):
                acc[e, ACC_TERMS + t] += terms[t, i]
        acc[e, ACC_DIST_FINAL] = mean_dist
        if step_count[e] > ip[I_EP_STEPS] - ip[I_TAIL_STEPS]:
            acc[e, ACC_DIST_TAIL] += mean_dist
            acc[e, ACC_TAIL_STEPS] += 1.0
        if step_count[e] > ip[I_EP_STEPS] - ip[I_TAIL3_STEPS]:
            acc[e, ACC_DIST_TAIL3] += mean_dist
            acc[e, ACC_TAIL3_STEPS] += 1.0
        if step_count[e] > ip[I_EP_STEPS] - ip[I_TAIL1_STEPS]:
            acc[e, ACC_DIST_TAIL1] += mean_dist
            acc[e, ACC_TAIL1_STEPS] += 1.0
        if after_grace:
            acc[e, ACC_COLL_GRACE] += n_new
        agent_metrics(e, step_count[e], pos, goal, new_coll, new_obst, after_grace, jumped, agent_acc, n_agents)
        if done[e]:
            n_done += 1
    return n_done


@njit(cache=True)
def observe_kernel(selected, state, fp, ip, obs, obstacles):
    """Observation rows ``obs`` of the swarms with ``selected[e]`` (after a reset or a state change)."""
    pos, vel, rot, omega, goal, rng = state.pos, state.vel, state.rot, state.omega, state.goal, state.rng
    obst, obst_index = obstacles.grid, obstacles.index
    n_agents = ip[I_N]
    k_slots = ip[I_K]
    nb_idx = np.zeros(max(k_slots, 1), np.int64)
    nb_d2 = np.zeros(max(k_slots, 1), np.float64)
    dummy_action = np.zeros((1, 4), np.float64)
    dummy_vec = np.zeros(n_agents, np.float64)
    dummy_rew = np.zeros(1, np.float32)
    dummy_terms = np.zeros((KERNEL_TERMS, 1), np.float32)
    px, py, pz = np.zeros(n_agents), np.zeros(n_agents), np.zeros(n_agents)
    row = np.zeros(n_agents)
    for e in range(selected.shape[0]):
        if selected[e]:
            gather_positions(e, pos, n_agents, px, py, pz)
            observe_swarm(e, pos, vel, rot, omega, goal, dummy_action, dummy_vec, dummy_vec, dummy_vec, px, py, pz,
                          row, rng, fp, ip, obs, dummy_rew, dummy_terms, nb_idx, nb_d2, False, obst, obst_index)


@njit(cache=True)
def refresh_contacts_kernel(selected, state, fp, ip):
    """Set the contact memory of the selected swarms to the current touching pairs (no new-contact count)."""
    pos, contact = state.pos, state.contact
    n_agents = ip[I_N]
    cd2 = fp[F_COLL_DIST] * fp[F_COLL_DIST]
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        base = e * n_agents
        for a in range(n_agents):
            for b in range(n_agents):
                contact[e, a, b] = 0
            for b in range(a + 1, n_agents):
                d2 = 0.0
                for k in range(3):
                    d = pos[base + b, k] - pos[base + a, k]
                    d2 += d * d
                contact[e, a, b] = 1 if d2 <= cd2 else 0


@njit(cache=True, inline="always")
def _spawn_drone(i, e, base, n_agents, check_below, center, pos, vel, rot, omega, motor, ou, room_contact, rng,
                 fp, spawn_half, spawn_min_z, spawn_min_sep):
    """Put drone ``i`` of swarm ``e`` at rest, motors off, random yaw, at a uniform point of the box
    ``center[e] +- spawn_half[e]`` (per axis; z cut to [spawn_min_z, ceiling]) at least ``spawn_min_sep``
    from the swarm's drones ``base .. base + check_below - 1`` other than ``i`` (rejection sampling, 100
    tries, then accepted anyway)."""
    half = fp[F_ROOM_HALF]
    height = fp[F_ROOM_H]
    sep2 = spawn_min_sep * spawn_min_sep
    hx, hy, hz = spawn_half[e, 0], spawn_half[e, 1], spawn_half[e, 2]
    z_lo = max(center[e, 2] - hz, spawn_min_z)
    z_hi = min(max(center[e, 2] + hz, z_lo), height)
    x, y, z = 0.0, 0.0, 0.0
    for _ in range(100):
        x = min(max(center[e, 0] + hx * (2.0 * uniform(rng, e) - 1.0), -half), half)
        y = min(max(center[e, 1] + hy * (2.0 * uniform(rng, e) - 1.0), -half), half)
        z = z_lo + (z_hi - z_lo) * uniform(rng, e)
        ok = True
        for b in range(check_below):
            j = base + b
            if j == i:
                continue
            d2 = (pos[j, 0] - x) ** 2 + (pos[j, 1] - y) ** 2 + (pos[j, 2] - z) ** 2
            if d2 < sep2:
                ok = False
                break
        if ok:
            break
    pos[i, 0], pos[i, 1], pos[i, 2] = x, y, z
    yaw = 2.0 * np.pi * uniform(rng, e)
    cy, sy = np.cos(yaw), np.sin(yaw)
    rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2] = cy, -sy, 0.0
    rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2] = sy, cy, 0.0
    rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2] = 0.0, 0.0, 1.0
    for k in range(3):
        vel[i, k] = 0.0
        omega[i, k] = 0.0
    for k in range(4):
        motor[i, k] = 0.0
        ou[i, k] = 0.0
    room_contact[i] = 0


@njit(cache=True)
def spawn_kernel(selected, state, box, fp, ip):
    """Start a new episode for the selected swarms: every drone spawned by ``_spawn_drone`` in order
    (``box``, a SpawnBox: ``center[e] +- half[e]``), kept ``min_sep`` away from the drones spawned before it."""
    pos, vel, rot, omega, motor, ou = state.pos, state.vel, state.rot, state.omega, state.motor, state.ou
    room_contact, rng = state.room_contact, state.rng
    center, spawn_half, spawn_min_z, spawn_min_sep = box.center, box.half, box.min_z, box.min_sep
    n_agents = ip[I_N]
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        base = e * n_agents
        for a in range(n_agents):
            _spawn_drone(base + a, e, base, n_agents, a, center, pos, vel, rot, omega, motor, ou, room_contact,
                         rng, fp, spawn_half, spawn_min_z, spawn_min_sep)


@njit(cache=True)
def respawn_kernel(rows, state, box, fp, ip):
    """Respawn the drones ``rows`` (int [R], ascending) mid-episode (``env.respawn_on_floor``): each one as
    at an episode start (``box``, a SpawnBox), kept ``box.min_sep`` away from every other drone of its swarm."""
    pos, vel, rot, omega, motor, ou = state.pos, state.vel, state.rot, state.omega, state.motor, state.ou
    room_contact, rng = state.room_contact, state.rng
    center, spawn_half, spawn_min_z, spawn_min_sep = box.center, box.half, box.min_z, box.min_sep
    n_agents = ip[I_N]
    for r in range(rows.shape[0]):
        i = rows[r]
        e = i // n_agents
        _spawn_drone(i, e, e * n_agents, n_agents, n_agents, center, pos, vel, rot, omega, motor, ou,
                     room_contact, rng, fp, spawn_half, spawn_min_z, spawn_min_sep)


@njit(cache=True)
def all_finite(x):
    """True if every entry of the 2-D array ``x`` is finite (no temporary array)."""
    for r in range(x.shape[0]):
        for c in range(x.shape[1]):
            if not np.isfinite(x[r, c]):
                return False
    return True
