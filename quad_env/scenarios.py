"""Scenario registry: where the goals are, and how they move.

A scenario is a small class registered by name. The environment calls, with arrays over all E swarms:

- ``allocate(num_envs)`` once: per-swarm scenario state (timers, curve parameters...) lives here;
- ``reset(selected, goal, center, rng)`` when swarms start an episode: write ``goal [E*N, 3]`` and the
  spawn ``center [E, 3]`` of every ``selected [E]`` swarm, drawing from the per-swarm streams ``rng``
  (drones spawn in the box ``center +- spawn_half[e]``; the environment sets ``spawn_half`` to SPAWN_HALF
  before every reset, a scenario may change it);
- ``update(goal, step_count, rng)`` before every control step, only if ``dynamic`` is True (moving goals);
  ``step_count[e]`` is the number of control steps the swarm has taken, so the goal set here is the one
  of step ``step_count[e] + 1`` (time ``step_count * control_dt``). A discrete goal change (a jump, a swap,
  a reshuffle) sets ``jumped[e] = 1``: the success metric then starts afresh (the environment clears it).
  Continuous goal motion (pursuit curves, breathing formations) is not a jump.

Only the swarms with ``active[e]`` are updated (``mix`` runs several scenarios side by side, each on the
swarms that drew it; a replayed episode keeps its goals: ``set_active(selected, False)``). All work on
whole batches through numba kernels, never per drone in Python. ``SCENARIOS`` lists the registered names;
``make_scenario`` turns a name into an instance (unknown names list the valid ones).
"""
from __future__ import annotations

from typing import Dict, Tuple, Type

import numpy as np

from quad_env.jit_cache import njit  # numba's njit, cached under the sources' hash
from quad_env.config import EnvConfig
from quad_env.obstacles import OBSTACLE_CLEARANCE
from quad_env.rng import uniform

FORMATION_CENTER = (0.0, 0.0, 2.0)
SPAWN_HALF = 2.0  # drones spawn uniformly within +-2 m of the formation centre ...
SPAWN_MIN_Z = 0.75  # ... but no lower than this ...
SPAWN_MIN_SEP = 0.3  # ... and at least this far apart (m)

ROOM_MARGIN = 0.5  # goals stay this far inside the walls, floor and ceiling (m)
CHANGE_INTERVAL_S = (4.0, 6.0)  # dynamic scenarios change their goals every U(4, 6) s

# Formation kinds (ints, for the kernels). Every kind works for any N >= 1; neighbouring goals are
# `spacing` apart (the nearest-neighbour distance of the sphere).
FORMATION_CIRCLE = 0  # horizontal circle, neighbours `spacing` apart
FORMATION_GRID = 1  # horizontal square-ish grid, `spacing` between rows and columns
FORMATION_CIRCLE_XZ = 2  # vertical circle in the x-z plane
FORMATION_CIRCLE_YZ = 3  # vertical circle in the y-z plane
FORMATION_GRID_XZ = 4  # vertical grid in the x-z plane
FORMATION_GRID_YZ = 5  # vertical grid in the y-z plane
FORMATION_SPHERE = 6  # Fibonacci points on a sphere, scaled so the nearest pair is `spacing` apart
FORMATION_CUBE = 7  # cubic lattice, filled layer by layer from the bottom
FORMATION_NAMES = ("circle", "grid", "circle_xz", "circle_yz", "grid_xz", "grid_yz", "sphere", "cube")
NUM_FORMATIONS = len(FORMATION_NAMES)
MAX_FORMATION_RADIUS = 2.0  # a circle wider than this falls back to the grid


@njit(cache=True)
def _planar_offsets(circle, n, spacing, out):
    """Horizontal circle (``circle``; a grid if wider than MAX_FORMATION_RADIUS) or grid, z = 0."""
    if circle and n >= 2:
        radius = spacing / (2.0 * np.sin(np.pi / n))
        if radius <= MAX_FORMATION_RADIUS:
            for a in range(n):
                ang = 2.0 * np.pi * a / n
                out[a, 0] = radius * np.cos(ang)
                out[a, 1] = radius * np.sin(ang)
                out[a, 2] = 0.0
            return
    cols = int(np.ceil(np.sqrt(n)))
    rows = (n + cols - 1) // cols
    for a in range(n):
        r, c = a // cols, a % cols
        out[a, 0] = (c - 0.5 * (cols - 1)) * spacing
        out[a, 1] = (r - 0.5 * (rows - 1)) * spacing
        out[a, 2] = 0.0


@njit(cache=True)
def formation_offsets(kind, n, spacing, out):
    """Write ``n`` goal offsets ``out [n, 3]`` of a formation centred at the origin (kinds: FORMATION_*)."""
    if kind == FORMATION_SPHERE:
        _sphere_offsets(n, spacing, out)
    elif kind == FORMATION_CUBE:
        _cube_offsets(n, spacing, out)
    elif kind == FORMATION_CIRCLE or kind == FORMATION_GRID:
        _planar_offsets(kind == FORMATION_CIRCLE, n, spacing, out)
    else:  # a vertical circle or grid: the horizontal one turned up
        _planar_offsets(kind <= FORMATION_CIRCLE_YZ, n, spacing, out)
        in_xz = kind == FORMATION_CIRCLE_XZ or kind == FORMATION_GRID_XZ
        for a in range(n):
            u, v = out[a, 0], out[a, 1]
            out[a, 0] = u if in_xz else 0.0
            out[a, 1] = 0.0 if in_xz else u
            out[a, 2] = v

