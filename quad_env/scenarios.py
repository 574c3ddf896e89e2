"""Scenario registry: where the goals are, and how they move.

A scenario is a small class registered by name. The environment calls, with arrays over all E swarms:

- ``allocate(num_envs)`` once: per-swarm scenario state (timers, curve parameters...) lives here;
- ``reset(selected, goal, center, rng)`` when swarms start an episode: write ``goal [E*N, 3]`` and the
  spawn ``center [E, 3]`` of every ``selected [E]`` swarm, drawing from the per-swarm streams ``rng``;
- ``update(goal, step_count, rng)`` before every control step, only if ``dynamic`` is True (moving goals).

All three work on whole batches through numba kernels, never per drone in Python. ``SCENARIOS`` lists the
registered names; ``make_scenario`` turns a name into an instance (unknown names list the valid ones).
"""
from __future__ import annotations

from typing import Dict, Tuple, Type

import numpy as np
from numba import njit

from quad_env.config import EnvConfig
from quad_env.rng import uniform

FORMATION_CENTER = (0.0, 0.0, 2.0)
SPAWN_HALF = 2.0  # drones spawn uniformly within +-2 m of the formation centre ...
SPAWN_MIN_Z = 0.75  # ... but no lower than this ...
SPAWN_MIN_SEP = 0.3  # ... and at least this far apart (m)

# Formation kinds (ints, for the kernels).
FORMATION_CIRCLE = 0  # horizontal circle, neighbours `spacing` apart
FORMATION_GRID = 1  # horizontal square-ish grid, `spacing` between rows and columns
FORMATION_NAMES = ("circle", "grid")
MAX_FORMATION_RADIUS = 2.0  # a circle wider than this falls back to the grid


@njit(cache=True)
def formation_offsets(kind, n, spacing, out):
    """Write ``n`` goal offsets ``out [n, 3]`` of a formation centred at the origin."""
    if kind == FORMATION_CIRCLE and n >= 2:
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

    def __init__(self, cfg: EnvConfig):
        if cfg.num_agents < self.min_agents:
            raise ValueError(f"scenario {self.name!r} needs env.num_agents >= {self.min_agents}, "
                             f"got {cfg.num_agents}")
        self.cfg = cfg
        self.num_agents = cfg.num_agents

    def allocate(self, num_envs: int) -> None:
        """Allocate per-swarm scenario state (none for static scenarios)."""
        self.num_envs = num_envs

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


SCENARIOS: Tuple[str, ...] = tuple(SCENARIO_REGISTRY)


def make_scenario(name: str, cfg: EnvConfig) -> Scenario:
    """Instance of the scenario called ``name``; unknown names raise ValueError listing the valid ones."""
    if name not in SCENARIO_REGISTRY:
        raise ValueError(f"unknown scenario {name!r}; valid: {sorted(SCENARIO_REGISTRY)}")
    return SCENARIO_REGISTRY[name](cfg)
