"""Obstacle layouts: vertical cylinders (floor to ceiling) on a square grid centred in the room.

The grid has G x G cells of side ``cell`` (``EnvConfig.obstacle_grid_cells``, ``obstacle_cell_size``); cell
(ix, iy) spans x in [x0 + ix cell, x0 + (ix + 1) cell) (x0 = -G cell / 2, the same for y) and, when
occupied, holds a cylinder of diameter ``obstacle_diameter`` on its centre. A layout is ``uint8 [E, G, G]``,
one grid per swarm, drawn anew at every reset from the swarm's own random stream: every cell is occupied
with probability ``obstacle_density``, cells visited in (ix, iy) row-major order, so one seed gives one
layout.

Spawn points and goals are kept out of the cylinders by a single rule, whatever the scenario: after the
goals and the spawn points of an episode are placed, every cylinder whose surface is closer than
``OBSTACLE_CLEARANCE`` (horizontally) to a spawn point or a goal is removed ("obstacles yield"). The
obstacle scenarios (o_random, o_static_same_goal) spawn and aim outside the obstacle grid, so nothing is
removed there and the density is the configured one. Goals that move during an episode (dynamic scenarios
run with obstacles on) are not checked.

The physics (contacts, bounce) and the observation field live in ``quad_env.kernels``.
"""
from __future__ import annotations

import numpy as np

from quad_env.jit_cache import njit  # numba's njit, cached under the sources' hash
from quad_env.config import EnvConfig
from quad_env.rng import uniform

OBSTACLE_CLEARANCE = 0.2  # m between a cylinder surface and any spawn point or goal of the episode


@njit(cache=True)
def draw_obstacles(selected, obst, rng, density):
    """Occupy every cell of the selected swarms' grids with probability ``density`` (one draw per cell)."""
    n = obst.shape[1]
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        for ix in range(n):
            for iy in range(n):
                obst[e, ix, iy] = 1 if uniform(rng, e) < density else 0


@njit(cache=True)
def _clear_around(e, x, y, obst, x0, cell, keep_out):
    """Remove the cylinders of swarm ``e`` whose axis is closer than ``keep_out`` to (x, y)."""
    n = obst.shape[1]
    ix_lo = max(int(np.floor((x - keep_out - x0) / cell)), 0)
    ix_hi = min(int(np.floor((x + keep_out - x0) / cell)), n - 1)
    iy_lo = max(int(np.floor((y - keep_out - x0) / cell)), 0)
    iy_hi = min(int(np.floor((y + keep_out - x0) / cell)), n - 1)
    for ix in range(ix_lo, ix_hi + 1):
        for iy in range(iy_lo, iy_hi + 1):
            dx = x - (x0 + (ix + 0.5) * cell)
            dy = y - (x0 + (iy + 0.5) * cell)
            if dx * dx + dy * dy < keep_out * keep_out:
                obst[e, ix, iy] = 0


@njit(cache=True)
def clear_spawns_and_goals(selected, obst, pos, goal, n_agents, x0, cell, radius, clearance):
    """The "obstacles yield" rule: no cylinder surface within ``clearance`` of a spawn point or a goal."""
    keep_out = radius + clearance
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        for a in range(n_agents):
            i = e * n_agents + a
            _clear_around(e, pos[i, 0], pos[i, 1], obst, x0, cell, keep_out)
            _clear_around(e, goal[i, 0], goal[i, 1], obst, x0, cell, keep_out)


def grid_origin(cfg: EnvConfig) -> float:
    """x (and y) of the grid's lower corner: the grid is centred in the room."""
    return -0.5 * cfg.obstacle_grid_cells * cfg.obstacle_cell_size


def obstacle_centers(grid: np.ndarray, cfg: EnvConfig) -> np.ndarray:
    """Axes (x, y) of the cylinders of one swarm's grid ``[G, G]``: float64 ``[C, 2]`` (row-major cell order)."""
    ix, iy = np.nonzero(grid)
    x0, cell = grid_origin(cfg), cfg.obstacle_cell_size
    return np.stack([x0 + (ix + 0.5) * cell, x0 + (iy + 0.5) * cell], axis=1).astype(np.float64)


# ---------------------------------------------------------------- candidate index for the obstacle field
INDEX_SLOTS = 7  # candidate cylinders kept per lookup cell (8 bytes with the count: the index stays in cache)


def index_spec(cfg: EnvConfig):
    """(dtype, bit shift) of the index entries: a candidate cell is stored as (ix << shift) | iy."""
    return (np.uint8, 4) if cfg.obstacle_grid_cells <= 16 else (np.uint16, 8)


def lookup_pad(cfg: EnvConfig) -> int:
    """Cells added around the obstacle grid so that the lookup grid covers the whole room."""
    spare = cfg.physics.room_half_width - 0.5 * cfg.obstacle_grid_cells * cfg.obstacle_cell_size
    return max(0, int(np.ceil(spare / cfg.obstacle_cell_size - 1e-9)))


@njit(cache=True, inline="always")
def _box_distances(lo_x, hi_x, lo_y, hi_y, cx, cy):
    """(min, max) distance from the point (cx, cy) to the points of the box [lo_x, hi_x] x [lo_y, hi_y]."""
    nx = max(lo_x - cx, 0.0, cx - hi_x)
    ny = max(lo_y - cy, 0.0, cy - hi_y)
    fx = max(abs(lo_x - cx), abs(hi_x - cx))
    fy = max(abs(lo_y - cy), abs(hi_y - cy))
    return np.sqrt(nx * nx + ny * ny), np.sqrt(fx * fx + fy * fy)


@njit(cache=True)
def index_obstacles(selected, obst, index, x0, cell, radius, sdf_max, pad, spacing, shift):
    """For every lookup cell (u, v) of the selected swarms (cells of the obstacle grid's size, ``pad`` more on
    each side), the cylinders that can be the nearest one to a point of the box B = cell grown by ``spacing``
    (where the obstacle field samples lie for a drone in the cell): ``index[e, u, v, 0]`` = their number
    (more than the slots: slots + 1, scan instead), ``index[e, u, v, 1:]`` = their cells (ix << shift) | iy
    (``index_spec``).

    With U = min over cylinders of the largest distance to B, a cylinder is kept if its smallest distance to
    B is <= U (it may be nearest for some point of B) and its surface may come closer than ``sdf_max``."""
    n = obst.shape[1]
    slots = index.shape[3] - 1
    lookup = index.shape[1]
    xl = x0 - pad * cell
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        for u in range(lookup):
            lo_x, hi_x = xl + u * cell - spacing, xl + (u + 1) * cell + spacing
            for v in range(lookup):
                lo_y, hi_y = xl + v * cell - spacing, xl + (v + 1) * cell + spacing
                upper = np.inf
                for ix in range(n):
                    for iy in range(n):
                        if obst[e, ix, iy] != 0:
                            near, far = _box_distances(lo_x, hi_x, lo_y, hi_y, x0 + (ix + 0.5) * cell,
                                                       x0 + (iy + 0.5) * cell)
                            upper = min(upper, far)
                count = 0
                for ix in range(n):
                    for iy in range(n):
                        if obst[e, ix, iy] == 0:
                            continue
                        near, far = _box_distances(lo_x, hi_x, lo_y, hi_y, x0 + (ix + 0.5) * cell,
                                                   x0 + (iy + 0.5) * cell)
                        if near <= upper and near - radius < sdf_max:
                            if count < slots:
                                index[e, u, v, 1 + count] = (ix << shift) | iy
                            count += 1
                index[e, u, v, 0] = min(count, slots + 1)