@njit(cache=True)
def _min_pair_distance(out, n):
    best = np.inf
    for a in range(n):
        for b in range(a + 1, n):
            d = np.sqrt((out[a, 0] - out[b, 0]) ** 2 + (out[a, 1] - out[b, 1]) ** 2 + (out[a, 2] - out[b, 2]) ** 2)
            best = min(best, d)
    return best


@njit(cache=True)
def _sphere_offsets(n, spacing, out):
    """Fibonacci sphere (near-uniform points), scaled so that the closest pair is ``spacing`` apart."""
    golden = np.pi * (3.0 - np.sqrt(5.0))
    for a in range(n):
        z = 1.0 - (2.0 * a + 1.0) / n
        r = np.sqrt(max(1.0 - z * z, 0.0))
        out[a, 0] = r * np.cos(golden * a)
        out[a, 1] = r * np.sin(golden * a)
        out[a, 2] = z
    if n == 1:
        out[0, 0], out[0, 1], out[0, 2] = 0.0, 0.0, 0.0
        return
    scale = spacing / _min_pair_distance(out, n)
    for a in range(n):
        for k in range(3):
            out[a, k] *= scale


@njit(cache=True)
def _cube_offsets(n, spacing, out):
    """c x c x c lattice (c = ceil(cbrt n)) filled layer by layer from the bottom, centred on the used part."""
    c = 1
    while c * c * c < n:
        c += 1
    layers = (n + c * c - 1) // (c * c)
    for a in range(n):
        layer, rest = a // (c * c), a % (c * c)
        out[a, 0] = (rest % c - 0.5 * (c - 1)) * spacing
        out[a, 1] = (rest // c - 0.5 * (c - 1)) * spacing
        out[a, 2] = (layer - 0.5 * (layers - 1)) * spacing


@njit(cache=True)
def place_formation(kind, n, spacing, cx, cy, cz, lo, hi, scratch, goal, first_row, center_out, e):
    """Goals of a formation in the room: offsets ``formation_offsets(kind, n, spacing)`` around the centre
    (cx, cy, cz), shrunk if the formation is larger than the box ``lo..hi`` [3] and the centre moved
    (the least) so that every goal lies in the box. Writes ``goal[first_row:first_row + n]`` and the
    centre used to ``center_out[e]``; returns the shrink factor (1 = none)."""
    formation_offsets(kind, n, spacing, scratch)
    shrink = 1.0
    for k in range(3):
        mn, mx = np.inf, -np.inf
        for a in range(n):
            mn = min(mn, scratch[a, k])
            mx = max(mx, scratch[a, k])
        if mx - mn > hi[k] - lo[k]:
            shrink = min(shrink, (hi[k] - lo[k]) / (mx - mn))
    c = np.array((cx, cy, cz))
    for k in range(3):
        mn, mx = np.inf, -np.inf
        for a in range(n):
            scratch[a, k] *= shrink
            mn = min(mn, scratch[a, k])
            mx = max(mx, scratch[a, k])
        c[k] = min(max(c[k], lo[k] - mn), hi[k] - mx)
        center_out[e, k] = c[k]
    for a in range(n):
        for k in range(3):
            goal[first_row + a, k] = c[k] + scratch[a, k]
    return shrink


@njit(cache=True, inline="always")
def _interval_steps(rng, e, lo_steps, hi_steps):
    """Steps until the next goal change: U(lo, hi) rounded."""
    return lo_steps + int(round((hi_steps - lo_steps) * uniform(rng, e)))


@njit(cache=True, inline="always")
def _random_kind(rng, e):
    return min(int(uniform(rng, e) * NUM_FORMATIONS), NUM_FORMATIONS - 1)


@njit(cache=True)
def _reset_same_goal(selected, goal, center, n_agents, cx, cy, cz):
    for e in range(selected.shape[0]):
        if selected[e]:
            center[e, 0], center[e, 1], center[e, 2] = cx, cy, cz
            for a in range(n_agents):
                i = e * n_agents + a
                goal[i, 0], goal[i, 1], goal[i, 2] = cx, cy, cz


@njit(cache=True)
def _reset_formation(selected, goal, center, rng, n_agents, cx, cy, cz, spacing_lo, spacing_hi):
    offsets = np.zeros((n_agents, 3), np.float64)
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        kind = FORMATION_CIRCLE if uniform(rng, e) < 0.5 else FORMATION_GRID
        spacing = spacing_lo + (spacing_hi - spacing_lo) * uniform(rng, e)
        formation_offsets(kind, n_agents, spacing, offsets)
        center[e, 0], center[e, 1], center[e, 2] = cx, cy, cz
        for a in range(n_agents):
            i = e * n_agents + a
            goal[i, 0] = cx + offsets[a, 0]
            goal[i, 1] = cy + offsets[a, 1]
            goal[i, 2] = cz + offsets[a, 2]


class Scenario:
    """Base class. Subclasses set ``name`` and implement ``reset`` (and ``update`` if ``dynamic``)."""

    name: str = ""
    min_agents: int = 1
    dynamic: bool = False  # True: ``update`` moves the goals every control step
    needs_obstacles: bool = False  # True: an environment running it needs env.obstacles (VecQuadEnv checks)

    def __init__(self, cfg: EnvConfig):
        if cfg.num_agents < self.min_agents:
            raise ValueError(f"scenario {self.name!r} needs env.num_agents >= {self.min_agents}, "
                             f"got {cfg.num_agents}")
        self.cfg = cfg
        self.num_agents = cfg.num_agents

    def allocate(self, num_envs: int) -> None:
        """Allocate per-swarm scenario state. Subclasses with state extend this (call super first)."""
        self.num_envs = num_envs
        self.active = np.ones(num_envs, np.bool_)  # swarms this scenario updates
        self.jumped = np.zeros(num_envs, np.uint8)  # 1: the goals jumped at this step (metrics restart)
        self.scratch = np.zeros((self.num_agents, 3), np.float64)  # formation offsets
        self.spawn_half = np.full((num_envs, 3), SPAWN_HALF)  # spawn box half-sizes per swarm (x, y, z)

    def set_active(self, selected: np.ndarray, flag: bool) -> None:
        """Switch the goal motion of the selected swarms on (fresh episodes) or off (replayed episodes)."""
        self.active[selected] = flag

    @property
    def dt(self) -> float:
        return self.cfg.control_dt

    @property
    def room_box(self):
        """(lo [3], hi [3]): where goals may lie, ROOM_MARGIN inside the room."""
        p = self.cfg.physics
        h = p.room_half_width - ROOM_MARGIN
        return np.array([-h, -h, ROOM_MARGIN]), np.array([h, h, p.room_height - ROOM_MARGIN])

    def interval_steps(self):
        """(lo, hi) control steps between goal changes."""
        return tuple(int(round(t / self.dt)) for t in CHANGE_INTERVAL_S)

    def reset(self, selected: np.ndarray, goal: np.ndarray, center: np.ndarray, rng: np.ndarray) -> None:
        raise NotImplementedError

    def update(self, goal: np.ndarray, step_count: np.ndarray, rng: np.ndarray) -> None:
        """Move the goals before a control step (dynamic scenarios only)."""

    def episode_name(self, env_index: int) -> str:
        """Name reported in the episode stats (a mixing scenario reports the one it drew)."""
        return self.name


SCENARIO_REGISTRY: Dict[str, Type[Scenario]] = {}


def register_scenario(cls: Type[Scenario]) -> Type[Scenario]:
    if not cls.name or cls.name in SCENARIO_REGISTRY:
        raise ValueError(f"scenario name {cls.name!r} is empty or already registered")
    SCENARIO_REGISTRY[cls.name] = cls
    return cls


@register_scenario
class StaticSameGoal(Scenario):
    """Every drone flies to the same fixed goal, the formation centre (0, 0, 2)."""

    name = "static_same_goal"

    def reset(self, selected, goal, center, rng):
        _reset_same_goal(selected, goal, center, self.num_agents, *FORMATION_CENTER)


@register_scenario
class StaticDiffGoal(Scenario):
    """Fixed goals in a formation around (0, 0, 2): a horizontal circle or grid (drawn per episode)
    with 0.25-0.5 m spacing. Circles wider than 2 m radius (large N) become grids."""

    name = "static_diff_goal"
    spacing = (0.25, 0.5)

    def reset(self, selected, goal, center, rng):
        _reset_formation(selected, goal, center, rng, self.num_agents, *FORMATION_CENTER, *self.spacing)


# ====================================================================== dynamic scenarios: kernels
@njit(cache=True)
def _reset_change_timer(selected, next_change, rng, lo_steps, hi_steps):
    for e in range(selected.shape[0]):
        if selected[e]:
            next_change[e] = _interval_steps(rng, e, lo_steps, hi_steps)


@njit(cache=True)
def _random_center(rng, e, cx, cy, cz):
    """A formation centre (cx, cy, cz) + (U(+-2), U(+-2), U(+-1)), at least 0.25 m high."""
    x = cx + 2.0 * (2.0 * uniform(rng, e) - 1.0)
    y = cy + 2.0 * (2.0 * uniform(rng, e) - 1.0)
    z = max(cz + (2.0 * uniform(rng, e) - 1.0), 0.25)
    return x, y, z


@njit(cache=True)
def _update_dynamic_same_goal(active, goal, step_count, rng, jumped, next_change, n_agents, cx, cy, cz,
                              lo_steps, hi_steps):
    for e in range(active.shape[0]):
        if not active[e] or step_count[e] < next_change[e]:
            continue
        x, y, z = _random_center(rng, e, cx, cy, cz)
        for a in range(n_agents):
            i = e * n_agents + a
            goal[i, 0], goal[i, 1], goal[i, 2] = x, y, z
        jumped[e] = 1
        next_change[e] += _interval_steps(rng, e, lo_steps, hi_steps)


@njit(cache=True)
def _random_formation(selected, goal, center, rng, scratch, n_agents, cx, cy, cz, random_center, spacing_lo,
                      spacing_hi, lo, hi):
    """A random formation kind and spacing U(lo, hi) per selected swarm, at (cx, cy, cz) or a random centre."""
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        x, y, z = cx, cy, cz
        if random_center:
            x, y, z = _random_center(rng, e, cx, cy, cz)
        kind = _random_kind(rng, e)
        spacing = spacing_lo + (spacing_hi - spacing_lo) * uniform(rng, e)
        place_formation(kind, n_agents, spacing, x, y, z, lo, hi, scratch, goal, e * n_agents, center, e)


@njit(cache=True)
def _update_dynamic_diff_goal(active, goal, step_count, rng, jumped, next_change, scratch, centers, n_agents,
                              cx, cy, cz, spacing_lo, spacing_hi, lo, hi, lo_steps, hi_steps):
    due = np.zeros(active.shape[0], np.bool_)
    for e in range(active.shape[0]):
        if active[e] and step_count[e] >= next_change[e]:
            due[e] = True
            jumped[e] = 1
    _random_formation(due, goal, centers, rng, scratch, n_agents, cx, cy, cz, True, spacing_lo, spacing_hi, lo, hi)
    for e in range(active.shape[0]):
        if due[e]:
            next_change[e] += _interval_steps(rng, e, lo_steps, hi_steps)


@njit(cache=True, inline="always")
def lissajous_point(t, omega, sign, cz):
    """The pursuit goal at time t: (-2 cos wt, 2 s sin 2wt, cz + sin 3wt); starts at (-2, 0, cz) and its
    speed is at most 5 w (at t = 0)."""
    return -2.0 * np.cos(omega * t), 2.0 * sign * np.sin(2.0 * omega * t), cz + np.sin(3.0 * omega * t)


@njit(cache=True)
def _reset_lissajous(selected, goal, center, rng, omega, sign, n_agents, omega_lo, omega_hi, cz):
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        omega[e] = omega_lo + (omega_hi - omega_lo) * uniform(rng, e)
        sign[e] = 1.0 if uniform(rng, e) < 0.5 else -1.0
        center[e, 0], center[e, 1], center[e, 2] = 0.0, 0.0, cz
        x, y, z = lissajous_point(0.0, omega[e], sign[e], cz)
        for a in range(n_agents):
            i = e * n_agents + a
            goal[i, 0], goal[i, 1], goal[i, 2] = x, y, z


@njit(cache=True)
def _update_lissajous(active, goal, step_count, omega, sign, n_agents, dt, cz):
    for e in range(active.shape[0]):
        if not active[e]:
            continue
        x, y, z = lissajous_point(step_count[e] * dt, omega[e], sign[e], cz)
        for a in range(n_agents):
            i = e * n_agents + a
            goal[i, 0], goal[i, 1], goal[i, 2] = x, y, z


@njit(cache=True)
def _plan_bezier(e, rng, ctrl, lo, hi, hop_lo, hop_hi):
    """New quadratic Bezier from ctrl[e, 0] (the current goal): end point a hop of U(hop_lo, hop_hi) m in a
    uniform random direction, inside the box lo..hi (20 tries, then clipped into it); middle control point
    the midpoint + U(+-1) m per axis, clipped. The curve stays in the box (convex hull)."""
    for _ in range(20):
        hop = hop_lo + (hop_hi - hop_lo) * uniform(rng, e)
        uz = 2.0 * uniform(rng, e) - 1.0
        phi = 2.0 * np.pi * uniform(rng, e)
        r = np.sqrt(1.0 - uz * uz)
        ok = True
        for k in range(3):
            u = r * np.cos(phi) if k == 0 else (r * np.sin(phi) if k == 1 else uz)
            ctrl[e, 2, k] = ctrl[e, 0, k] + hop * u
            ok = ok and lo[k] <= ctrl[e, 2, k] <= hi[k]
        if ok:
            break
    for k in range(3):
        ctrl[e, 2, k] = min(max(ctrl[e, 2, k], lo[k]), hi[k])
        mid = 0.5 * (ctrl[e, 0, k] + ctrl[e, 2, k]) + (2.0 * uniform(rng, e) - 1.0)
        ctrl[e, 1, k] = min(max(mid, lo[k]), hi[k])


@njit(cache=True)
def _reset_bezier(selected, goal, center, rng, ctrl, start, n_agents, cx, cy, cz, lo, hi, hop_lo, hop_hi):
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        center[e, 0], center[e, 1], center[e, 2] = cx, cy, cz
        ctrl[e, 0, 0], ctrl[e, 0, 1], ctrl[e, 0, 2] = cx, cy, cz
        start[e] = 0
        _plan_bezier(e, rng, ctrl, lo, hi, hop_lo, hop_hi)
        for a in range(n_agents):
            i = e * n_agents + a
            goal[i, 0], goal[i, 1], goal[i, 2] = cx, cy, cz


@njit(cache=True)
def _update_bezier(active, goal, step_count, rng, ctrl, start, n_agents, period_steps, lo, hi, hop_lo, hop_hi):
    for e in range(active.shape[0]):
        if not active[e]:
            continue
        if step_count[e] - start[e] >= period_steps:  # re-plan from the end of the current curve
            for k in range(3):
                ctrl[e, 0, k] = ctrl[e, 2, k]
            start[e] += period_steps
            _plan_bezier(e, rng, ctrl, lo, hi, hop_lo, hop_hi)
        s = (step_count[e] - start[e]) / period_steps
        w0, w1, w2 = (1.0 - s) * (1.0 - s), 2.0 * s * (1.0 - s), s * s
        x = w0 * ctrl[e, 0, 0] + w1 * ctrl[e, 1, 0] + w2 * ctrl[e, 2, 0]
        y = w0 * ctrl[e, 0, 1] + w1 * ctrl[e, 1, 1] + w2 * ctrl[e, 2, 1]
        z = w0 * ctrl[e, 0, 2] + w1 * ctrl[e, 1, 2] + w2 * ctrl[e, 2, 2]
        for a in range(n_agents):
            i = e * n_agents + a
            goal[i, 0], goal[i, 1], goal[i, 2] = x, y, z


@njit(cache=True)
def _reset_swarm_vs_swarm(selected, goal, center, rng, scratch, team_center, offsets, n_agents, cx, cy, cz,
                          sep_lo, sep_hi, spacing_lo, spacing_hi, lo, hi):
    """Team A = drones [0, N // 2), team B = the rest; each its own random formation, centres U(sep) apart
    along a random direction through (cx, cy, cz). ``offsets`` keep each drone's place in its formation."""
    n_a = n_agents // 2
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        sep = sep_lo + (sep_hi - sep_lo) * uniform(rng, e)
        uz = 2.0 * uniform(rng, e) - 1.0
        phi = 2.0 * np.pi * uniform(rng, e)
        r = np.sqrt(1.0 - uz * uz)
        ux, uy = r * np.cos(phi), r * np.sin(phi)
        for team in range(2):
            side = -0.5 if team == 0 else 0.5
            first = e * n_agents + (0 if team == 0 else n_a)
            count = n_a if team == 0 else n_agents - n_a
            kind = _random_kind(rng, e)
            spacing = spacing_lo + (spacing_hi - spacing_lo) * uniform(rng, e)
            place_formation(kind, count, spacing, cx + side * sep * ux, cy + side * sep * uy,
                            cz + side * sep * uz, lo, hi, scratch, goal, first, team_center[team], e)
            for i in range(first, first + count):
                for k in range(3):
                    offsets[i, k] = goal[i, k] - team_center[team, e, k]
        center[e, 0], center[e, 1], center[e, 2] = cx, cy, cz


@njit(cache=True)
def _update_swarm_vs_swarm(active, goal, step_count, rng, jumped, next_change, team_center, offsets, n_agents,
                           lo, hi, lo_steps, hi_steps):
    """The two teams swap formation centres (each keeps its shape, moved back into the room if needed)."""
    n_a = n_agents // 2
    for e in range(active.shape[0]):
        if not active[e] or step_count[e] < next_change[e]:
            continue
        for k in range(3):
            t = team_center[0, e, k]
            team_center[0, e, k] = team_center[1, e, k]
            team_center[1, e, k] = t
        for a in range(n_agents):
            i = e * n_agents + a
            team = 0 if a < n_a else 1
            for k in range(3):
                goal[i, k] = min(max(team_center[team, e, k] + offsets[i, k], lo[k]), hi[k])
        jumped[e] = 1
        next_change[e] += _interval_steps(rng, e, lo_steps, hi_steps)


@njit(cache=True)
def _update_swap_goals(active, goal, step_count, rng, jumped, next_change, n_agents, lo_steps, hi_steps):
    """Reshuffle which drone flies to which goal of the formation (Fisher-Yates over the swarm's rows)."""
    for e in range(active.shape[0]):
        if not active[e] or step_count[e] < next_change[e]:
            continue
        base = e * n_agents
        for a in range(n_agents - 1, 0, -1):
            b = min(int(uniform(rng, e) * (a + 1)), a)
            for k in range(3):
                t = goal[base + a, k]
                goal[base + a, k] = goal[base + b, k]
                goal[base + b, k] = t
        jumped[e] = 1
        next_change[e] += _interval_steps(rng, e, lo_steps, hi_steps)


@njit(cache=True)
def _reset_breathing(selected, goal, center, rng, scratch, offsets, size_lo_frac, period, n_agents, cx, cy, cz,
                     spacing_lo, spacing_hi, frac_lo, frac_hi, period_lo, period_hi, lo, hi):
    """A random formation at its largest spacing U(spacing) (``offsets`` from the centre); it breathes down
    to a fraction U(frac) of that size with a period U(period) steps."""
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        kind = _random_kind(rng, e)
        spacing = spacing_lo + (spacing_hi - spacing_lo) * uniform(rng, e)
        size_lo_frac[e] = frac_lo + (frac_hi - frac_lo) * uniform(rng, e)
        period[e] = period_lo + (period_hi - period_lo) * uniform(rng, e)
        place_formation(kind, n_agents, spacing, cx, cy, cz, lo, hi, scratch, goal, e * n_agents, center, e)
        for a in range(n_agents):
            i = e * n_agents + a
            for k in range(3):
                offsets[i, k] = goal[i, k] - center[e, k]


@njit(cache=True, inline="always")
def breathing_scale(step, size_lo_frac, period):
    """Formation size (fraction of the largest) at a step: 1 at the start, size_lo_frac half a period later."""
    return 1.0 - (1.0 - size_lo_frac) * 0.5 * (1.0 - np.cos(2.0 * np.pi * step / period))


@njit(cache=True)
def _update_breathing(active, goal, step_count, centers, offsets, size_lo_frac, period, n_agents):
    for e in range(active.shape[0]):
        if not active[e]:
            continue
        scale = breathing_scale(step_count[e], size_lo_frac[e], period[e])
        for a in range(n_agents):
            i = e * n_agents + a
            for k in range(3):
                goal[i, k] = centers[e, k] + scale * offsets[i, k]


@njit(cache=True)
def _draw_choice(selected, rng, num_choices, choice):
    for e in range(selected.shape[0]):
        if selected[e]:
            choice[e] = min(int(uniform(rng, e) * num_choices), num_choices - 1)


# ====================================================================== dynamic scenarios: classes
class _TimedScenario(Scenario):
    """A scenario whose goals change every U(4, 6) s (``next_change[e]``, in control steps)."""

    dynamic = True

    def allocate(self, num_envs):
        super().allocate(num_envs)
        self.next_change = np.zeros(num_envs, np.int64)

    def _reset_timer(self, selected, rng):
        _reset_change_timer(selected, self.next_change, rng, *self.interval_steps())


@register_scenario
class DynamicSameGoal(_TimedScenario):
    """One shared goal, first at (0, 0, 2); every U(4, 6) s it jumps to (U(+-2), U(+-2), 2 + U(+-1))."""

    name = "dynamic_same_goal"

    def reset(self, selected, goal, center, rng):
        _reset_same_goal(selected, goal, center, self.num_agents, *FORMATION_CENTER)
        self._reset_timer(selected, rng)

    def update(self, goal, step_count, rng):
        _update_dynamic_same_goal(self.active, goal, step_count, rng, self.jumped, self.next_change,
                                  self.num_agents, *FORMATION_CENTER, *self.interval_steps())


@register_scenario
class DynamicDiffGoal(_TimedScenario):
    """A random formation (any of FORMATION_NAMES, spacing U(0.25, 0.5) m) around (0, 0, 2); every
    U(4, 6) s a new random centre (as dynamic_same_goal), formation kind and spacing."""

    name = "dynamic_diff_goal"
    spacing = (0.25, 0.5)

    def allocate(self, num_envs):
        super().allocate(num_envs)
        self.centers = np.zeros((num_envs, 3))

    def reset(self, selected, goal, center, rng):
        _random_formation(selected, goal, center, rng, self.scratch, self.num_agents, *FORMATION_CENTER, False,
                          *self.spacing, *self.room_box)
        self._reset_timer(selected, rng)

    def update(self, goal, step_count, rng):
        _update_dynamic_diff_goal(self.active, goal, step_count, rng, self.jumped, self.next_change,
                                  self.scratch, self.centers, self.num_agents, *FORMATION_CENTER, *self.spacing,
                                  *self.room_box, *self.interval_steps())


@register_scenario
class Lissajous3D(Scenario):
    """Evasion-pursuit: one shared goal on the 3-D Lissajous curve (-2 cos wt, +-2 sin 2wt, 2 + sin 3wt),
    starting at (-2, 0, 2); w ~ U(0.3, 0.6) rad/s per episode (top speed 5 w: 1.5-3 m/s), the direction
    of the y lobe random."""

    name = "ep_lissajous3D"
    dynamic = True
    omega = (0.3, 0.6)

    def allocate(self, num_envs):
        super().allocate(num_envs)
        self.omega_e = np.zeros(num_envs)
        self.sign = np.ones(num_envs)

    def reset(self, selected, goal, center, rng):
        _reset_lissajous(selected, goal, center, rng, self.omega_e, self.sign, self.num_agents, *self.omega,
                         FORMATION_CENTER[2])

    def update(self, goal, step_count, rng):
        _update_lissajous(self.active, goal, step_count, self.omega_e, self.sign, self.num_agents, self.dt,
                          FORMATION_CENTER[2])


@register_scenario
class RandomBezier(Scenario):
    """Evasion-pursuit: one shared goal, starting at (0, 0, 2), follows random quadratic Bezier curves,
    each lasting 5 s and ending a 5-10 m hop away (the next starts where it ended); curves stay
    ROOM_MARGIN inside the room."""

    name = "ep_rand_bezier"
    dynamic = True
    period_s = 5.0
    hop = (5.0, 10.0)

    def allocate(self, num_envs):
        super().allocate(num_envs)
        self.ctrl = np.zeros((num_envs, 3, 3))  # [E, control point, xyz]
        self.start = np.zeros(num_envs, np.int64)  # step at which the current curve started

    def reset(self, selected, goal, center, rng):
        _reset_bezier(selected, goal, center, rng, self.ctrl, self.start, self.num_agents, *FORMATION_CENTER,
                      *self.room_box, *self.hop)

    def update(self, goal, step_count, rng):
        _update_bezier(self.active, goal, step_count, rng, self.ctrl, self.start, self.num_agents,
                       int(round(self.period_s / self.dt)), *self.room_box, *self.hop)


@register_scenario
class SwarmVsSwarm(_TimedScenario):
    """Two teams (drones [0, N//2) and the rest), each in its own random formation (spacing U(0.25, 0.5) m)
    whose centres are U(0.5, 2) m apart along a random direction through (0, 0, 2); every U(4, 6) s the
    teams swap centres, flying through each other. Needs N >= 2."""

    name = "swarm_vs_swarm"
    min_agents = 2
    separation = (0.5, 2.0)
    spacing = (0.25, 0.5)

    def allocate(self, num_envs):
        super().allocate(num_envs)
        self.team_center = np.zeros((2, num_envs, 3))
        self.offsets = np.zeros((num_envs * self.num_agents, 3))

    def reset(self, selected, goal, center, rng):
        _reset_swarm_vs_swarm(selected, goal, center, rng, self.scratch, self.team_center, self.offsets,
                              self.num_agents, *FORMATION_CENTER, *self.separation, *self.spacing,
                              *self.room_box)
        self._reset_timer(selected, rng)

    def update(self, goal, step_count, rng):
        _update_swarm_vs_swarm(self.active, goal, step_count, rng, self.jumped, self.next_change, self.team_center,
                               self.offsets, self.num_agents, *self.room_box, *self.interval_steps())


@register_scenario
class SwapGoals(_TimedScenario):
    """A random formation (spacing U(0.4, 0.8) m) around (0, 0, 2); every U(4, 6) s the goals are dealt to
    the drones anew (a uniform random permutation)."""

    name = "swap_goals"
    spacing = (0.4, 0.8)

    def reset(self, selected, goal, center, rng):
        _random_formation(selected, goal, center, rng, self.scratch, self.num_agents, *FORMATION_CENTER, False,
                          *self.spacing, *self.room_box)
        self._reset_timer(selected, rng)

    def update(self, goal, step_count, rng):
        _update_swap_goals(self.active, goal, step_count, rng, self.jumped, self.next_change, self.num_agents,
                           *self.interval_steps())


@register_scenario
class DynamicFormations(Scenario):
    """A random formation around (0, 0, 2) that breathes: its spacing starts at U(0.5, 1.0) m and shrinks
    smoothly (cosine) to a fraction U(0.3, 0.6) of it and back, with a period of U(4, 6) s."""

    name = "dynamic_formations"
    dynamic = True
    spacing = (0.5, 1.0)
    size_fraction = (0.3, 0.6)

    def allocate(self, num_envs):
        super().allocate(num_envs)
        self.centers = np.zeros((num_envs, 3))
        self.offsets = np.zeros((num_envs * self.num_agents, 3))
        self.size_lo = np.ones(num_envs)
        self.period = np.ones(num_envs)

    def reset(self, selected, goal, center, rng):
        _reset_breathing(selected, goal, self.centers, rng, self.scratch, self.offsets, self.size_lo, self.period,
                         self.num_agents, *FORMATION_CENTER, *self.spacing, *self.size_fraction,
                         *self.interval_steps(), *self.room_box)
        center[selected] = self.centers[selected]

    def update(self, goal, step_count, rng):
        _update_breathing(self.active, goal, step_count, self.centers, self.offsets, self.size_lo, self.period,
                          self.num_agents)


# ====================================================================== obstacle scenarios
@njit(cache=True, inline="always")
def _side_to_world(side, u, v):
    """(along, across) coordinates of a course seen from ``side`` (0-3, quarter turns) -> world (x, y)."""
    if side == 0:
        return u, v
    if side == 1:
        return -v, u
    if side == 2:
        return -u, -v
    return v, -u


@njit(cache=True)
def _reset_obstacle_course(selected, goal, center, spawn_half, rng, n_agents, same_goal, along_half, spawn_lo,
                           spawn_hi, goal_lo, goal_hi, cz, goal_z_half, min_sep):
    """Spawn box on one side of the obstacle grid, goals on the opposite side, the side drawn per episode.

    In course coordinates (along, across), turned to the world by a random quarter turn: drones spawn with
    across in [-spawn_hi, -spawn_lo] and along in +-along_half; goals lie at across in [goal_lo, goal_hi],
    along in +-along_half, z in cz +- goal_z_half: one shared goal in the middle of that band
    (``same_goal``) or one uniform goal per drone, at least ``min_sep`` apart (100 tries, then accepted).
    """
    for e in range(selected.shape[0]):
        if not selected[e]:
            continue
        side = min(int(4.0 * uniform(rng, e)), 3)
        x, y = _side_to_world(side, 0.0, -0.5 * (spawn_lo + spawn_hi))
        center[e, 0], center[e, 1], center[e, 2] = x, y, cz
        hu, hv = along_half, 0.5 * (spawn_hi - spawn_lo)
        spawn_half[e, 0] = hu if side % 2 == 0 else hv
        spawn_half[e, 1] = hv if side % 2 == 0 else hu
        base = e * n_agents
        if same_goal:
            gx, gy = _side_to_world(side, 0.0, 0.5 * (goal_lo + goal_hi))
            for a in range(n_agents):
                goal[base + a, 0], goal[base + a, 1], goal[base + a, 2] = gx, gy, cz
            continue
        for a in range(n_agents):
            gx, gy, gz = 0.0, 0.0, cz
            for _ in range(100):
                u = along_half * (2.0 * uniform(rng, e) - 1.0)
                v = goal_lo + (goal_hi - goal_lo) * uniform(rng, e)
                gz = cz + goal_z_half * (2.0 * uniform(rng, e) - 1.0)
                gx, gy = _side_to_world(side, u, v)
                ok = True
                for b in range(a):
                    d2 = (goal[base + b, 0] - gx) ** 2 + (goal[base + b, 1] - gy) ** 2 + (goal[base + b, 2] - gz) ** 2
                    if d2 < min_sep * min_sep:
                        ok = False
                        break
                if ok:
                    break
            goal[base + a, 0], goal[base + a, 1], goal[base + a, 2] = gx, gy, gz


class _ObstacleCourse(Scenario):
    """Drones start on one side of the obstacle grid and fly through it to goals on the opposite side (the
    side is drawn per episode among the four). Spawns and goals lie in the free band between the grid and
    the walls, so no cylinder has to yield; goals are static."""

    needs_obstacles = True
    same_goal = False
    goal_z_half = 1.0  # goals at z in 2 +- this (o_random)
    wall_gap = 0.1  # spawn points stay this far from the walls (goals: ROOM_MARGIN)

    def __init__(self, cfg):
        super().__init__(cfg)
        half_grid = 0.5 * cfg.obstacle_grid_cells * cfg.obstacle_cell_size
        room = cfg.physics.room_half_width
        edge_surface = half_grid - 0.5 * cfg.obstacle_cell_size + 0.5 * cfg.obstacle_diameter
        self.band_lo = max(half_grid, edge_surface + OBSTACLE_CLEARANCE) + 0.1  # clear of the outer row
        self.goal_hi = room - ROOM_MARGIN
        self.spawn_hi = room - self.wall_gap
        self.along_half = half_grid - 0.5 * cfg.obstacle_cell_size  # the span of the cylinder axes
        if self.goal_hi - self.band_lo < 0.2 or self.along_half <= 0:
            raise ValueError(
                f"scenario {self.name!r} needs a free band of >= 0.2 m between the obstacle grid and the walls "
                f"(minus {ROOM_MARGIN} m): lower env.obstacle_grid_cells * env.obstacle_cell_size "
                f"({cfg.obstacle_grid_cells} x {cfg.obstacle_cell_size} m) or raise env.physics.room_half_width "
                f"({room} m)")

    def reset(self, selected, goal, center, rng):
        _reset_obstacle_course(selected, goal, center, self.spawn_half, rng, self.num_agents, self.same_goal,
                               self.along_half, self.band_lo, self.spawn_hi, self.band_lo, self.goal_hi,
                               FORMATION_CENTER[2], self.goal_z_half, SPAWN_MIN_SEP)


@register_scenario
class ObstacleRandom(_ObstacleCourse):
    """Obstacle course: every drone has its own random static goal (at least 0.3 m from the others) on the
    far side of the obstacle grid, at z in [1, 3] m."""

    name = "o_random"


@register_scenario
class ObstacleStaticSameGoal(_ObstacleCourse):
    """Obstacle course: one shared static goal at z = 2 m in the middle of the far side of the obstacle grid."""

    name = "o_static_same_goal"
    same_goal = True


MIX_SCENARIOS = ("static_same_goal", "static_diff_goal", "dynamic_same_goal", "dynamic_diff_goal",
                 "ep_lissajous3D", "ep_rand_bezier", "swarm_vs_swarm", "swap_goals", "dynamic_formations")
MIX_OBSTACLE_SCENARIOS = ("o_random", "o_static_same_goal")  # joined to the mix when obstacles are on


@register_scenario
class Mix(Scenario):
    """Each episode of each swarm draws one of MIX_SCENARIOS uniformly (swarm_vs_swarm only if N >= 2), and
    with ``env.obstacles`` also MIX_OBSTACLE_SCENARIOS (every episode then has cylinders in the room);
    the episode stats name the scenario drawn."""

    name = "mix"
    dynamic = True

    def __init__(self, cfg):
        super().__init__(cfg)
        candidates = MIX_SCENARIOS + (MIX_OBSTACLE_SCENARIOS if cfg.obstacles else ())
        names = [n for n in candidates if SCENARIO_REGISTRY[n].min_agents <= cfg.num_agents]
        self.names = tuple(names)
        self.members = [SCENARIO_REGISTRY[n](cfg) for n in names]

    def allocate(self, num_envs):
        super().allocate(num_envs)
        self.choice = np.zeros(num_envs, np.int64)
        for m in self.members:
            m.allocate(num_envs)
            m.jumped = self.jumped  # one flag array shared by all (each swarm runs one member)
            m.spawn_half = self.spawn_half  # ... and so is the spawn box

    def set_active(self, selected, flag):
        super().set_active(selected, flag)
        if not flag:  # (a fresh episode activates the member it draws, in ``reset``)
            for m in self.members:
                m.active[selected] = False

    def reset(self, selected, goal, center, rng):
        _draw_choice(selected, rng, len(self.members), self.choice)
        for k, m in enumerate(self.members):
            mine = self.choice == k
            m.active[selected] = mine[selected]
            if (mine & selected).any():
                m.reset(selected & mine, goal, center, rng)

    def update(self, goal, step_count, rng):
        for m in self.members:
            if m.dynamic:
                m.update(goal, step_count, rng)

    def episode_name(self, env_index):
        return self.names[self.choice[env_index]]


SCENARIOS: Tuple[str, ...] = tuple(SCENARIO_REGISTRY)


def make_scenario(name: str, cfg: EnvConfig) -> Scenario:
    """Instance of the scenario called ``name``; unknown names raise ValueError listing the valid ones."""
    if name not in SCENARIO_REGISTRY:
        raise ValueError(f"unknown scenario {name!r}; valid: {sorted(SCENARIO_REGISTRY)}")
    return SCENARIO_REGISTRY[name](cfg)
