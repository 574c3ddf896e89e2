"""A scripted reference for the quality goal: is Dist <= 0.45 m, Col <= 0.1, Suc >= 95 % reachable at all?

    python -m benchmarks.scripted_ring                          # radii 0, 0.25, 0.35, 0.45 m; 50 episodes
    python -m benchmarks.scripted_ring --radii 0.35 --episodes 20

No learning: the hand-written controller (``quad_env.controller.GoalSeekingController``, true state) flies
each drone of a ``static_same_goal`` swarm to its own slot on a horizontal ring of radius r around the shared
goal, with no collision avoidance on the way. It flies in the same evaluation environment and on the same
seeded episodes as ``swarm_appo.evaluate`` flies a Table 1 checkpoint (``configs/table1/recipe.yaml``, the
training aids off), and the cells are the tables' metrics (``swarm_appo.eval_tables.METRICS``). r = 0 sends every
drone to the goal point itself. Appended to benchmarks/RESULTS.md with the command, commit and machine.
"""
from __future__ import annotations

import argparse
import datetime
from typing import Dict, Sequence

import numpy as np

from benchmarks.common import load_average, publish, section_header

COLUMNS = ("rew", "dist", "col", "cold", "suc")


def ring_offsets(num_agents: int, radius: float) -> np.ndarray:
    """[N, 3] slot of each drone on a horizontal ring of ``radius`` around the goal, evenly spaced."""
    angles = 2 * np.pi * np.arange(num_agents) / num_agents
    return np.stack([radius * np.cos(angles), radius * np.sin(angles), np.zeros(num_agents)], axis=1)


def fly_ring(env_cfg, radius: float, episodes: int, seed: int) -> Dict[str, float]:
    """Episode means of the table metrics for the controller flying to the ring of ``radius``."""
    from quad_env import VecQuadEnv
    from quad_env.controller import GoalSeekingController
    from swarm_appo.eval_tables import METRICS

    env = VecQuadEnv(env_cfg, num_envs=episodes, seed=seed, auto_reset=False)
    env.reset()
    controller = GoalSeekingController(env_cfg)
    offset = np.tile(ring_offsets(env_cfg.num_agents, radius), (episodes, 1))
    for _ in range(env_cfg.episode_steps):
        state = env.get_state()
        state.goal = state.goal + offset  # the controller's target; the env scores the shared goal
        _, _, term, trunc = env.step(controller(state))
        if (term | trunc).all():
            break
    stats = env.pop_episode_stats()
    return {k: float(np.mean([METRICS[k].value(e) for e in stats])) * METRICS[k].scale for k in COLUMNS}


def main(argv: Sequence[str] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--radii", default="0,0.25,0.35,0.45", help="ring radii in metres, comma-separated")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--config", default="configs/table1/recipe.yaml", help="the training config whose "
                   "evaluation environment is flown")
    p.add_argument("--no-append", action="store_true")
    args = p.parse_args(argv)
    from swarm_appo.config import load_config
    from swarm_appo.eval_tables import METRICS
    from swarm_appo.evaluation import default_eval_seed, evaluation_env

    try:
        radii = [float(r) for r in args.radii.split(",")]
    except ValueError:
        p.error(f"--radii: comma-separated numbers in metres, got {args.radii!r}")
    if any(not r >= 0 for r in radii):
        p.error(f"--radii: radii must be >= 0, got {args.radii!r}")
    cfg = load_config(args.config, [])
    env_cfg = evaluation_env(cfg.env)
    seed = default_eval_seed(cfg.runner.seed)
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    rows = []
    for radius in radii:
        m = fly_ring(env_cfg, radius, args.episodes, seed)
        rows.append(f"| scripted ring r = {radius:.2f} m | " + " | ".join(f"{m[k]:.2f}" for k in COLUMNS) + " |")
        print(rows[-1], flush=True)
    header = " | ".join(METRICS[k].column for k in COLUMNS)
    section = "\n".join([
        *section_header("scripted_ring", started, argv, ["quad_env"], load_before),
        f"- {env_cfg.scenario}, N = {env_cfg.num_agents}, {args.episodes} episodes (seed {seed}, the episodes "
        f"`swarm_appo.evaluate` flies for a seed-{cfg.runner.seed} run of `{args.config}`), the training aids off; "
        "no learning: the hand-written controller (true state) flies each drone to its own slot on a horizontal "
        "ring around the shared goal, without avoidance on the way",
        "", f"| policy | {header} |", "|---|" + "---:|" * len(COLUMNS), *rows])
    publish(section, not args.no_append)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
