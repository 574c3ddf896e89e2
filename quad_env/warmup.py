"""Compile the simulator's kernels ahead of use, one process per simulator dtype, into the keyed numba cache.

Every process that steps an environment first compiles (or loads from ``quad_env.jit_cache``'s folder) the
kernels for the argument types it uses. With a cold cache, processes that start together (pytest-xdist
workers, rollout workers) each compile the same kernels at the same moment: the work is repeated, not shared.
``python -m quad_env.warmup --jobs 2`` compiles them once, the float64 and the float32 simulator in two
processes side by side, so later processes only load them (about 1 s instead of 20-30 s per dtype).

What is warmed: every scenario (``mix``, with and without obstacles), collision replay, floor respawn, the
step/simulate/observe entry points with float32 and float64 actions, and the observation of fine obstacle grids
(a uint16 cell index). A kernel a variant does not reach is still compiled on first use, as before: warming is an
optimisation, never a requirement.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from typing import List, Sequence

import numpy as np

from quad_env import config
from quad_env.config import EnvConfig

# the simulator's dtypes (quad_env.config), the default first: it is the larger job
SIM_DTYPES = tuple(sorted(config.SIM_DTYPES, key=lambda d: d != EnvConfig.sim_dtype))


def variants(sim_dtype: str) -> List[EnvConfig]:
    """The environment configs warmed for ``sim_dtype``: float64 (the default) with every scenario of ``mix``,
    with and without obstacles; float32 with one scenario (the scenario kernels' float32 versions are rarely
    used and compile on first use)."""
    short = dict(num_agents=2, num_neighbors=1, sim_dtype=sim_dtype, replay_prob=0.5, episode_duration=0.05)
    if sim_dtype == "float32":
        return [EnvConfig(scenario="static_same_goal", respawn_on_floor=True, **short)]
    return [EnvConfig(scenario="mix", respawn_on_floor=True, **short),
            EnvConfig(scenario="mix", obstacles=True, **short)]


FINE_OBSTACLE_GRID = EnvConfig(num_agents=2, num_neighbors=1, obstacles=True, obstacle_grid_cells=18,
                               obstacle_cell_size=0.5, obstacle_diameter=0.3)


def warm(sim_dtype: str) -> None:
    """Compile (or load) the kernels of ``variants(sim_dtype)``, in this process: reset, step with float32 and
    float64 actions past the episode's end (auto reset, replay), a floor contact (respawn), observe, simulate."""
    from quad_env.vec_env import VecQuadEnv

    for cfg in variants(sim_dtype):
        env = VecQuadEnv(cfg.validate(), num_envs=48, seed=0)  # 48 swarms: the first reset draws every mix member
        mid = np.zeros((env.num_drones, 4))  # half thrust: the values do not matter, the types do
        for actions in (mid.astype(np.float32), mid):
            for _ in range(cfg.episode_steps + 1):
                env.step(actions)
        if cfg.respawn_on_floor:
            pos = env.get_state().pos.copy()
            pos[0, 2] = 0.0
            env.set_state(pos=pos)
            env.step(mid)
        env.observe()
        env.simulate(mid)
        env.pop_episode_stats()
    if sim_dtype == "float32":
        # The float32 job is the shorter one (~22 s against ~30 s, one core each): it also compiles the float64
        # observation kernel of fine obstacle grids (more than 16 cells: a uint16 cell index); their step kernel
        # compiles on first use.
        VecQuadEnv(FINE_OBSTACLE_GRID.validate(), num_envs=1, seed=0).observe()


def warm_in_parallel(dtypes: Sequence[str] = SIM_DTYPES, jobs: int = 2) -> List[int]:
    """Warm each dtype in its own Python process, ``jobs`` at a time; returns the processes' exit codes."""
    unknown = [d for d in dtypes if d not in SIM_DTYPES]
    if unknown:
        raise ValueError(f"unknown sim dtype(s) {unknown}; valid: {list(SIM_DTYPES)}")
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    codes: List[int] = []
    pending = list(dtypes)
    while pending:
        batch, pending = pending[:jobs], pending[jobs:]
        procs = [subprocess.Popen([sys.executable, "-m", "quad_env.warmup", "--dtypes", d, "--jobs", "1"])
                 for d in batch]
        codes += [p.wait() for p in procs]
    return codes


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dtypes", default=",".join(SIM_DTYPES),
                        help=f"comma-separated simulator dtypes to warm (default: {','.join(SIM_DTYPES)})")
    parser.add_argument("--jobs", type=int, default=2, help="processes side by side (default: 2)")
    args = parser.parse_args(argv)
    dtypes = [d.strip() for d in args.dtypes.split(",") if d.strip()]
    start = time.perf_counter()
    if args.jobs == 1 and len(dtypes) == 1:
        if dtypes[0] not in SIM_DTYPES:
            parser.error(f"unknown sim dtype {dtypes[0]!r}; valid: {list(SIM_DTYPES)}")
        warm(dtypes[0])
        return 0
    try:
        codes = warm_in_parallel(dtypes, args.jobs)
    except ValueError as e:
        parser.error(str(e))
    print(f"quad_env.warmup: {','.join(dtypes)} in {time.perf_counter() - start:.1f} s (exit codes {codes})")
    return max(codes, default=0)


if __name__ == "__main__":
    sys.exit(main())
